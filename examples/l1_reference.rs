//! How far is the library's L1 from the converged answer of its own IRLS?
//!
//! For each frame bundle (with a `reference` layer) this solves the same IRLS as
//! `src/recon/poisson_l1.rs` (same weight rule, regularisation schedule and step count) in
//! f64, each weighted system by preconditioned CG down to a relative residual of `--tol`
//! (default 1e-8), then runs the library's L1 with each requested variant and prints, per
//! frame, the relMSE of both against the reference and their ratio.
//!
//! ```text
//! cargo run --release --example l1_reference -- [--tol 1e-8] [--variant NAME=VALUE,...]... \
//!     FILE_OR_DIR...
//! ```
//!
//! A variant is a comma-separated list of L1 parameter assignments (`cg_tolerance=1e-3`) or a
//! preset name (`published`); the empty variant `default` is always run first.
//!
//! The solver here shares no code with the library: plain loops over the 5-point stencil, a
//! DCT preconditioner of its own (rustdct in f64) scaled by the weighted diagonal.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use rayon::prelude::*;
use rustdct::{DctPlanner, TransformType2And3};

use gdrecon::{io, metrics, Context, Frame, Method, MethodConfig, Plan, Policy, Progress};

/// Weight of the data term (the library's default).
const ALPHA: f64 = 0.2;

fn main() {
    if let Err(e) = run() {
        eprintln!("l1_reference: {e}");
        std::process::exit(1);
    }
}

fn run() -> Result<(), String> {
    let mut tol = 1e-8;
    // The schedule of the default configuration, unless overridden.
    let default = MethodConfig::default_for(Method::PoissonL1);
    let number = |name: &str| match default.get(name) {
        Ok(gdrecon::recon::Value::Float(v)) => f64::from(v),
        Ok(gdrecon::recon::Value::Int(v)) => v as f64,
        _ => unreachable!("L1 has a numeric parameter {name}"),
    };
    let mut steps = number("reweight_steps") as u32;
    let mut reg_min = number("reg_floor");
    let mut variants = vec!["default".to_owned()];
    let mut inputs = Vec::new();
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--tol" => {
                tol = args
                    .next()
                    .and_then(|v| v.parse().ok())
                    .ok_or("--tol needs a number")?
            }
            "--steps" => {
                steps = args
                    .next()
                    .and_then(|v| v.parse().ok())
                    .ok_or("--steps needs a number")?
            }
            "--reg-min" => {
                reg_min = args
                    .next()
                    .and_then(|v| v.parse().ok())
                    .ok_or("--reg-min needs a number")?
            }
            "--variant" => variants.push(args.next().ok_or("--variant needs a value")?),
            _ => inputs.push(PathBuf::from(a)),
        }
    }
    let files = bundles(&inputs)?;
    if files.is_empty() {
        return Err("no .exr bundles given".into());
    }
    let context = Context::new(Default::default()).map_err(|e| e.to_string())?;
    println!("frame\tbase\tconverged\tvariant\trelmse\tratio\tseconds\treport");
    let mut worst = vec![0.0f64; variants.len()];
    for file in &files {
        let frame = io::exr::read_bundle(file, Policy::Replace).map_err(|e| e.to_string())?;
        let Some(reference) = frame.reference() else {
            return Err(format!("{}: no reference layer", file.display()));
        };
        let name = file.file_name().unwrap().to_string_lossy().into_owned();
        let t0 = Instant::now();
        let (converged, iterations) = converged_l1(&frame, steps, reg_min, tol);
        let t_ref = t0.elapsed().as_secs_f64();
        let conv = metrics::compare(&converged, reference)
            .map_err(|e| e.to_string())?
            .rel_mse;
        let base = metrics::compare(frame.color(), reference)
            .map_err(|e| e.to_string())?
            .rel_mse;
        eprintln!("{name}: converged in {t_ref:.1} s, CG iterations per step {iterations:?}");
        for (i, v) in variants.iter().enumerate() {
            let config = variant(v)?;
            let (w, h) = frame.size();
            let mut plan = Plan::new(&context, &config, w, h).map_err(|e| e.to_string())?;
            let t = Instant::now();
            let (out, report) = plan
                .execute(&frame, &Progress::none())
                .map_err(|e| e.to_string())?;
            let secs = t.elapsed().as_secs_f64();
            let r = metrics::compare(&out, reference)
                .map_err(|e| e.to_string())?
                .rel_mse;
            worst[i] = worst[i].max(r / conv);
            println!(
                "{name}\t{base:.5e}\t{conv:.5e}\t{v}\t{r:.5e}\t{:.4}\t{secs:.3}\t{}",
                r / conv,
                report.notes.join("; ")
            );
        }
    }
    for (v, w) in variants.iter().zip(&worst) {
        println!("# worst ratio to converged, {v}: {w:.4}");
    }
    Ok(())
}

