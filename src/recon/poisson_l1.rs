//! Screened Poisson reconstruction, L1: the robust variant of gradient-domain path tracing.
//!
//! Minimises the group-L1 energy `sum_p ||alpha (I - I_b)(p)|| + ||(D_x I - dx)(p)|| +
//! ||(D_y I - dy)(p)||`, where each norm is the Euclidean norm over R, G, B of one residual
//! row, by iteratively reweighted least squares (IRLS), as the reference solver does:
//! - step 0 uses unit weights (the L2 problem); step `k >= 1` sets, per residual row,
//!   `w = 1 / (||e_row|| + reg_k)` with `reg_k = 0.05 * 0.5^(k-1)`, one weight shared by
//!   R, G, B, then rescales all weights so that they average 1 over all rows (we do not:
//!   the solution does not depend on a common scale of the weights; see `reweight`);
//! - each weighted system `(alpha^2 W_d + D_x^T W_x D_x + D_y^T W_y D_y) I = alpha^2 W_d I_b +
//!   D_x^T W_x dx + D_y^T W_y dy` is solved by conjugate gradients warm-started from the
//!   previous step (from `I_b` at step 0).
//!
//! Where we differ:
//! - CG is preconditioned by the exact L2 solve (the DCT inverse of `alpha^2 + D^T D`, which
//!   equals the system matrix at unit weights, diagonally rescaled to the weights) or by a
//!   multigrid V-cycle on the weighted system (the default), and each step stops at a
//!   relative residual of `cg_tolerance` (1e-6) or once an iteration moves the image by less
//!   than `cg_change` (5e-5) in the error metric's units, so every step is solved, not
//!   truncated: the answer is the IRLS's own, whatever the frame.
//! - `reg_k` stops halving at `reg_floor` (1e-2). Below it the weights span more than six
//!   orders of magnitude, each step's system becomes so ill-conditioned that no iteration cap
//!   reaches its solution (the f64 solve to 1e-8 takes 2000-6000 CG iterations per late step),
//!   and the converged result is worse, not better (on the validation set, 1.8x at 4 spp).
//! - IRLS may stop before `reweight_steps`: after a step whose CG had nothing to do (the
//!   next would repeat it, same bits), or, unless `step_change` is 0, once a step at the
//!   floor moves the image by less than that (the default 2e-4: 7-20 of 20 steps on the
//!   validation and test frames, every frame within 0.3 % of all twenty; the combiner's
//!   candidates, 1e-3: 7 of 12 steps at 720p, within 0.3 % of all twelve).
//! - A step's CG also stops once an iteration moves the image by less than `cg_relative`
//!   (0.05) of what the previous step moved it: an early step need not be solved more finely
//!   than the next reweighting will move it (26 % fewer iterations on the validation and test
//!   frames, every frame within 0.5 %).
//!
//! [`PoissonL1Config::published`] reproduces the reference schedule (20 steps x 50 plain CG
//! iterations) and [`PoissonL1Config::fast`] the truncated solve of earlier versions, for
//! comparison. `examples/l1_reference.rs` measures how far a configuration is from its IRLS
//! solved in f64 to 1e-8.

use std::time::{Duration, Instant};

use rayon::prelude::*;

use super::band::{self, banded, BandScope, BAND_TRIM, NOISE_BAND};
use super::dct::DctPoisson;
use super::multigrid::{multigrid_bytes, Multigrid};
use super::ops::{apply_weighted, plane_sums, row_sum, weighted_row, Dims, Operator, RowWeights};
use super::param::{choices, Param, Params, Preset, Range};
use super::poisson_l2::{ALPHA_RANGE, DEFAULT_ALPHA};
use super::prior::{on_prior_memory, DataTerm, OnPrior, Scratch, DATA_DOC, PRIOR_ALPHA_DOC};
use super::{bytes_for, Method, Reconstructor, Register, MIB};
use crate::context::Context;
use crate::error::Result;
use crate::frame::Frame;
use crate::image::{try_vec, Image};
use crate::progress::Progress;
use crate::report::{Report, Stage};

/// Settings of the L1 (IRLS) screened Poisson solve; names, defaults and ranges are in its
/// parameter table below (listed in `docs/PARAMETERS.md`).
#[derive(Clone, Copy, Debug, PartialEq)]
#[non_exhaustive]
pub struct PoissonL1Config {
    /// Weight of the data term, as in L2.
    pub alpha: f32,
    /// IRLS steps, the first with unit weights.
    pub reweight_steps: u32,
    /// Maximum CG iterations per step.
    pub cg_iterations: u32,
    /// Relative CG residual at which a step stops; 0 runs all `cg_iterations`.
    pub cg_tolerance: f32,
    /// A step's CG also stops once an iteration moves the image by less than this, measured
    /// like the error metric (the root mean square of `change / sqrt(I^2 + 0.01)`); 0 never.
    pub cg_change: f32,
    /// IRLS stops once a step at the regularisation's floor moves the image by less than
    /// this, measured like `cg_change`; 0 runs every step.
    pub step_change: f32,
    /// A step's CG also stops once an iteration moves the image by less than this fraction
    /// of how far the previous step moved it (both measured like `cg_change`); 0 never.
    pub cg_relative: f32,
    /// Precondition CG (with `preconditioner`).
    pub preconditioned: bool,
    /// Which preconditioner CG uses when `preconditioned`.
    pub preconditioner: Preconditioner,
    /// Lower bound of the IRLS regularisation `reg_k` (radiance units).
    pub reg_floor: f32,
    /// What the data term anchors to: the base image or the prior.
    pub data: DataTerm,
    /// Weight of the data term when it is the prior.
    pub prior_alpha: f32,
    /// Half-width of the noise band the output is clamped to, in standard deviations of the
    /// base image's noise (`recon/band.rs`); 0: off.
    pub noise_band: f32,
    /// The noise band's trimming ratio at 64 spp or more (`recon/band.rs`); 0: never trimmed.
    pub band_trim: f32,
    /// Below 64 spp also trim the band of bright neighbours the gradients confirm as an
    /// object's edge (`recon/emitters.rs`); off here: on validation it cost `l1` 5 % on
    /// `dusk` at 4 spp and `gradnet` 1.4 % on `dusk` at 16 spp.
    pub band_emitters: bool,
    /// Where the band clamps: every pixel, or only beside an emitter's edge (`recon/band.rs`).
    pub band_scope: BandScope,
    /// OIDN's scratch memory when it computes the prior: lowered by a memory limit
    /// ([`Register::fit_memory`]), not a parameter.
    pub(crate) scratch: Scratch,
}

/// The preconditioner of each IRLS step's conjugate gradients.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum Preconditioner {
    /// The exact DCT solve of the unweighted system, diagonally rescaled to the weights.
    Dct,
    /// An algebraic multigrid V-cycle on the weighted system itself (`src/recon/multigrid.rs`);
    /// step 0, whose weights are all 1, starts from the DCT's exact solve.
    Multigrid,
    /// The inverse of the weighted system's diagonal; step 0 starts from the DCT's exact
    /// solve, as with `Multigrid`.
    Jacobi,
}

choices!(Preconditioner { Dct => "dct", Multigrid => "multigrid", Jacobi => "jacobi" });

/// `prior_alpha` of L1: the prior path's weight, chosen on the validation split
/// (docs/benchmarks.md, "The prior"; see [`PoissonL1Config::prior`]).
pub(crate) const DEFAULT_PRIOR_ALPHA_L1: f32 = 2.5;

/// `reg_floor` of the `prior` preset: half the default floor. Chosen on the validation split
/// by the frame that binds the prior path's bar (no frame more than 5 % worse than OIDN):
/// among floors 1e-2 to 1e-3 with `prior_alpha` 2.5, the lowest worst-frame ratio to OIDN
/// with every geometric mean within 0.5 % of 1e-2's (1.016 against 1.028, `indirect` 16 spp;
/// means 0.878 / 0.858 / 0.802 against 0.879 / 0.855 / 0.799 at 4 / 16 / 64 spp). A lower
/// floor keeps IRLS closer to L1 where the residuals are small, as in dim rooms whose
/// gradients are noisy, where a floor of 1e-2 leaves it nearly least squares and lets the
/// noise through (`docs/benchmarks.md`, thirtieth session). At 1280 x 720 it costs one more
/// IRLS step.
const PRIOR_REG_FLOOR: f32 = 5e-3;

/// Default of [`PoissonL1Config::cg_change`].
const CG_CHANGE: f32 = 5e-5;

/// Default of [`PoissonL1Config::step_change`].
const STEP_CHANGE: f32 = 2e-4;

