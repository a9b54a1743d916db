//! Screened Poisson reconstruction, L2: the exact minimiser of
//! `||D_x I - dx||^2 + ||D_y I - dy||^2 + alpha^2 ||I - I_b||^2`, per channel.
//!
//! The normal equations `(alpha^2 + D^T D) I = alpha^2 I_b + D^T g` are solved exactly by the
//! DCT (see `super::dct`): two 2-D transforms and a division, O(n log n). Gradient-domain path
//! tracing's reference solver runs 50 unpreconditioned CG steps instead, which stops short of
//! this minimiser; we solve it exactly.

use super::dct::DctPoisson;
use super::ops::{grad_adjoint, Dims};
use super::param::{Param, Params, Range};
use super::prior::{on_prior_memory, DataTerm, OnPrior, Scratch, DATA_DOC, PRIOR_ALPHA_DOC};
use super::{bytes_for, Method, Reconstructor, Register, MIB};
use crate::context::Context;
use crate::error::Result;
use crate::frame::Frame;
use crate::image::{try_vec, Image};
use crate::progress::Progress;
use crate::report::Report;

/// Settings of the L2 screened Poisson solve; its parameters are declared in its table
/// ([`param`](super::param)), the one place their names, ranges and meanings are written.
#[derive(Clone, Copy, Debug, PartialEq)]
#[non_exhaustive]
pub struct PoissonL2Config {
    /// Weight of the data term (see the table).
    pub alpha: f32,
    /// What the data term anchors to: the base image or the prior.
    pub data: DataTerm,
    /// Weight of the data term when it is the prior.
    pub prior_alpha: f32,
    /// OIDN's scratch memory when it computes the prior: lowered by a memory limit
    /// ([`Register::fit_memory`]), not a parameter.
    pub(crate) scratch: Scratch,
}

impl Default for PoissonL2Config {
    fn default() -> Self {
        PoissonL2Config {
            alpha: DEFAULT_ALPHA,
            data: DataTerm::Colour,
            prior_alpha: DEFAULT_PRIOR_ALPHA_L2,
            scratch: Scratch::default(),
        }
    }
}

/// `prior_alpha` of L2, chosen on the validation split (docs/benchmarks.md, "The prior"): L2
/// cannot tell the gradients' detail from their noise, so it must lean on the prior. At 10 it
/// is 0.98-1.00x OIDN alone (geometric mean per spp) and at worst 1.12x on a frame; at
/// 3 the worst frame is 10x. Use L1's preset `prior`, which can.
pub(crate) const DEFAULT_PRIOR_ALPHA_L2: f32 = 10.0;

/// Gradient-domain path tracing's data weight.
pub(crate) const DEFAULT_ALPHA: f32 = 0.2;

/// The accepted `alpha` for L2 (0 is pure Poisson) and, open at 0, for L1.
pub(crate) const ALPHA_RANGE: Range = Range::closed(0.0, 1e4);

impl Params for PoissonL2Config {
    const TABLE: &'static [Param<Self>] = &[
        Param::float(
            "alpha",
            ALPHA_RANGE,
            "Weight of the data term: residual rows are alpha (I - I_b); 0 is pure Poisson \
             with the base image's mean",
            |c| c.alpha,
            |c, v| c.alpha = v,
        ),
        Param::choice(
            "data",
            DataTerm::NAMES,
            DATA_DOC,
            |c| c.data.index(),
            |c, v| c.data = DataTerm::ALL[v],
        ),
        Param::float(
            "prior_alpha",
            ALPHA_RANGE,
            PRIOR_ALPHA_DOC,
            |c| c.prior_alpha,
            |c, v| c.prior_alpha = v,
        ),
    ];
}