/// The L1 configuration of a variant: `default`, a preset name, or `NAME=VALUE,...`.
fn variant(spec: &str) -> Result<MethodConfig, String> {
    if spec == "default" {
        return Ok(MethodConfig::default_for(Method::PoissonL1));
    }
    if !spec.contains('=') {
        return MethodConfig::preset(Method::PoissonL1, spec).map_err(|e| e.to_string());
    }
    let mut config = MethodConfig::default_for(Method::PoissonL1);
    for a in spec.split(',') {
        config.set_assignment(a).map_err(|e| e.to_string())?;
    }
    Ok(config)
}

/// The `.exr` files among `inputs` (directories are listed, sorted).
fn bundles(inputs: &[PathBuf]) -> Result<Vec<PathBuf>, String> {
    let mut out = Vec::new();
    for p in inputs {
        if p.is_dir() {
            let mut v: Vec<PathBuf> = std::fs::read_dir(p)
                .map_err(|e| format!("{}: {e}", p.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|x| x == "exr"))
                .collect();
            v.sort();
            out.extend(v);
        } else {
            out.push(Path::new(p).to_path_buf());
        }
    }
    Ok(out)
}

/// The IRLS of the library's L1 solved tightly in f64; returns the image and the CG
/// iterations of each step (largest over channels).
fn converged_l1(frame: &Frame, steps: u32, reg_min: f64, tol: f64) -> (gdrecon::Image, Vec<usize>) {
    let (w, h) = frame.size();
    let n = w * h;
    let plane = |img: &gdrecon::Image, c: usize| -> Vec<f64> {
        img.plane(c).iter().map(|&v| f64::from(v)).collect()
    };
    let ib: Vec<Vec<f64>> = (0..3).map(|c| plane(frame.color(), c)).collect();
    let gx: Vec<Vec<f64>> = (0..3).map(|c| plane(frame.dx(), c)).collect();
    let gy: Vec<Vec<f64>> = (0..3).map(|c| plane(frame.dy(), c)).collect();
    let mut x = ib.clone();
    let mut wt = Weights {
        w,
        h,
        d: vec![1.0; n],
        x: vec![1.0; n],
        y: vec![1.0; n],
    };
    for y in 0..h {
        wt.x[y * w + w - 1] = 0.0;
    }
    wt.y[(h - 1) * w..].fill(0.0);
    let dct = Dct::new(w, h);
    let mut iterations = Vec::new();
    for k in 0..steps {
        if k > 0 {
            wt.reweight(
                &x,
                &ib,
                &gx,
                &gy,
                (0.05 * 0.5f64.powi(k as i32 - 1)).max(reg_min),
            );
        }
        let scale = wt.scale();
        let its = x
            .par_iter_mut()
            .enumerate()
            .map(|(c, xc)| {
                let b = wt.rhs(&ib[c], &gx[c], &gy[c]);
                pcg(&wt, &dct, &scale, &b, xc, tol)
            })
            .collect::<Vec<_>>();
        iterations.push(its.into_iter().max().unwrap_or(0));
    }
    let img = gdrecon::Image::from_fn(3, w, h, |(c, px, py)| x[c][py * w + px] as f32);
    (img, iterations)
}