/// Default of [`PoissonL1Config::cg_relative`].
const CG_RELATIVE: f32 = 0.05;

/// The converged answer by default (see `docs/benchmarks.md`, "An L1 that converges"): every
/// step's CG runs to a relative residual of 1e-6 (the 1000-iteration cap is a safety net
/// that no validation frame reaches), and the regularisation stops halving at 1e-2, where each
/// IRLS step stays well conditioned. On every validation frame the result is within 1 % of
/// the same IRLS solved to 1e-8 in f64. Why 1e-6 and not 1e-3: the residual is measured
/// against the whole right-hand side, which bright pixels dominate; on a dim frame with small
/// bright lights 1e-3 left the dark regions unsolved (6.6x the converged error). Solving only
/// the last steps tightly does not help (the early steps' weights are already wrong: 3.3x),
/// nor does weighting the residual norm like the error metric (1.3x at 1e-4). 1e-5 was
/// enough on the validation set but 6 % off on a synthetic 1000:1 frame (1e-6: 0.7 %;
/// `tests/poisson.rs`).
///
/// `cg_change` (5e-5) stops a step sooner where the residual rule is stricter than the image
/// needs: once an iteration changes the image by less than 5e-5 in the error metric's units
/// (root mean square of `change / sqrt(I^2 + 0.01)`, per channel), the rest of the solve
/// barely moves the relMSE (each multigrid-preconditioned update is about a fifth of the
/// last). Being relative per pixel, it does not let bright pixels hide unsolved dark
/// ones, which is why the residual rule could not be loosened. Chosen on the validation split
/// (within 0.3 % of the f64 IRLS on every frame; 1e-4 was 1.0 % off on a dim frame), it saves
/// 28 % of the iterations there (19 % on the test split) and a third at 720p (79 -> 52).
///
/// `step_change` (2e-4) ends IRLS once a step at the regularisation's floor moves the image
/// by less than that, in the same units. A dim frame is why it is not larger: there (`dusk`,
/// mean radiance under 0.05) IRLS creeps, each step moving the image by little in these
/// units but the relMSE by a lot (3e-4 stopped `dusk` 64 spp at step 15 for 1.13x the
/// every-step error, 1e-3 at step 9 for 1.51x). At 2e-4 every dim and HDR frame of the
/// validation and test splits runs all 20 steps and no frame moves by more than 0.3 %, while
/// brighter frames stop after 7-19 (720p synthetic frame: 1.30x -> 0.99x OIDN's time).
///
/// `cg_relative` (0.05) solves each step only as far as the IRLS is still moving: once a CG
/// iteration moves the image by less than 5 % of what the previous step moved it, the rest of
/// the step's solve is below what the next reweighting changes anyway. Chosen on validation
/// (every frame within 1 % of solving each step to `cg_change`; 0.1 was 1.4 % off on `studio`
/// 16 spp): within 0.08 % there and 0.5 % on test, 26 % fewer CG iterations on both, 720p
/// 0.95x -> 0.76x OIDN's time.
impl Default for PoissonL1Config {
    fn default() -> Self {
        PoissonL1Config {
            alpha: DEFAULT_ALPHA,
            reweight_steps: 20,
            cg_iterations: 1000,
            cg_tolerance: 1e-6,
            cg_change: CG_CHANGE,
            step_change: STEP_CHANGE,
            cg_relative: CG_RELATIVE,
            preconditioned: true,
            preconditioner: Preconditioner::Multigrid,
            reg_floor: 1e-2,
            data: DataTerm::Colour,
            prior_alpha: DEFAULT_PRIOR_ALPHA_L1,
            noise_band: NOISE_BAND,
            band_trim: BAND_TRIM,
            band_emitters: false,
            band_scope: BandScope::All,
            scratch: Scratch::default(),
        }
    }
}

impl PoissonL1Config {
    /// The preconditioner CG uses, if any.
    pub(crate) fn preconditioner(&self) -> Option<Preconditioner> {
        self.preconditioned.then_some(self.preconditioner)
    }

    /// The truncated solve that was the default until 0.2: at most 8 CG iterations per step,
    /// stopped at a relative residual of 1e-2, the regularisation halving to 2e-7. Faster, and
    /// on the validation set often a little better (truncation regularises), but not converged:
    /// on frames whose low frequencies must travel far (a room lit through a gap) it was 1.5-5x
    /// worse than the converged answer.
    pub fn fast() -> Self {
        PoissonL1Config {
            cg_iterations: 8,
            cg_tolerance: 1e-2,
            cg_change: 0.0,
            step_change: 0.0,
            cg_relative: 0.0,
            preconditioner: Preconditioner::Dct,
            reg_floor: 0.0,
            ..Self::default()
        }
    }

    /// The prior path: the data term is the prior (Open Image Denoise's output, or the frame's
    /// `prior` layer) with weight 2.5, 12 IRLS steps, CG to a relative residual of 1e-4, the
    /// regularisation's floor at 5e-3 (chosen on validation by the worst frame against OIDN:
    /// `docs/benchmarks.md`, thirtieth session).
    ///
    /// Chosen on the validation split against OIDN alone (docs/benchmarks.md, "The prior"):
    /// the group-L1 data term keeps the prior wherever the gradients disagree with it
    /// strongly and follows the gradients where they carry detail the denoiser lost. A
    /// smaller weight wins more on average but loses to OIDN on caustics (2: 1.23x OIDN on
    /// one frame), a larger one gives the gain away (3: 0.92x instead of 0.88x at 4 spp); L2
    /// cannot tell the two apart (at best 0.98x). With the prior as anchor the system is well
    /// conditioned, so 1e-4 is converged (1e-6 changes relMSE by under 1 %) at a third of
    /// the cost; 1e-3 is not (up to 8 % worse). The noise band only beside emitters' edges
    /// ([`BandScope::Edges`], edge trimming on), from 16 spp: the denoiser spreads a bulb
    /// into its dark ring, and the band holds those pixels to the base (the guard's
    /// `lamps_16spp` from 8.4x its base to 0.53x; validation 1.4 % better at 16 spp, 3.0 %
    /// at 64, no frame worse by more than 0.3 %). Everywhere, the band costs this path on
    /// validation (4 spp: 23 % on one frame; the prior is so much better than the base that
    /// its cuts, where the variance estimate undershoots, outweigh the errors it catches);
    /// below 16 spp a dark pixel's few samples too often all missed the lamp
    /// (`docs/benchmarks.md`, thirty-third session). CG is
    /// Jacobi-preconditioned: with the prior as anchor, one diagonal pass does what a
    /// multigrid V-cycle did at a tenth of its cost (at 1280 x 720: 12 CG iterations instead
    /// of 7, the solve 40 % faster; validation relMSE within 0.3 %).
    pub fn prior() -> Self {
        PoissonL1Config {
            preconditioner: Preconditioner::Jacobi,
            data: DataTerm::Prior,
            prior_alpha: DEFAULT_PRIOR_ALPHA_L1,
            reweight_steps: 12,
            cg_tolerance: 1e-4,
            cg_change: 0.0,
            step_change: 0.0,
            cg_relative: 0.0,
            band_emitters: true,
            band_scope: BandScope::Edges,
            reg_floor: PRIOR_REG_FLOOR,
            ..Self::default()
        }
    }

    /// The published schedule of gradient-domain path tracing's reference solver:
    /// 20 reweighting steps x 50 unpreconditioned CG iterations, no early stop.
    pub fn published() -> Self {
        PoissonL1Config {
            cg_iterations: 50,
            cg_tolerance: 0.0,
            cg_change: 0.0,
            step_change: 0.0,
            cg_relative: 0.0,
            preconditioned: false,
            reg_floor: 0.0,
            noise_band: 0.0,
            ..Self::default()
        }
    }
}