impl Register for PoissonL2Config {
    const PRIOR_SWEEP: &'static [&'static str] = &["data=prior"];

    fn plan(
        &self,
        context: &Context,
        width: usize,
        height: usize,
    ) -> Result<Box<dyn Reconstructor>> {
        Ok(match self.data {
            DataTerm::Colour => Box::new(PoissonL2::new(*self, width, height)?),
            DataTerm::Prior => {
                let anchored = PoissonL2Config {
                    alpha: self.prior_alpha,
                    ..*self
                };
                let inner = Box::new(PoissonL2::new(anchored, width, height)?);
                Box::new(OnPrior::new(context, width, height, self.scratch, inner)?)
            }
        })
    }

    fn memory_estimate(&self, width: usize, height: usize) -> u64 {
        // Eigenvalues (1 plane), right-hand side and transposed planes (3 + 3), the output
        // (3): 10 f32 planes, 40 B a pixel (the DCT plans and per-thread scratch are rows);
        // measured 40.4, 40.2 and 40.1 B a pixel at 256 x 192, 640 x 360 and 1280 x 720
        // (tests/memory.rs, a counting allocator), so 44 and 1 MiB.
        let own = bytes_for(width, height, 44, MIB);
        match self.data {
            DataTerm::Colour => own,
            DataTerm::Prior => own.saturating_add(on_prior_memory(width, height, self.scratch)),
        }
    }

    fn fit_memory(&mut self, width: usize, height: usize, limit: u64) {
        if self.data == DataTerm::Prior {
            self.scratch
                .fit_on_prior(width, height, limit, bytes_for(width, height, 44, MIB));
        }
    }
}

/// A planned L2 solve for one size.
pub(crate) struct PoissonL2 {
    dims: Dims,
    alpha: f32,
    solver: DctPoisson,
    rhs: Vec<f32>,
}

impl PoissonL2 {
    /// Plans the solve for `width` x `height` frames.
    pub(crate) fn new(config: PoissonL2Config, width: usize, height: usize) -> Result<Self> {
        let dims = Dims {
            w: width,
            h: height,
        };
        Ok(PoissonL2 {
            dims,
            alpha: config.alpha,
            solver: DctPoisson::new(dims, config.alpha)?,
            rhs: try_vec(3 * dims.len(), 0.0)?,
        })
    }
}

/// Writes `alpha^2 b + D^T g` for the three channels into `rhs` (planar).
pub(crate) fn screened_rhs(frame: &Frame, alpha2: f32, dims: Dims, rhs: &mut [f32]) {
    let n = dims.len();
    let (b, gx, gy) = (
        frame.color().as_slice(),
        frame.dx().as_slice(),
        frame.dy().as_slice(),
    );
    for c in 0..3 {
        let r = c * n..(c + 1) * n;
        let plane = &mut rhs[r.clone()];
        grad_adjoint(&gx[r.clone()], &gy[r.clone()], dims, plane);
        for (v, &bv) in plane.iter_mut().zip(&b[r]) {
            *v += alpha2 * bv;
        }
    }
}

impl Reconstructor for PoissonL2 {
    fn method(&self) -> Method {
        Method::PoissonL2
    }

    fn reconstruct_into(
        &mut self,
        frame: &Frame,
        out: &mut Image,
        report: &mut Report,
        progress: &Progress,
    ) -> Result<()> {
        let alpha2 = self.alpha * self.alpha;
        let dims = self.dims;
        report.time("rhs", || screened_rhs(frame, alpha2, dims, &mut self.rhs));
        progress.update(0.2)?;
        report.time("dct solve", || self.solver.solve(&mut self.rhs));
        if self.alpha == 0.0 {
            // The DCT returned the zero-mean solution; the data term is gone, so take the mean
            // from the base image (the only information about it).
            let n = dims.len();
            for c in 0..3 {
                let b = &frame.color().as_slice()[c * n..(c + 1) * n];
                let mean = (b.iter().map(|&v| f64::from(v)).sum::<f64>() / n as f64) as f32;
                self.rhs[c * n..(c + 1) * n]
                    .iter_mut()
                    .for_each(|v| *v += mean);
            }
            report.note("alpha = 0: pure Poisson, mean taken from the base image");
        }
        out.as_mut_slice().copy_from_slice(&self.rhs);
        progress.update(1.0)
    }
}