/// Row weights of one IRLS step: data, horizontal and vertical rows (0 where a row does not
/// exist).
struct Weights {
    w: usize,
    h: usize,
    d: Vec<f64>,
    x: Vec<f64>,
    y: Vec<f64>,
}

impl Weights {
    fn reweight(
        &mut self,
        x: &[Vec<f64>],
        ib: &[Vec<f64>],
        gx: &[Vec<f64>],
        gy: &[Vec<f64>],
        reg: f64,
    ) {
        let (w, h) = (self.w, self.h);
        let norm = |f: &dyn Fn(usize) -> f64| (0..3).map(f).map(|v| v * v).sum::<f64>().sqrt();
        let mut sum = 0.0;
        for p in 0..w * h {
            let (px, py) = (p % w, p / w);
            self.d[p] = 1.0 / (ALPHA * norm(&|c| x[c][p] - ib[c][p]) + reg);
            sum += self.d[p];
            if px + 1 < w {
                self.x[p] = 1.0 / (norm(&|c| x[c][p + 1] - x[c][p] - gx[c][p]) + reg);
                sum += self.x[p];
            }
            if py + 1 < h {
                self.y[p] = 1.0 / (norm(&|c| x[c][p + w] - x[c][p] - gy[c][p]) + reg);
                sum += self.y[p];
            }
        }
        let rows = w * h + h * (w - 1) + (h - 1) * w;
        let s = rows as f64 / sum;
        for v in self.d.iter_mut().chain(&mut self.x).chain(&mut self.y) {
            *v *= s;
        }
    }

    /// `A v` for `A = alpha^2 W_d + D_x^T W_x D_x + D_y^T W_y D_y`.
    fn apply(&self, v: &[f64], out: &mut [f64]) {
        let (w, h) = (self.w, self.h);
        for p in 0..w * h {
            out[p] = ALPHA * ALPHA * self.d[p] * v[p];
        }
        for p in 0..w * h {
            if p % w + 1 < w {
                let e = self.x[p] * (v[p + 1] - v[p]);
                out[p] -= e;
                out[p + 1] += e;
            }
            if p / w + 1 < h {
                let e = self.y[p] * (v[p + w] - v[p]);
                out[p] -= e;
                out[p + w] += e;
            }
        }
    }

    /// `b = alpha^2 W_d I_b + D_x^T W_x dx + D_y^T W_y dy`.
    fn rhs(&self, ib: &[f64], gx: &[f64], gy: &[f64]) -> Vec<f64> {
        let (w, h) = (self.w, self.h);
        let mut b: Vec<f64> = (0..w * h)
            .map(|p| ALPHA * ALPHA * self.d[p] * ib[p])
            .collect();
        for p in 0..w * h {
            if p % w + 1 < w {
                b[p] -= self.x[p] * gx[p];
                b[p + 1] += self.x[p] * gx[p];
            }
            if p / w + 1 < h {
                b[p] -= self.y[p] * gy[p];
                b[p + w] += self.y[p] * gy[p];
            }
        }
        b
    }

    /// `sqrt(diag(L) / diag(A))` per pixel, `L` the unweighted operator.
    fn scale(&self) -> Vec<f64> {
        let (w, h) = (self.w, self.h);
        (0..w * h)
            .map(|p| {
                let (px, py) = (p % w, p / w);
                let mut da = ALPHA * ALPHA * self.d[p] + self.x[p] + self.y[p];
                let mut dl = ALPHA * ALPHA;
                if px > 0 {
                    da += self.x[p - 1];
                    dl += 1.0;
                }
                if px + 1 < w {
                    dl += 1.0;
                }
                if py > 0 {
                    da += self.y[p - w];
                    dl += 1.0;
                }
                if py + 1 < h {
                    dl += 1.0;
                }
                if da > 0.0 {
                    (dl / da).sqrt()
                } else {
                    1.0
                }
            })
            .collect()
    }
}