impl Params for PoissonL1Config {
    const TABLE: &'static [Param<Self>] = &[
        Param::float(
            "alpha",
            Range {
                min_open: true,
                ..ALPHA_RANGE
            },
            "Weight of the data term: residual rows are alpha (I - I_b)",
            |c| c.alpha,
            |c, v| c.alpha = v,
        ),
        Param::int(
            "reweight_steps",
            1,
            1000,
            "IRLS steps, the first with unit weights",
            |c| c.reweight_steps.into(),
            |c, v| c.reweight_steps = v as u32,
        ),
        Param::int(
            "cg_iterations",
            1,
            100_000,
            "Maximum conjugate-gradient iterations per IRLS step",
            |c| c.cg_iterations.into(),
            |c, v| c.cg_iterations = v as u32,
        ),
        Param::float(
            "cg_tolerance",
            Range::below(0.0, 1.0),
            "Stop a step's CG when every channel's residual norm is below this fraction of its \
             right-hand side's; 0 runs every iteration",
            |c| c.cg_tolerance,
            |c, v| c.cg_tolerance = v,
        ),
        Param::float(
            "cg_change",
            Range::below(0.0, 1.0),
            "Also stop a step's CG once an iteration moves the image by less than this, measured \
             like the error metric (root mean square of change / sqrt(I^2 + 0.01)); 0: never",
            |c| c.cg_change,
            |c, v| c.cg_change = v,
        ),
        Param::float(
            "step_change",
            Range::below(0.0, 1.0),
            "Stop IRLS once a step at the regularisation's floor moves the image by less than \
             this, measured like cg_change; 0 runs every step",
            |c| c.step_change,
            |c, v| c.step_change = v,
        ),
        Param::float(
            "cg_relative",
            Range::below(0.0, 1.0),
            "Also stop a step's CG once an iteration moves the image by less than this fraction \
             of how far the previous step moved it (both measured like cg_change); 0: never",
            |c| c.cg_relative,
            |c, v| c.cg_relative = v,
        ),
        Param::bool(
            "preconditioned",
            "Precondition CG with the exact L2 (DCT) solve",
            |c| c.preconditioned,
            |c, v| c.preconditioned = v,
        ),
        Param::choice(
            "preconditioner",
            Preconditioner::NAMES,
            "CG's preconditioner: 'dct' (the exact unweighted solve, rescaled to the weights), \
             'multigrid' (an algebraic V-cycle on the weighted system) or 'jacobi' (its inverse \
             diagonal: enough where a strong data term conditions the system, as on the prior, \
             with cg_change and cg_relative 0, since its small iterations would end CG early); \
             with the last two, step 0, at unit weights, is solved by the DCT",
            |c| c.preconditioner.index(),
            |c, v| c.preconditioner = Preconditioner::ALL[v],
        ),
        Param::float(
            "reg_floor",
            Range::closed(0.0, 1e6),
            "Lower bound of the IRLS regularisation, which halves from 0.05 at every step",
            |c| c.reg_floor,
            |c, v| c.reg_floor = v,
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
            Range {
                min_open: true,
                ..ALPHA_RANGE
            },
            PRIOR_ALPHA_DOC,
            |c| c.prior_alpha,
            |c, v| c.prior_alpha = v,
        ),
        band::param(|c| c.noise_band, |c, v| c.noise_band = v),
        band::trim_param(|c| c.band_trim, |c, v| c.band_trim = v),
        band::emitters_param(|c| c.band_emitters, |c, v| c.band_emitters = v),
        band::scope_param(
            |c| c.band_scope.index(),
            |c, v| c.band_scope = BandScope::ALL[v],
        ),
    ];

    const PRESETS: &'static [Preset<Self>] = &[
        Preset {
            name: "fast",
            doc: "truncated, not converged: at most 8 DCT-preconditioned CG iterations per \
                  step, stopped at a relative residual of 1e-2, no regularisation floor (the \
                  default until 0.2)",
            config: PoissonL1Config::fast,
        },
        Preset {
            name: "published",
            doc: "the reference solver's schedule: 20 steps x 50 plain CG iterations, no early \
                 stop, no noise band",
            config: PoissonL1Config::published,
        },
        Preset {
            name: "prior",
            doc: "the prior path: data term the prior (Open Image Denoise's output or the \
                  frame's 'prior' layer), prior_alpha 2.5, 12 steps, CG to 1e-4, \
                  regularisation floor 5e-3, the noise band beside emitters' edges only (from \
                  16 spp)",
            config: PoissonL1Config::prior,
        },
    ];
}

impl Register for PoissonL1Config {
    const SWEEP: &'static [&'static str] =
        &["", "step_change=0", "fast", "reweight_steps=5", "published"];
    const PRIOR_SWEEP: &'static [&'static str] = &["prior"];

    fn plan(
        &self,
        context: &Context,
        width: usize,
        height: usize,
    ) -> Result<Box<dyn Reconstructor>> {
        let inner: Box<dyn Reconstructor> = match self.data {
            DataTerm::Colour => Box::new(PoissonL1::new(*self, width, height)?),
            DataTerm::Prior => {
                let anchored = PoissonL1Config {
                    alpha: self.prior_alpha,
                    ..*self
                };
                let inner = Box::new(PoissonL1::new(anchored, width, height)?);
                Box::new(OnPrior::new(context, width, height, self.scratch, inner)?)
            }
        };
        Ok(banded(
            inner,
            self.noise_band,
            self.band_trim,
            self.band_emitters,
            self.band_scope,
        ))
    }

    fn memory_estimate(&self, width: usize, height: usize) -> u64 {
        let own = self.own_memory(width, height);
        match self.data {
            DataTerm::Colour => own,
            DataTerm::Prior => own.saturating_add(on_prior_memory(width, height, self.scratch)),
        }
    }

    fn fit_memory(&mut self, width: usize, height: usize, limit: u64) {
        if self.data == DataTerm::Prior {
            let own = self.own_memory(width, height);
            self.scratch.fit_on_prior(width, height, limit, own);
        }
    }
}

impl PoissonL1Config {
    /// The solve's bytes and its output, the prior apart.
    fn own_memory(&self, width: usize, height: usize) -> u64 {
        l1_memory(self, width, height).saturating_add(bytes_for(width, height, 12, 0))
    }
}

/// Bytes a [`PoissonL1`] holds (without the output image): six 3-plane CG vectors and four
/// weight planes (22 f32 planes) with 4 B a pixel to spare, and the preconditioner: the DCT's
/// eigenvalues and transposed planes (4 planes; with the multigrid too, for step 0) and the
/// multigrid hierarchy ([`multigrid_bytes`], about 21 B a pixel: its fine level reads the
/// solve's operator). With the output, peak heap measured by a counting allocator
/// (tests/memory.rs, `peak_table`, twenty-seventh session): 150.0 and 149.6 B a pixel at
/// 640 x 360 and 1280 x 720 with the multigrid (estimate 1.05x and 1.03x), 100.2 and 100.1
/// without a preconditioner (preset `published`, estimate 1.08x and 1.05x).
pub(crate) fn l1_memory(config: &PoissonL1Config, width: usize, height: usize) -> u64 {
    // With `step_change` or `cg_relative`, the image before each step (3 planes).
    let before = if config.step_change > 0.0 || config.cg_relative > 0.0 {
        bytes_for(width, height, 12, 0)
    } else {
        0
    };
    before.saturating_add(match config.preconditioner() {
        Some(Preconditioner::Multigrid) => {
            bytes_for(width, height, 4 * 26 + 4, MIB).saturating_add(multigrid_bytes(width, height))
        }
        Some(_) => bytes_for(width, height, 4 * 26 + 4, MIB),
        None => bytes_for(width, height, 4 * 22 + 4, MIB),
    })
}

/// A planned L1 solve for one size; all buffers are allocated here and reused.
pub(crate) struct PoissonL1 {
    dims: Dims,
    cfg: PoissonL1Config,
    precond: Option<DctPoisson>,
    multigrid: Option<Multigrid>,
    /// With the multigrid: the DCT inverse of the unit-weight operator, which is step 0's
    /// system, so step 0 starts from its exact solution (multigrid needs 7-8 iterations
    /// there, more than in any later step).
    start: Option<DctPoisson>,
    x: Vec<f32>,
    /// `x` before the current step (empty unless `step_change` or `cg_relative` is set).
    before: Vec<f32>,
    r: Vec<f32>,
    z: Vec<f32>,
    p: Vec<f32>,
    q: Vec<f32>,
    b: Vec<f32>,
    /// The weighted system's operator: `alpha^2 w_d` on the diagonal, `w_x` and `w_y` on the
    /// edges (0 on the rows that do not exist). The multigrid reads it where it is.
    op: Operator,
    /// Diagonal scaling of the DCT preconditioner: `sqrt(diag(L) / diag(A))`, with `L` the
    /// unweighted operator the DCT inverts and `A` the weighted one; with Jacobi,
    /// `1 / diag(A)`.
    scale: Vec<f32>,
    partials: Vec<f64>,
    /// Per-row dot products of the three planes, scratch of [`Self::apply`].
    row_dots: Vec<[f64; 3]>,
    /// Row partials of two sums at once (see [`Self::step`]).
    pairs: Vec<(f64, f64)>,
    /// Time spent in the preconditioner during the current execution (for the report).
    precond_time: Duration,
    /// Stop once a step is a fixed point (always, except in the test that shows the skipped
    /// steps would change nothing).
    skip_repeats: bool,
}

