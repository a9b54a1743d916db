//! Screened Poisson reconstruction, L1: the robust variant of gradient-domain path tracing.
//!
//! Minimises the group-L1 energy `sum_p ||alpha (I - I_b)(p)|| + ||(D_x I - dx)(p)|| +
//! ||(D_y I - dy)(p)||`, where each norm is the Euclidean norm over R, G, B of one residual
//! row, by iteratively reweighted least squares (IRLS), as the reference solver does:
//! - step 0 uses unit weights (the L2 problem); step `k >= 1` sets, per residual row,
//!   `w = 1 / (||e_row|| + reg_k)` with `reg_k = 0.05 * 0.5^(k-1)`, one weight shared by
//!   R, G, B, then rescales all weights so that they average 1 over all rows;
//! - each weighted system `(alpha^2 W_d + D_x^T W_x D_x + D_y^T W_y D_y) I = alpha^2 W_d I_b +
//!   D_x^T W_x dx + D_y^T W_y dy` is solved by conjugate gradients warm-started from the
//!   previous step (from `I_b` at step 0).
//!
//! Where we differ: CG is preconditioned by the exact L2 solve (the DCT inverse of
//! `alpha^2 + D^T D`, which equals the system matrix at unit weights), and stops at a relative
//! residual tolerance. Step 0 then converges in one iteration, and later steps in a few.
//! [`PoissonL1Config::published`] reproduces the reference schedule (20 steps x 50 plain CG
//! iterations) for comparison.

use rayon::prelude::*;

use super::dct::DctPoisson;
use super::ops::{apply_weighted, grad_adjoint, plane_sums, Dims, RowWeights};
use super::poisson_l2::check_alpha;
use super::{Method, Reconstructor};
use crate::error::{Error, Result};
use crate::frame::Frame;
use crate::image::Image;
use crate::progress::Progress;
use crate::report::Report;

/// Settings of the L1 (IRLS) screened Poisson solve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoissonL1Config {
    /// Weight of the data term, as in L2; must be positive. Default 0.2.
    pub alpha: f32,
    /// IRLS steps, the first with unit weights. Default 20.
    pub reweight_steps: u32,
    /// Maximum CG iterations per step. Default 8.
    pub cg_iterations: u32,
    /// Stop CG when every channel's residual norm falls below this fraction of its
    /// right-hand side's norm; 0 runs all `cg_iterations`. Default 1e-3.
    pub cg_tolerance: f32,
    /// Precondition CG with the exact L2 (DCT) solve. Default true.
    pub preconditioned: bool,
}

impl Default for PoissonL1Config {
    fn default() -> Self {
        PoissonL1Config {
            alpha: 0.2,
            reweight_steps: 20,
            cg_iterations: 8,
            cg_tolerance: 1e-3,
            preconditioned: true,
        }
    }
}

impl PoissonL1Config {
    /// The published schedule of gradient-domain path tracing's reference solver:
    /// 20 reweighting steps x 50 unpreconditioned CG iterations, no early stop.
    pub fn published() -> Self {
        PoissonL1Config {
            alpha: 0.2,
            reweight_steps: 20,
            cg_iterations: 50,
            cg_tolerance: 0.0,
            preconditioned: false,
        }
    }

    pub(crate) fn validate(&self) -> Result<()> {
        check_alpha(self.alpha, f32::MIN_POSITIVE)?;
        if self.reweight_steps == 0 || self.reweight_steps > 1000 {
            return Err(Error::arg(format!(
                "reweight_steps is {}, expected 1 to 1000",
                self.reweight_steps
            )));
        }
        if self.cg_iterations == 0 || self.cg_iterations > 100_000 {
            return Err(Error::arg(format!(
                "cg_iterations is {}, expected 1 to 100000",
                self.cg_iterations
            )));
        }
        if !(self.cg_tolerance.is_finite() && (0.0..1.0).contains(&self.cg_tolerance)) {
            return Err(Error::arg(format!(
                "cg_tolerance is {}, expected a value in [0, 1)",
                self.cg_tolerance
            )));
        }
        Ok(())
    }
}

/// A planned L1 solve for one size; all buffers are allocated here and reused.
pub struct PoissonL1 {
    dims: Dims,
    cfg: PoissonL1Config,
    precond: Option<DctPoisson>,
    x: Vec<f32>,
    r: Vec<f32>,
    z: Vec<f32>,
    p: Vec<f32>,
    q: Vec<f32>,
    b: Vec<f32>,
    wd: Vec<f32>,
    wx: Vec<f32>,
    wy: Vec<f32>,
    partials: Vec<f64>,
}

/// What one CG solve did.
struct CgOutcome {
    iterations: u32,
    rel_residual: f64,
}