/// Preconditioned CG on `A x = b` from the given `x`, to `||r|| <= tol ||b||`, the DCT solve
/// scaled by `s` (`Weights::scale`) as preconditioner; returns the iterations taken.
fn pcg(wt: &Weights, dct: &Dct, s: &[f64], b: &[f64], x: &mut [f64], tol: f64) -> usize {
    let n = b.len();
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(a, b)| a * b).sum::<f64>();
    let precondition = |r: &[f64]| -> Vec<f64> {
        let mut z: Vec<f64> = r.iter().zip(s).map(|(r, s)| r * s).collect();
        dct.solve(&mut z);
        z.iter_mut().zip(s).for_each(|(z, s)| *z *= s);
        z
    };
    let mut q = vec![0.0; n];
    wt.apply(x, &mut q);
    let mut r: Vec<f64> = b.iter().zip(&q).map(|(b, q)| b - q).collect();
    let bb = dot(b, b).max(1e-300);
    let mut z = precondition(&r);
    let mut p = z.clone();
    let mut rz = dot(&r, &z);
    for it in 0..100_000 {
        if dot(&r, &r) <= tol * tol * bb {
            return it;
        }
        wt.apply(&p, &mut q);
        let a = rz / dot(&p, &q);
        for i in 0..n {
            x[i] += a * p[i];
            r[i] -= a * q[i];
        }
        z = precondition(&r);
        let rz_new = dot(&r, &z);
        let beta = rz_new / rz;
        rz = rz_new;
        for i in 0..n {
            p[i] = z[i] + beta * p[i];
        }
    }
    100_000
}

/// `(alpha^2 + D^T D)^-1` with Neumann boundaries by the 2-D DCT-II (rustdct, f64).
struct Dct {
    w: usize,
    h: usize,
    rows: Arc<dyn TransformType2And3<f64>>,
    cols: Arc<dyn TransformType2And3<f64>>,
    /// `4 / (w h) / (alpha^2 + lambda_x + lambda_y)`, row-major.
    inv: Vec<f64>,
}

impl Dct {
    fn new(w: usize, h: usize) -> Self {
        let mut planner = DctPlanner::new();
        let eig =
            |k: usize, n: usize| 2.0 - 2.0 * (std::f64::consts::PI * k as f64 / n as f64).cos();
        let inv = (0..w * h)
            .map(|p| 4.0 / (w * h) as f64 / (ALPHA * ALPHA + eig(p % w, w) + eig(p / w, h)))
            .collect();
        Dct {
            w,
            h,
            rows: planner.plan_dct2(w),
            cols: planner.plan_dct2(h),
            inv,
        }
    }

    fn solve(&self, v: &mut [f64]) {
        let (w, h) = (self.w, self.h);
        v.chunks_mut(w).for_each(|row| self.rows.process_dct2(row));
        let mut t = transpose(v, w, h);
        t.chunks_mut(h).for_each(|col| self.cols.process_dct2(col));
        for x in 0..w {
            for y in 0..h {
                t[x * h + y] *= self.inv[y * w + x];
            }
        }
        t.chunks_mut(h).for_each(|col| self.cols.process_dct3(col));
        v.copy_from_slice(&transpose(&t, h, w));
        v.chunks_mut(w).for_each(|row| self.rows.process_dct3(row));
    }
}

/// The `h x w` transpose of a row-major `w`-wide plane.
fn transpose(v: &[f64], w: usize, h: usize) -> Vec<f64> {
    let mut t = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            t[x * h + y] = v[y * w + x];
        }
    }
    t
}