/// What one CG solve did.
struct CgOutcome {
    iterations: u32,
    rel_residual: f64,
    /// Stopped by `cg_iterations`, before either tolerance was met.
    capped: bool,
}

impl PoissonL1 {
    /// Plans the solve for `width` x `height` frames.
    pub(crate) fn new(config: PoissonL1Config, width: usize, height: usize) -> Result<Self> {
        Self::new_for(&[config], width, height)
    }

    /// Plans one solve that [`Self::reconfigure`] can switch between `configs` (the first is
    /// the one planned): it holds every preconditioner they use.
    pub(crate) fn new_for(
        configs: &[PoissonL1Config],
        width: usize,
        height: usize,
    ) -> Result<Self> {
        let config = configs[0];
        let dims = Dims {
            w: width,
            h: height,
        };
        let n = dims.len();
        let v3 = || try_vec(3 * n, 0.0f32);
        let uses = |p| configs.iter().any(|c| c.preconditioner() == Some(p));
        let (dct, multigrid, jacobi) = (
            uses(Preconditioner::Dct),
            uses(Preconditioner::Multigrid),
            uses(Preconditioner::Jacobi),
        );
        Ok(PoissonL1 {
            dims,
            cfg: config,
            precond: dct
                .then(|| DctPoisson::new(dims, config.alpha))
                .transpose()?,
            multigrid: multigrid.then(|| Multigrid::new(dims)).transpose()?,
            start: (multigrid || jacobi)
                .then(|| DctPoisson::new(dims, config.alpha))
                .transpose()?,
            x: v3()?,
            before: if config.step_change > 0.0 || config.cg_relative > 0.0 {
                v3()?
            } else {
                Vec::new()
            },
            r: v3()?,
            z: v3()?,
            p: v3()?,
            q: v3()?,
            b: v3()?,
            op: Operator {
                data: try_vec(n, 1.0)?,
                ex: try_vec(n, 1.0)?,
                ey: try_vec(n, 1.0)?,
            },
            scale: try_vec(n, 1.0)?,
            partials: Vec::new(),
            row_dots: Vec::new(),
            pairs: Vec::new(),
            precond_time: Duration::ZERO,
            skip_repeats: true,
        })
    }

    /// Makes this the solve planned for `config`, which must differ from the planned one in
    /// `alpha`, `reweight_steps`, `step_change` and the preconditioner at most (what the
    /// combiner's two candidates differ in; [`Self::new_for`] plans every preconditioner they
    /// use): one plan then serves both, and each execution gives the same bits as a plan made
    /// for its configuration (`reconfigured_solve_is_a_fresh_one`).
    // The combiner is its only caller, and it needs ONNX Runtime (the `gradnet` feature).
    #[cfg_attr(not(feature = "gradnet"), allow(dead_code))]
    pub(crate) fn reconfigure(&mut self, config: PoissonL1Config) {
        let comparable = |c: &PoissonL1Config| PoissonL1Config {
            alpha: 0.0,
            reweight_steps: 0,
            step_change: 0.0,
            preconditioned: false,
            preconditioner: Preconditioner::Dct,
            ..*c
        };
        assert_eq!(
            comparable(&config),
            comparable(&self.cfg),
            "a reconfigured L1 solve may change alpha, reweight_steps, step_change and the \
             preconditioner only"
        );
        assert!(
            match config.preconditioner() {
                None => true,
                Some(Preconditioner::Dct) => self.precond.is_some(),
                Some(Preconditioner::Multigrid) => self.multigrid.is_some(),
                Some(Preconditioner::Jacobi) => self.start.is_some(),
            },
            "a reconfigured L1 solve uses a preconditioner it was planned with"
        );
        assert_eq!(
            config.step_change > 0.0 || config.cg_relative > 0.0,
            !self.before.is_empty(),
            "a reconfigured L1 solve keeps its step_change buffer"
        );
        if config.alpha != self.cfg.alpha {
            for dct in [self.precond.as_mut(), self.start.as_mut()]
                .into_iter()
                .flatten()
            {
                dct.set_alpha(config.alpha);
            }
        }
        self.cfg = config;
    }

    /// Unit weights (step 0; the diagonal is then `alpha^2`), with the rows that do not exist
    /// (last column of `x`, last row of `y`) at weight 0 so that every later pass can ignore
    /// the boundary.
    fn reset_weights(&mut self) {
        let Dims { w, h } = self.dims;
        for v in [&mut self.op.ex, &mut self.op.ey, &mut self.scale] {
            v.fill(1.0);
        }
        self.op.data.fill(self.cfg.alpha * self.cfg.alpha);
        self.op.ex.chunks_mut(w).for_each(|row| row[w - 1] = 0.0);
        self.op.ey[(h - 1) * w..].fill(0.0);
    }