impl PoissonL1 {
    /// Plans the solve for `width` x `height` frames.
    pub fn new(config: PoissonL1Config, width: usize, height: usize) -> Result<Self> {
        config.validate()?;
        let dims = Dims {
            w: width,
            h: height,
        };
        let n = dims.len();
        let v3 = || vec![0.0f32; 3 * n];
        Ok(PoissonL1 {
            dims,
            cfg: config,
            precond: config
                .preconditioned
                .then(|| DctPoisson::new(dims, config.alpha)),
            x: v3(),
            r: v3(),
            z: v3(),
            p: v3(),
            q: v3(),
            b: v3(),
            wd: vec![1.0; n],
            wx: vec![1.0; n],
            wy: vec![1.0; n],
            partials: Vec::new(),
        })
    }

    /// IRLS weights from the residuals of the current `x`, normalised to mean 1.
    fn reweight(&mut self, frame: &Frame, step: u32) {
        let Dims { w, h } = self.dims;
        let n = w * h;
        let reg = 0.05f32 * 0.5f32.powi(step as i32 - 1);
        let alpha = self.cfg.alpha;
        let (x, ib) = (&self.x, frame.color().as_slice());
        let (gx, gy) = (frame.dx().as_slice(), frame.dy().as_slice());
        let norm3 =
            |f: &dyn Fn(usize) -> f32| -> f32 { (0..3).map(|c| f(c) * f(c)).sum::<f32>().sqrt() };
        self.wd
            .par_chunks_mut(w)
            .zip(self.wx.par_chunks_mut(w))
            .zip(self.wy.par_chunks_mut(w))
            .enumerate()
            .map(|(yy, ((wd, wx), wy))| {
                let mut sum = 0.0f64;
                for xx in 0..w {
                    let i = yy * w + xx;
                    let ed = alpha * norm3(&|c| x[c * n + i] - ib[c * n + i]);
                    wd[xx] = 1.0 / (ed + reg);
                    sum += f64::from(wd[xx]);
                    wx[xx] = if xx + 1 < w {
                        let e = norm3(&|c| x[c * n + i + 1] - x[c * n + i] - gx[c * n + i]);
                        1.0 / (e + reg)
                    } else {
                        0.0
                    };
                    wy[xx] = if yy + 1 < h {
                        let e = norm3(&|c| x[c * n + i + w] - x[c * n + i] - gy[c * n + i]);
                        1.0 / (e + reg)
                    } else {
                        0.0
                    };
                    sum += f64::from(wx[xx]) + f64::from(wy[xx]);
                }
                sum
            })
            .collect_into_vec(&mut self.partials);
        let rows = n + h * (w - 1) + (h - 1) * w;
        let mean = self.partials.iter().sum::<f64>() / rows as f64;
        let s = (1.0 / mean) as f32;
        for v in [&mut self.wd, &mut self.wx, &mut self.wy] {
            v.par_iter_mut().for_each(|w| *w *= s);
        }
    }

    /// `b = alpha^2 W_d I_b + D_x^T W_x dx + D_y^T W_y dy`; uses `z` and `q` as scratch.
    fn weighted_rhs(&mut self, frame: &Frame) {
        let n = self.dims.len();
        let alpha2 = self.cfg.alpha * self.cfg.alpha;
        let (ib, gx, gy) = (
            frame.color().as_slice(),
            frame.dx().as_slice(),
            frame.dy().as_slice(),
        );
        for c in 0..3 {
            let r = c * n..(c + 1) * n;
            let (zx, qy) = (&mut self.z[r.clone()], &mut self.q[r.clone()]);
            multiply(&gx[r.clone()], &self.wx, zx);
            multiply(&gy[r.clone()], &self.wy, qy);
            let b = &mut self.b[r.clone()];
            grad_adjoint(zx, qy, self.dims, b);
            b.par_iter_mut()
                .zip(ib[r].par_iter().zip(self.wd.par_iter()))
                .for_each(|(v, (&i, &wd))| *v += alpha2 * wd * i);
        }
    }

    fn apply(&self, src: &[f32], dst: &mut [f32]) {
        let n = self.dims.len();
        let wt = RowWeights {
            data: &self.wd,
            x: &self.wx,
            y: &self.wy,
        };
        let alpha2 = self.cfg.alpha * self.cfg.alpha;
        for (s, d) in src.chunks(n).zip(dst.chunks_mut(n)) {
            apply_weighted(s, alpha2, &wt, self.dims, d);
        }
    }

    fn precondition(&mut self) {
        self.z.copy_from_slice(&self.r);
        if let Some(m) = self.precond.as_mut() {
            m.solve(&mut self.z);
        }
    }

    fn dots(&mut self, which: Dot) -> [f64; 3] {
        let (a, b) = match which {
            Dot::RR => (&self.r, &self.r),
            Dot::RZ => (&self.r, &self.z),
            Dot::PQ => (&self.p, &self.q),
            Dot::BB => (&self.b, &self.b),
        };
        let s = plane_sums(
            a,
            b,
            self.dims.w,
            self.dims.len(),
            &mut self.partials,
            |x, y| f64::from(x) * f64::from(y),
        );
        [s[0], s[1], s[2]]
    }