    /// Sets up IRLS step `k >= 1` from the current `x` in one pass over memory: the weights
    /// `1 / (||e_row|| + reg)` of every residual row, the right-hand side `b` of the weighted
    /// system (not stored), and the residual `r = b - A x` CG starts from. Returns `b . b` and
    /// `r . r` per channel.
    ///
    /// The reference solver also rescales the weights to average 1. The weighted least-squares
    /// solution does not depend on a common scale of the weights, and neither does any step
    /// of CG or of its preconditioners (every quantity scales with them, exactly so in floating
    /// point for a power of two); leaving the rescaling out is rescaling by 1, and saves the
    /// pass that would need all the weights before the system could be formed.
    fn reweight(&mut self, frame: &Frame, reg: f32) -> ([f64; 3], [f64; 3]) {
        let Dims { w, h } = self.dims;
        let n = w * h;
        let alpha = self.cfg.alpha;
        let planes = Planes {
            x: &self.x,
            colour: frame.color().as_slice(),
            dx: frame.dx().as_slice(),
            dy: frame.dy().as_slice(),
            n,
            w,
        };
        let (r0, rest) = self.r.split_at_mut(n);
        let (r1, r2) = rest.split_at_mut(n);
        let len = REWEIGHT_BAND * w;
        let band = |(up, b): &mut (Vec<f32>, Vec<f32>),
                    (k, (((data, wx), wy), ((r0, r1), r2))): ReweightBand<'_>| {
            let top = k * REWEIGHT_BAND;
            if top > 0 {
                // The vertical weights above the band, which its first row's system needs.
                planes.vertical_weights(top - 1, h, reg, up);
            }
            let mut sums = [0.0f64; 6];
            let mut r = [r0, r1, r2];
            for j in 0..data.len() / w {
                let (y, o) = (top + j, j * w);
                planes.data_weights(y, alpha, reg, &mut data[o..o + w]);
                planes.horizontal_weights(y, reg, &mut wx[o..o + w]);
                let (done, wy) = wy.split_at_mut(o);
                planes.vertical_weights(y, h, reg, &mut wy[..w]);
                let wy_up: Option<&[f32]> = match (y, j) {
                    (0, _) => None,
                    (_, 0) => Some(up),
                    _ => Some(&done[o - w..]),
                };
                let row_weights = RowWeights {
                    data: &data[o..o + w],
                    x: &wx[o..o + w],
                    y: &wy[..w],
                };
                for (c, r) in r.iter_mut().enumerate() {
                    let r = &mut r[o..o + w];
                    planes.rhs_row(c, y, &row_weights, wy_up, b);
                    let x = |y: usize| planes.row(planes.x, c, y);
                    let above = wy_up.map(|wy_up| (x(y - 1), wy_up));
                    let below = (y + 1 < h).then(|| x(y + 1));
                    weighted_row(r, &row_weights, x(y), above, below);
                    for (r, &b) in r.iter_mut().zip(b.iter()) {
                        *r = b - *r;
                    }
                    sums[c] += f64::from(row_sum(b, b, |b, _| b * b));
                    sums[3 + c] += f64::from(row_sum(r, r, |r, _| r * r));
                }
            }
            sums
        };
        let sums: Vec<[f64; 6]> = self
            .op
            .data
            .par_chunks_mut(len)
            .zip(self.op.ex.par_chunks_mut(len))
            .zip(self.op.ey.par_chunks_mut(len))
            .zip(
                r0.par_chunks_mut(len)
                    .zip(r1.par_chunks_mut(len))
                    .zip(r2.par_chunks_mut(len)),
            )
            .enumerate()
            .map_init(|| (vec![0.0; w], vec![0.0; w]), band)
            .collect();
        // Bands in order: the same sums for any number of threads.
        let total = |i: usize| sums.iter().map(|s| s[i]).sum::<f64>();
        (
            std::array::from_fn(total),
            std::array::from_fn(|c| total(3 + c)),
        )
    }

    /// The regularisation of IRLS step `step >= 1`: 0.05 halved at every step, at least the
    /// floor.
    fn reg(&self, step: u32) -> f32 {
        (0.05f32 * 0.5f32.powi(step as i32 - 1)).max(self.cfg.reg_floor)
    }

    /// `b = alpha^2 W_d I_b + D_x^T W_x dx + D_y^T W_y dy`; returns `b . b` per channel.
    /// Relies on the zero weights of the rows that do not exist (see `reset_weights`).
    fn weighted_rhs(&mut self, frame: &Frame) -> [f64; 3] {
        let Dims { w, h } = self.dims;
        let planes = Planes {
            x: &self.x,
            colour: frame.color().as_slice(),
            dx: frame.dx().as_slice(),
            dy: frame.dy().as_slice(),
            n: w * h,
            w,
        };
        let (data, wx, wy) = (&self.op.data, &self.op.ex, &self.op.ey);
        self.b
            .par_chunks_mut(w)
            .enumerate()
            .map(|(r, row)| {
                let (c, y) = (r / h, r % h);
                let k = y * w; // offset in the (shared) weight planes
                let row_weights = RowWeights {
                    data: &data[k..k + w],
                    x: &wx[k..k + w],
                    y: &wy[k..k + w],
                };
                let wy_up = (y >= 1).then(|| &wy[k - w..k]);
                planes.rhs_row(c, y, &row_weights, wy_up, row);
                f64::from(row_sum(row, row, |v, _| v * v))
            })
            .collect_into_vec(&mut self.partials);
        per_channel(&self.partials)
    }

    /// `dst = A src` per channel; returns `src . dst`.
    fn apply(&mut self, src: &[f32], dst: &mut [f32]) -> [f64; 3] {
        let wt = self.op.weights();
        apply_weighted(
            src,
            &wt,
            self.dims,
            dst,
            &mut self.row_dots,
            |_, _, row, u| f64::from(row_sum(row, u, |a, b| a * b)),
        )
    }

    /// `r = b - A x`, in the same pass as `A x`; returns `r . r` per channel.
    fn residual(&mut self) -> [f64; 3] {
        let wt = self.op.weights();
        let Dims { w, h } = self.dims;
        let b = &self.b;
        let finish = |plane: usize, y: usize, row: &mut [f32], _: &[f32]| {
            let o = plane * w * h + y * w;
            for (r, &b) in row.iter_mut().zip(&b[o..o + w]) {
                *r = b - *r;
            }
            f64::from(row_sum(row, row, |r, _| r * r))
        };
        let (x, r) = (&self.x, &mut self.r);
        apply_weighted(x, &wt, self.dims, r, &mut self.row_dots, finish)
    }

    /// `x += a p`, `r -= a q` (per-channel `a`); returns `r . r` per channel and, per
    /// channel, the mean over pixels of `(a p)^2 / (x^2 + 0.01)` (the change in the error
    /// metric's units).
    fn step(&mut self, a: [f32; 3]) -> ([f64; 3], [f64; 3]) {
        let Dims { w, h } = self.dims;
        self.x
            .par_chunks_mut(w)
            .zip(self.r.par_chunks_mut(w))
            .zip(self.p.par_chunks(w).zip(self.q.par_chunks(w)))
            .enumerate()
            .map(|(row, ((x, r), (p, q)))| {
                let a = a[row / h];
                for (((x, r), &p), &q) in x.iter_mut().zip(r.iter_mut()).zip(p).zip(q) {
                    *x += a * p;
                    *r -= a * q;
                }
                // Summed in a second loop over the row (in cache), which vectorises.
                let rr = row_sum(r, r, |r, _| r * r);
                let change = row_sum(x, p, |x, p| (a * p) * (a * p) / (x * x + 0.01));
                (f64::from(rr), f64::from(change))
            })
            .collect_into_vec(&mut self.pairs);
        let rows = self.pairs.len() / 3;
        let sum = |c: usize, f: fn(&(f64, f64)) -> f64| {
            self.pairs[c * rows..(c + 1) * rows]
                .iter()
                .map(f)
                .sum::<f64>()
        };
        let n = self.dims.len() as f64;
        (
            std::array::from_fn(|c| sum(c, |v| v.0)),
            std::array::from_fn(|c| sum(c, |v| v.1) / n),
        )
    }

    /// `z = S L^-1 S r`: the DCT inverse of the unweighted operator, made aware of the
    /// weights by a symmetric diagonal scaling (so the preconditioner stays SPD; it halves
    /// the CG iterations of the plain DCT preconditioner). Returns `r . z` per channel.
    fn precondition(&mut self) -> [f64; 3] {
        let n = self.dims.len();
        let w = self.dims.w;
        let Some(kind) = self.cfg.preconditioner() else {
            self.z.copy_from_slice(&self.r);
            let r = std::mem::take(&mut self.r);
            let rr = plane_sums(&r, &r, w, n, &mut self.partials, |a, b| {
                f64::from(a) * f64::from(b)
            });
            self.r = r;
            return [rr[0], rr[1], rr[2]];
        };
        let t0 = Instant::now();
        if kind == Preconditioner::Jacobi {
            let s = &self.scale;
            self.z
                .par_chunks_mut(w)
                .zip(self.r.par_chunks(w))
                .enumerate()
                .map(|(row, (z, r))| {
                    let o = (row % self.dims.h) * w;
                    for ((z, &r), &s) in z.iter_mut().zip(r).zip(&s[o..o + w]) {
                        *z = r * s;
                    }
                    row_sum(r, z, |r, z| f64::from(r) * f64::from(z))
                })
                .collect_into_vec(&mut self.partials);
            self.precond_time += t0.elapsed();
            return per_channel(&self.partials);
        }
        if let (Preconditioner::Multigrid, Some(mg)) = (kind, self.multigrid.as_mut()) {
            let rz = mg.apply(&self.op, &self.r, &mut self.z);
            self.precond_time += t0.elapsed();
            return rz;
        }
        let s = &self.scale;
        self.z
            .par_chunks_mut(n)
            .zip(self.r.par_chunks(n))
            .for_each(|(z, r)| {
                z.par_iter_mut()
                    .zip(r.par_iter().zip(s.par_iter()))
                    .for_each(|(z, (&r, &s))| *z = r * s);
            });
        if let Some(m) = self.precond.as_mut() {
            m.solve(&mut self.z);
        }
        let rows_per_plane = self.dims.h;
        self.z
            .par_chunks_mut(w)
            .zip(self.r.par_chunks(w))
            .enumerate()
            .map(|(row, (z, r))| {
                let o = (row % rows_per_plane) * w;
                for (z, &s) in z.iter_mut().zip(&s[o..o + w]) {
                    *z *= s;
                }
                f64::from(row_sum(r, z, |r, z| r * z))
            })
            .collect_into_vec(&mut self.partials);
        self.precond_time += t0.elapsed();
        per_channel(&self.partials)
    }

    /// Recomputes [`Self::scale`] from the current weights (zero at missing rows).
    fn update_scale(&mut self) {
        let Dims { w, h } = self.dims;
        let alpha2 = self.cfg.alpha * self.cfg.alpha;
        let jacobi = self.cfg.preconditioner() == Some(Preconditioner::Jacobi);
        let (data, wx, wy) = (&self.op.data, &self.op.ex, &self.op.ey);
        self.scale
            .par_chunks_mut(w)
            .enumerate()
            .for_each(|(y, row)| {
                let k = y * w;
                let (dr, wxr, wyr) = (&data[k..k + w], &wx[k..k + w], &wy[k..k + w]);
                // diag(L): alpha^2 plus the number of neighbours; diag(A): alpha^2 wd plus the
                // weights of the edges at the pixel.
                let vertical = f32::from(u8::from(y >= 1) + u8::from(y + 1 < h));
                for i in 0..w {
                    let horizontal = f32::from(u8::from(i >= 1) + u8::from(i + 1 < w));
                    let left = if i >= 1 { wxr[i - 1] } else { 0.0 };
                    let up = if y >= 1 { wy[k + i - w] } else { 0.0 };
                    let da = dr[i] + left + wxr[i] + up + wyr[i];
                    let dl = alpha2 + horizontal + vertical;
                    row[i] = if jacobi {
                        if da > 0.0 {
                            1.0 / da
                        } else {
                            0.0
                        }
                    } else if da > 0.0 {
                        (dl / da).sqrt()
                    } else {
                        1.0
                    };
                }
            });
    }

    /// How far the step moved the image from `before`, like `cg_change`: the largest
    /// channel's root mean square of `(x - before) / sqrt(x^2 + 0.01)`.
    fn step_moved(&mut self) -> f64 {
        let n = self.dims.len();
        let sums = plane_sums(
            &self.x,
            &self.before,
            self.dims.w,
            n,
            &mut self.partials,
            |x, b| f64::from((x - b) * (x - b) / (x * x + 0.01)),
        );
        (sums.into_iter().fold(0.0, f64::max) / n as f64).sqrt()
    }

    /// Preconditioned CG on the current weighted system, warm-started from `x` (`r` holds its
    /// residual, `rr` its `r . r` per channel), with per-channel step sizes (three independent
    /// systems run in lockstep). It also stops once
    /// an iteration moves the image by less than `cg_change` or `min_move` (`cg_relative`'s
    /// share of the previous step's move; 0: none), whichever is larger.
    fn cg(
        &mut self,
        bb: [f64; 3],
        mut rr: [f64; 3],
        min_move: f64,
        progress: &dyn Fn(f64) -> Result<()>,
    ) -> Result<CgOutcome> {
        let tol2 = f64::from(self.cfg.cg_tolerance).powi(2);
        let change2 = f64::from(self.cfg.cg_change).max(min_move).powi(2);
        let bb = bb.map(|v| v.max(f64::MIN_POSITIVE));
        let rel = |rr: [f64; 3]| (0..3).map(|c| rr[c] / bb[c]).fold(0.0, f64::max);
        if rel(rr) <= tol2 {
            return Ok(CgOutcome {
                iterations: 0,
                rel_residual: rel(rr).sqrt(),
                capped: false,
            });
        }
        let mut rz = self.precondition();
        // p = z: the next `precondition` rewrites all of `z` before it is read.
        std::mem::swap(&mut self.p, &mut self.z);
        let max = self.cfg.cg_iterations;
        let (mut it, mut capped) = (0, true);
        while it < max {
            let (p, mut q) = (std::mem::take(&mut self.p), std::mem::take(&mut self.q));
            let pq = self.apply(&p, &mut q);
            (self.p, self.q) = (p, q);
            let a: [f32; 3] = std::array::from_fn(|c| {
                let converged = rr[c] <= tol2 * bb[c];
                if converged || pq[c].is_nan() || pq[c] <= 0.0 {
                    0.0
                } else {
                    (rz[c] / pq[c]) as f32
                }
            });
            let change;
            (rr, change) = self.step(a);
            it += 1;
            progress(f64::from(it) / f64::from(max))?;
            // The largest channel's change: every channel has stopped moving.
            let moved = change.into_iter().fold(0.0, f64::max);
            if rel(rr) <= tol2 || (change2 > 0.0 && moved <= change2) {
                capped = false;
                break;
            }
            if it == max {
                break;
            }
            let rz_new = self.precondition();
            let beta: [f32; 3] = std::array::from_fn(|c| {
                if rz[c] > 0.0 {
                    (rz_new[c] / rz[c]) as f32
                } else {
                    0.0
                }
            });
            rz = rz_new;
            let h = self.dims.h;
            self.p
                .par_chunks_mut(self.dims.w)
                .zip(self.z.par_chunks(self.dims.w))
                .enumerate()
                .for_each(|(row, (p, z))| {
                    let beta = beta[row / h];
                    for (p, &z) in p.iter_mut().zip(z) {
                        *p = z + beta * *p;
                    }
                });
        }
        Ok(CgOutcome {
            iterations: it,
            rel_residual: rel(rr).sqrt(),
            capped,
        })
    }
}

/// Rows per task of [`PoissonL1::reweight`].
const REWEIGHT_BAND: usize = 16;

/// One band of [`PoissonL1::reweight`]: its index, its rows of the three weight planes and of
/// the three residual planes.
type ReweightBand<'a> = (
    usize,
    (
        ((&'a mut [f32], &'a mut [f32]), &'a mut [f32]),
        ((&'a mut [f32], &'a mut [f32]), &'a mut [f32]),
    ),
);

/// The current image and the frame's planes (three planes of `n` values each) that the IRLS
/// residual rows are made of.
struct Planes<'a> {
    x: &'a [f32],
    colour: &'a [f32],
    dx: &'a [f32],
    dy: &'a [f32],
    n: usize,
    w: usize,
}

impl<'a> Planes<'a> {
    /// Row `y` of plane `c` of `v`.
    fn row(&self, v: &'a [f32], c: usize, y: usize) -> &'a [f32] {
        let o = c * self.n + y * self.w;
        &v[o..o + self.w]
    }

    /// Row `y` of all three planes of `v`.
    fn rows(&self, v: &'a [f32], y: usize) -> [&'a [f32]; 3] {
        std::array::from_fn(|c| self.row(v, c, y))
    }

    /// The data rows' weights `w_d = 1 / (||alpha (x - I_b)|| + reg)` of row `y`, times
    /// `alpha^2`.
    fn data_weights(&self, y: usize, alpha: f32, reg: f32, out: &mut [f32]) {
        let (x, colour) = (self.rows(self.x, y), self.rows(self.colour, y));
        norm_weights(out, x, colour, None, alpha, reg);
        // The operator's diagonal: alpha^2 w_d.
        let alpha2 = alpha * alpha;
        out.iter_mut().for_each(|v| *v *= alpha2);
    }

    /// The horizontal rows' weights of row `y`: `||x(p + 1) - x(p) - dx(p)||` for `p` in the
    /// first `w - 1` columns, 0 in the last.
    fn horizontal_weights(&self, y: usize, reg: f32, out: &mut [f32]) {
        let w = self.w;
        let (x, dx) = (self.rows(self.x, y), self.rows(self.dx, y));
        let (right, left) = (x.map(|v| &v[1..]), x.map(|v| &v[..w - 1]));
        norm_weights(&mut out[..w - 1], right, left, Some(dx), 1.0, reg);
        out[w - 1] = 0.0;
    }

    /// The vertical rows' weights of row `y` (of `h`): `||x(p + w) - x(p) - dy(p)||`, all 0
    /// on the last row.
    fn vertical_weights(&self, y: usize, h: usize, reg: f32, out: &mut [f32]) {
        if y + 1 >= h {
            out.fill(0.0);
            return;
        }
        let (x, below, dy) = (
            self.rows(self.x, y),
            self.rows(self.x, y + 1),
            self.rows(self.dy, y),
        );
        norm_weights(out, below, x, Some(dy), 1.0, reg);
    }

    /// Row `y` of plane `c` of the right-hand side `alpha^2 W_d I_b + D_x^T W_x dx + D_y^T
    /// W_y dy`, `wt` holding the row's operator (`alpha^2 w_d`, `w_x`, `w_y`) and `wy_up` the
    /// vertical weights above it (`None` on the first row).
    fn rhs_row(&self, c: usize, y: usize, wt: &RowWeights, wy_up: Option<&[f32]>, out: &mut [f32]) {
        let w = self.w;
        let (ib, gx, gy) = (
            self.row(self.colour, c, y),
            self.row(self.dx, c, y),
            self.row(self.dy, c, y),
        );
        for i in 0..w {
            out[i] = wt.data[i] * ib[i] - wt.x[i] * gx[i] - wt.y[i] * gy[i];
        }
        for i in 1..w {
            out[i] += wt.x[i - 1] * gx[i - 1];
        }
        if let Some(wy_up) = wy_up {
            let gy_up = self.row(self.dy, c, y - 1);
            for i in 0..w {
                out[i] += wy_up[i] * gy_up[i];
            }
        }
    }
}

/// `out = 1 / (scale ||a - b - g|| + reg)`, the norm over the three planes' rows (no `g`:
/// 0). Compiled for AVX-512 and AVX2 too (it takes a square root and a division per cell);
/// Rust never fuses multiply-adds, so every target gives the same bits.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn norm_weights(
    out: &mut [f32],
    a: [&[f32]; 3],
    b: [&[f32]; 3],
    g: Option<[&[f32]; 3]>,
    scale: f32,
    reg: f32,
) {
    let w = out.len();
    let ([a0, a1, a2], [b0, b1, b2]) = (a.map(|v| &v[..w]), b.map(|v| &v[..w]));
    match g.map(|g| g.map(|v| &v[..w])) {
        Some([g0, g1, g2]) => {
            for i in 0..w {
                let e0 = a0[i] - b0[i] - g0[i];
                let e1 = a1[i] - b1[i] - g1[i];
                let e2 = a2[i] - b2[i] - g2[i];
                out[i] = 1.0 / (scale * (e0 * e0 + e1 * e1 + e2 * e2).sqrt() + reg);
            }
        }
        None => {
            for i in 0..w {
                let (e0, e1, e2) = (a0[i] - b0[i], a1[i] - b1[i], a2[i] - b2[i]);
                out[i] = 1.0 / (scale * (e0 * e0 + e1 * e1 + e2 * e2).sqrt() + reg);
            }
        }
    }
}