    /// Preconditioned CG on the current weighted system, warm-started from `x`.
    fn cg(&mut self, progress: &dyn Fn(f64) -> Result<()>) -> Result<CgOutcome> {
        let n = self.dims.len();
        let tol2 = f64::from(self.cfg.cg_tolerance).powi(2);
        let bb = self.dots(Dot::BB).map(|v| v.max(f64::MIN_POSITIVE));
        let x = std::mem::take(&mut self.x);
        let mut q = std::mem::take(&mut self.q);
        self.apply(&x, &mut q);
        (self.x, self.q) = (x, q);
        self.r
            .par_iter_mut()
            .zip(self.b.par_iter().zip(self.q.par_iter()))
            .for_each(|(r, (&b, &q))| *r = b - q);
        let rel = |rr: [f64; 3]| (0..3).map(|c| rr[c] / bb[c]).fold(0.0, f64::max);
        let mut rr = self.dots(Dot::RR);
        if rel(rr) <= tol2 {
            return Ok(CgOutcome {
                iterations: 0,
                rel_residual: rel(rr).sqrt(),
            });
        }
        self.precondition();
        let mut rz = self.dots(Dot::RZ);
        self.p.copy_from_slice(&self.z);
        let max = self.cfg.cg_iterations;
        let mut it = 0;
        while it < max {
            let p = std::mem::take(&mut self.p);
            let mut q = std::mem::take(&mut self.q);
            self.apply(&p, &mut q);
            (self.p, self.q) = (p, q);
            let pq = self.dots(Dot::PQ);
            let step: [f32; 3] = std::array::from_fn(|c| {
                let converged = rr[c] <= tol2 * bb[c];
                if converged || !(pq[c] > 0.0) {
                    0.0
                } else {
                    (rz[c] / pq[c]) as f32
                }
            });
            for c in 0..3 {
                let r = c * n..(c + 1) * n;
                let a = step[c];
                self.x[r.clone()]
                    .par_iter_mut()
                    .zip(self.r[r.clone()].par_iter_mut())
                    .zip(self.p[r.clone()].par_iter().zip(self.q[r].par_iter()))
                    .for_each(|((x, r), (&p, &q))| {
                        *x += a * p;
                        *r -= a * q;
                    });
            }
            it += 1;
            rr = self.dots(Dot::RR);
            progress(f64::from(it) / f64::from(max))?;
            if rel(rr) <= tol2 {
                break;
            }
            if it == max {
                break;
            }
            self.precondition();
            let rz_new = self.dots(Dot::RZ);
            let beta: [f32; 3] = std::array::from_fn(|c| {
                if rz[c] > 0.0 {
                    (rz_new[c] / rz[c]) as f32
                } else {
                    0.0
                }
            });
            rz = rz_new;
            for c in 0..3 {
                let r = c * n..(c + 1) * n;
                let bc = beta[c];
                self.p[r.clone()]
                    .par_iter_mut()
                    .zip(self.z[r].par_iter())
                    .for_each(|(p, &z)| *p = z + bc * *p);
            }
        }
        Ok(CgOutcome {
            iterations: it,
            rel_residual: rel(rr).sqrt(),
        })
    }
}

#[derive(Clone, Copy)]
enum Dot {
    RR,
    RZ,
    PQ,
    BB,
}

fn multiply(a: &[f32], b: &[f32], out: &mut [f32]) {
    out.par_iter_mut()
        .zip(a.par_iter().zip(b.par_iter()))
        .for_each(|(o, (&a, &b))| *o = a * b);
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
        for v in [&mut self.wd, &mut self.wx, &mut self.wy] {
            v.fill(1.0);
        }
        let (mut total_iters, mut last_rel) = (0u32, 0.0f64);
        let start = std::time::Instant::now();
        for step in 0..steps {
            if step > 0 {
                self.reweight(frame, step);
            }
            self.weighted_rhs(frame);
            let scoped =
                progress.scoped(f64::from(step) / f64::from(steps), 1.0 / f64::from(steps));
            let outcome = self.cg(&|f| scoped.update(f))?;
            total_iters += outcome.iterations;
            last_rel = outcome.rel_residual;
        }
        report.stages.push(crate::report::Stage {
            name: "irls".into(),
            time: start.elapsed(),
        });
        report.note(format!(
            "IRLS: {steps} steps, {total_iters} CG iterations ({}), last relative residual {last_rel:.2e}",
            if self.precond.is_some() {
                "DCT-preconditioned"
            } else {
                "unpreconditioned"
            }
        ));
        out.as_mut_slice().copy_from_slice(&self.x);
        progress.update(1.0)
    }
}