/// Sums row partials (three planes of equal row count) per channel, in order.
fn per_channel(partials: &[f64]) -> [f64; 3] {
    let rows = partials.len() / 3;
    std::array::from_fn(|c| partials[c * rows..(c + 1) * rows].iter().sum())
}

impl Reconstructor for PoissonL1 {
    fn method(&self) -> Method {
        Method::PoissonL1
    }

    fn reconstruct_into(
        &mut self,
        frame: &Frame,
        out: &mut Image,
        report: &mut Report,
        progress: &Progress,
    ) -> Result<()> {
        let steps = self.cfg.reweight_steps;
        self.x.copy_from_slice(frame.color().as_slice());
        self.reset_weights();
        let (mut total_iters, mut last_rel) = (0u32, 0.0f64);
        let (mut reweight_time, mut cg_time) = (Duration::ZERO, Duration::ZERO);
        self.precond_time = Duration::ZERO;
        let mut capped = 0u32;
        // Steps run: fewer than `steps` once a step is a fixed point (see below).
        let mut ran = steps;
        let mut last_iterations = None;
        // Set when `step_change` ended IRLS: how far the last step moved the image.
        let mut settled = None;
        let kappa = f64::from(self.cfg.cg_relative);
        // How far the previous step moved the image (measured from step 1 on).
        let mut last_move = 0.0;
        for step in 0..steps {
            // A step whose CG had nothing to do left `x` as its weights found it; when the
            // regularisation has stopped changing too (it is at `reg_floor`), every later step
            // would compute the same weights, the same system and again no iteration: stop.
            // The output is the same bits as running them.
            if self.skip_repeats
                && step >= 2
                && last_iterations == Some(0)
                && self.reg(step) == self.reg(step - 1)
            {
                ran = step;
                break;
            }
            let t0 = Instant::now();
            // Step 0's system has unit weights (set before the loop); a later step's is
            // formed from the current image, with its residual.
            let reweighted = (step > 0).then(|| self.reweight(frame, self.reg(step)));
            // The DCT's scaling is 1 at unit weights (step 0); Jacobi's is not.
            match self.cfg.preconditioner() {
                Some(Preconditioner::Dct) if step > 0 => self.update_scale(),
                Some(Preconditioner::Jacobi) => self.update_scale(),
                _ => {}
            }
            if let (Some(Preconditioner::Multigrid), Some(mg)) =
                (self.cfg.preconditioner(), self.multigrid.as_mut())
            {
                mg.set_operator(&self.op);
            }
            // (step + f) / steps: exact at step boundaries, so progress is monotone.
            let at = |f: f64| progress.update((f64::from(step) + f) / f64::from(steps));
            // Report (and let the caller cancel) at every step, also those whose CG has
            // nothing to do: cancellation latency stays below one step.
            at(0.0)?;
            let (bb, rr) = match reweighted {
                Some(sums) => sums,
                None => {
                    let bb = self.weighted_rhs(frame);
                    let starts = matches!(
                        self.cfg.preconditioner(),
                        Some(Preconditioner::Multigrid | Preconditioner::Jacobi)
                    );
                    if let (true, Some(dct)) = (starts, self.start.as_mut()) {
                        // Unit weights: the DCT solves the system itself (CG then checks it).
                        self.x.copy_from_slice(&self.b);
                        dct.solve(&mut self.x);
                        // The DCT solve takes 30 ms at 1280 x 720 on two cores: a cancel
                        // meanwhile is seen here, not after the first CG iteration as well.
                        at(0.0)?;
                    }
                    (bb, self.residual())
                }
            };
            let t1 = Instant::now();
            reweight_time += t1 - t0;
            // Once the regularisation is at its floor, the weights only follow the image: a
            // step that barely moves it leaves the next step's weights barely changed, and
            // IRLS may stop after it (not after the last step, which ends anyway).
            let may_settle = self.cfg.step_change > 0.0
                && step >= 1
                && step + 1 < steps
                && self.reg(step + 1) == self.reg(step);
            let measure = may_settle || (kappa > 0.0 && step > 0);
            if measure {
                self.before.copy_from_slice(&self.x);
            }
            let outcome = self.cg(bb, rr, kappa * last_move, &at)?;
            cg_time += t1.elapsed();
            total_iters += outcome.iterations;
            last_iterations = Some(outcome.iterations);
            last_rel = outcome.rel_residual;
            capped += u32::from(outcome.capped);
            if measure {
                let moved = self.step_moved();
                last_move = moved;
                if may_settle && moved <= f64::from(self.cfg.step_change) {
                    ran = step + 1;
                    settled = Some(moved);
                    break;
                }
            }
        }
        for (name, time) in [
            ("reweight", reweight_time),
            ("cg", cg_time.saturating_sub(self.precond_time)),
            ("precondition", self.precond_time),
        ] {
            report.stages.push(Stage {
                name: name.into(),
                time,
            });
        }
        if capped > 0 && (self.cfg.cg_tolerance > 0.0 || self.cfg.cg_change > 0.0) {
            report.note(format!(
                "IRLS: {capped} of {steps} steps stopped at cg_iterations = {} before reaching \
                 cg_tolerance or cg_change",
                self.cfg.cg_iterations
            ));
        }
        let skipped = if let Some(moved) = settled {
            format!(
                " (step {} moved the image by {moved:.1e}, under step_change = {})",
                ran - 1,
                self.cfg.step_change
            )
        } else if ran < steps {
            format!(
                " (the last {} skipped: step {ran} would repeat step {}, whose CG had nothing \
                 to do)",
                steps - ran,
                ran - 1
            )
        } else {
            String::new()
        };
        report.note(format!(
            "IRLS: {ran} of {steps} steps{skipped}, {total_iters} CG iterations ({}), last relative residual {last_rel:.2e}",
            match self.cfg.preconditioner() {
                Some(Preconditioner::Dct) => "DCT-preconditioned",
                Some(Preconditioner::Multigrid) =>
                    "multigrid-preconditioned; step 0 solved by the DCT",
                Some(Preconditioner::Jacobi) => "Jacobi-preconditioned; step 0 solved by the DCT",
                None => "unpreconditioned",
            }
        ));
        out.as_mut_slice().copy_from_slice(&self.x);
        progress.update(1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::synthetic_frame;

    /// One 96 x 64 solve of `frame` (`skip`: the fixed-point rule); its output and notes.
    fn solve(config: PoissonL1Config, frame: &Frame, skip: bool) -> (Image, String) {
        let mut solve = PoissonL1::new(config, 96, 64).unwrap();
        solve.skip_repeats = skip;
        let mut out = Image::zeros(3, 96, 64);
        let mut report = Report::default();
        solve
            .reconstruct_into(frame, &mut out, &mut report, &Progress::none())
            .unwrap();
        (out, report.notes.join("; "))
    }

    /// The one-pass setup of a reweighted step forms the IRLS system of the module comment:
    /// its weights, `b . b` and the residual `r = b - A x` (with `r . r`) against plain
    /// per-pixel loops in f64, on a frame of several bands (the last one short) and an odd
    /// width, from an image that is not the base image.
    #[test]
    fn reweighting_forms_the_weighted_system_and_its_residual() {
        let (w, h) = (23, 2 * REWEIGHT_BAND + 7);
        let n = w * h;
        let frame = synthetic_frame(w, h, 4.0, 3);
        let (alpha, reg) = (0.2f64, 0.0125f64);
        let mut solve = PoissonL1::new(PoissonL1Config::default(), w, h).unwrap();
        for (i, (x, &c)) in solve.x.iter_mut().zip(frame.color().as_slice()).enumerate() {
            *x = c + 0.05 * (i as f32 * 0.37).sin();
        }
        let (bb, rr) = solve.reweight(&frame, reg as f32);

        let f = |v: &[f32], c: usize, x: usize, y: usize| f64::from(v[c * n + y * w + x]);
        let (xs, ib) = (solve.x.clone(), frame.color().as_slice());
        let (gx, gy) = (frame.dx().as_slice(), frame.dy().as_slice());
        let norm = |e: &dyn Fn(usize) -> f64| (0..3).map(|c| e(c) * e(c)).sum::<f64>().sqrt();
        let (mut wd, mut wx, mut wy) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
        for y in 0..h {
            for x in 0..w {
                let p = y * w + x;
                wd[p] = 1.0 / (alpha * norm(&|c| f(&xs, c, x, y) - f(ib, c, x, y)) + reg);
                if x + 1 < w {
                    let e = |c| f(&xs, c, x + 1, y) - f(&xs, c, x, y) - f(gx, c, x, y);
                    wx[p] = 1.0 / (norm(&e) + reg);
                }
                if y + 1 < h {
                    let e = |c| f(&xs, c, x, y + 1) - f(&xs, c, x, y) - f(gy, c, x, y);
                    wy[p] = 1.0 / (norm(&e) + reg);
                }
            }
        }
        // Relative to `scale`: `r` is a difference of f32 terms of up to that size.
        let close = |got: f64, want: f64, scale: f64, what: &str| {
            assert!(
                (got - want).abs() <= 1e-5 * scale.max(1e-3),
                "{what}: {got} against {want}"
            );
        };
        for p in 0..n {
            let data = alpha * alpha * wd[p];
            close(f64::from(solve.op.data[p]), data, data, "alpha^2 w_d");
            close(f64::from(solve.op.ex[p]), wx[p], wx[p], "w_x");
            close(f64::from(solve.op.ey[p]), wy[p], wy[p], "w_y");
        }
        for c in 0..3 {
            // b and A x per pixel, edge by edge.
            let (mut b, mut ax) = (vec![0.0; n], vec![0.0; n]);
            for y in 0..h {
                for x in 0..w {
                    let p = y * w + x;
                    b[p] += alpha * alpha * wd[p] * f(ib, c, x, y);
                    ax[p] += alpha * alpha * wd[p] * f(&xs, c, x, y);
                    let mut edge = |q: usize, weight: f64, g: f64| {
                        let flux = weight * (f(&xs, c, q % w, q / w) - f(&xs, c, x, y));
                        (ax[p], ax[q]) = (ax[p] - flux, ax[q] + flux);
                        (b[p], b[q]) = (b[p] - weight * g, b[q] + weight * g);
                    };
                    if x + 1 < w {
                        edge(p + 1, wx[p], f(gx, c, x, y));
                    }
                    if y + 1 < h {
                        edge(p + w, wy[p], f(gy, c, x, y));
                    }
                }
            }
            let mut want_rr = 0.0;
            for p in 0..n {
                let (r, scale) = (b[p] - ax[p], b[p].abs().max(ax[p].abs()));
                close(f64::from(solve.r[c * n + p]), r, scale, "r");
                want_rr += r * r;
            }
            let want_bb = b.iter().map(|b| b * b).sum();
            close(bb[c], want_bb, want_bb, "b . b");
            close(rr[c], want_rr, want_rr, "r . r");
        }
    }

    /// One plan reconfigured between the combiner's two candidates gives each the bits of a
    /// plan made for it.
    #[test]
    fn reconfigured_solve_is_a_fresh_one() {
        let noisy = synthetic_frame(96, 64, 16.0, 5);
        let strong = PoissonL1Config {
            alpha: 2.5,
            step_change: 1e-3,
            ..PoissonL1Config::prior()
        };
        // The combiner's pair: the weak solve multigrid-preconditioned, the strong one not.
        let weak = PoissonL1Config {
            alpha: 0.5,
            reweight_steps: 9,
            preconditioner: Preconditioner::Multigrid,
            ..strong
        };
        assert_eq!(strong.preconditioner(), Some(Preconditioner::Jacobi));
        let run = |solve: &mut PoissonL1| {
            let mut out = Image::zeros(3, 96, 64);
            solve
                .reconstruct_into(&noisy, &mut out, &mut Report::default(), &Progress::none())
                .unwrap();
            out
        };
        let mut shared = PoissonL1::new_for(&[strong, weak], 96, 64).unwrap();
        for config in [strong, weak, strong, weak] {
            shared.reconfigure(config);
            let fresh = run(&mut PoissonL1::new(config, 96, 64).unwrap());
            assert_eq!(run(&mut shared), fresh, "alpha {}", config.alpha);
        }
    }

    /// The steps skipped after a fixed point are the ones that would have changed nothing:
    /// running them gives the same bits. On this frame the prior path's tolerance (1e-4) and
    /// weight (2.5), on a frame anchored to a clean image, leave a late step with no CG
    /// iteration, so steps are skipped.
    #[test]
    fn skipping_repeated_steps_changes_no_bit() {
        // Anchored to its reference, as the prior path anchors to a denoiser's output.
        let noisy = synthetic_frame(96, 64, 16.0, 3);
        let frame =
            crate::recon::prior::anchored(noisy.reference().unwrap().clone(), &noisy).unwrap();
        let config = PoissonL1Config {
            alpha: DEFAULT_PRIOR_ALPHA_L1,
            ..PoissonL1Config::prior()
        };
        let run = |skip: bool| solve(config, &frame, skip);
        let (skipped, note) = run(true);
        let (all, all_note) = run(false);
        assert!(note.contains("skipped"), "no step was skipped: {note}");
        assert!(!all_note.contains("skipped"), "{all_note}");
        assert_eq!(skipped.as_slice(), all.as_slice(), "{note}");
    }

    /// `cg_relative` ends a step's CG once an iteration moves the image by under that fraction
    /// of the previous step's move: fewer iterations, and an answer close to solving each step
    /// to `cg_change` (the validation frames: within 0.08 %, docs/benchmarks.md).
    #[test]
    fn cg_relative_saves_iterations_and_keeps_the_answer() {
        let frame = synthetic_frame(96, 64, 4.0, 7);
        let iterations = |note: &str| -> u32 {
            let at = note.find(" CG iterations").expect("the IRLS note");
            note[..at].rsplit(' ').next().unwrap().parse().unwrap()
        };
        let run = |cg_relative: f32| {
            let config = PoissonL1Config {
                cg_relative,
                step_change: 0.0,
                ..PoissonL1Config::default()
            };
            solve(config, &frame, true)
        };
        let (tight, tight_note) = run(0.0);
        let (loose, loose_note) = run(0.05);
        assert!(
            iterations(&loose_note) < iterations(&tight_note),
            "{loose_note} | {tight_note}"
        );
        let reference = frame.reference().unwrap();
        let error = |img: &Image| crate::metrics::compare(img, reference).unwrap().rel_mse;
        let ratio = error(&loose) / error(&tight);
        assert!((ratio - 1.0).abs() < 0.01, "relMSE ratio {ratio}");
    }

    /// `step_change` ends IRLS only once the regularisation is at its floor (step 4 here:
    /// 0.05 halves to the 1e-2 floor of the combiner's candidates), and then close to where
    /// every step would have led:
    /// IRLS converges linearly, each step moving the image by about 0.6x the last, so what the
    /// skipped steps would still do is about 1.5x the threshold (checked against 3x).
    #[test]
    fn step_change_stops_at_the_floor_close_to_every_step() {
        let noisy = synthetic_frame(96, 64, 4.0, 5);
        let frame =
            crate::recon::prior::anchored(noisy.reference().unwrap().clone(), &noisy).unwrap();
        let run = |step_change: f32| {
            let config = PoissonL1Config {
                alpha: 0.5,
                step_change,
                reg_floor: 1e-2,
                ..PoissonL1Config::prior()
            };
            solve(config, &frame, true)
        };
        let (_, note) = run(0.9);
        assert!(note.contains("IRLS: 5 of 12 steps (step 4 moved"), "{note}");
        let (all, all_note) = run(0.0);
        assert!(all_note.contains("IRLS: 12 of 12 steps"), "{all_note}");
        let tau = 1e-3;
        let (early, note) = run(tau);
        assert!(note.contains("moved the image by"), "{note}");
        let (a, b) = (early.as_slice(), all.as_slice());
        let n = a.len() / 3;
        for c in 0..3 {
            let ms = (c * n..(c + 1) * n)
                .map(|i| f64::from((a[i] - b[i]).powi(2) / (b[i] * b[i] + 0.01)))
                .sum::<f64>()
                / n as f64;
            assert!(
                ms.sqrt() <= 3.0 * f64::from(tau),
                "channel {c}: {} ({note})",
                ms.sqrt()
            );
        }
    }
}
