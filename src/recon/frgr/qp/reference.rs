//! The gradient-guided filter as released before the lane-parallel rewrite of `qp.rs`: one
//! pixel at a time, windows gathered through `reflect`, the scalar cyclic solver. Kept as the
//! reference the fast path must reproduce (tests only), and for the exact solver (SMO) the
//! cyclic solver's objective is checked against.

use rayon::prelude::*;

use super::{QpLevel, Skipped, MAX_K, MAX_N};
use crate::image::Image;
use crate::recon::frgr::util::reflect;

/// The state of one simplex QP solve, `Q = B^T B + diag(v)`.
pub(crate) struct Simplex<'a> {
    pub b: &'a [[f32; MAX_N]],
    pub v: &'a [f32],
    pub n: usize,
}

impl Simplex<'_> {
    /// Runs the cyclic vertex line search from `w` (on the simplex) in O(K) per iteration;
    /// returns the number of iterations.
    pub fn solve(&self, w: &mut [f32], max_iter: usize) -> usize {
        let (n, k) = (self.n, self.b.len());
        let mut s = [0.0f32; MAX_K];
        let mut col2 = [0.0f32; MAX_N];
        for (row, sk) in self.b.iter().zip(s.iter_mut()) {
            *sk = (0..n).map(|q| row[q] * w[q]).sum();
            for q in 0..n {
                col2[q] += row[q] * row[q];
            }
        }
        let mut svw: f32 = (0..n).map(|q| self.v[q] * w[q] * w[q]).sum();
        let mut scale = 1.0f32;
        let mut quiet = 0;
        let mut it = 0;
        while it < max_iter && quiet < n {
            it += 1;
            let i = it % n;
            if i == 0 {
                // Once per sweep (amortised O(K)): fold the scale in, renormalise the sum to 1
                // and recompute the projections, so that f32 drift cannot accumulate.
                let total: f32 = w[..n].iter().sum::<f32>() * scale;
                for x in &mut w[..n] {
                    *x *= scale / total;
                }
                scale = 1.0;
                for (row, sk) in self.b.iter().zip(s.iter_mut()) {
                    *sk = (0..n).map(|q| row[q] * w[q]).sum();
                }
                svw = (0..n).map(|q| self.v[q] * w[q] * w[q]).sum();
            }
            let wi = scale * w[i];
            let mut qw_i = self.v[i] * wi;
            let mut ss = 0.0;
            for (row, &sr) in self.b.iter().zip(&s[..k]) {
                qw_i += row[i] * sr;
                ss += sr * sr;
            }
            let wqw = ss + svw;
            let dqw = qw_i - wqw;
            let dqd = col2[i] + self.v[i] - 2.0 * qw_i + wqw;
            let t = -dqw / dqd;
            let t = if t.is_finite() {
                t.clamp(0.0, 1.0)
            } else {
                0.0
            };
            if t < 1e-8 {
                quiet += 1;
                continue;
            }
            quiet = 0;
            let keep = 1.0 - t;
            for (sr, row) in s[..k].iter_mut().zip(self.b) {
                *sr = keep * *sr + t * row[i];
            }
            svw = keep * keep * svw + 2.0 * t * keep * self.v[i] * wi + t * t * self.v[i];
            let new_scale = keep * scale;
            if new_scale < 1e-12 {
                w[..n].fill(0.0);
                w[i] = 1.0;
                scale = 1.0;
            } else {
                w[i] += t / new_scale;
                scale = new_scale;
            }
        }
        for x in &mut w[..n] {
            *x *= scale;
        }
        it
    }

    /// Solves the QP to optimality (KKT gap below `tol`) by pairwise steps (SMO): move weight
    /// from the support index with the largest `(Qw)_j` to the index with the smallest, with
    /// the exact line search. O(K n) per iteration, linear convergence (`Q` is positive
    /// definite when `v > 0`). For tests and as the `exact` reference of the release's
    /// early-stopped cyclic solver.
    pub fn solve_exact(&self, w: &mut [f32], max_iter: usize, tol: f64) -> usize {
        let n = self.n;
        let mut wd: Vec<f64> = w[..n].iter().map(|&x| f64::from(x)).collect();
        let qw = |wd: &[f64]| -> Vec<f64> {
            let s: Vec<f64> = self
                .b
                .iter()
                .map(|r| (0..n).map(|q| f64::from(r[q]) * wd[q]).sum())
                .collect();
            (0..n)
                .map(|j| {
                    self.b
                        .iter()
                        .zip(&s)
                        .map(|(r, s)| f64::from(r[j]) * s)
                        .sum::<f64>()
                        + f64::from(self.v[j]) * wd[j]
                })
                .collect()
        };
        let mut it = 0;
        while it < max_iter {
            it += 1;
            let g = qw(&wd);
            let i = (0..n).min_by(|&a, &b| g[a].total_cmp(&g[b])).unwrap_or(0);
            let Some(j) = (0..n)
                .filter(|&j| wd[j] > 0.0)
                .max_by(|&a, &b| g[a].total_cmp(&g[b]))
            else {
                break;
            };
            let gap = g[j] - g[i];
            if gap <= tol {
                break;
            }
            let bij: f64 = self
                .b
                .iter()
                .map(|r| f64::from(r[i]) * f64::from(r[j]))
                .sum();
            let bii: f64 = self.b.iter().map(|r| f64::from(r[i]).powi(2)).sum();
            let bjj: f64 = self.b.iter().map(|r| f64::from(r[j]).powi(2)).sum();
            let curv = bii + bjj - 2.0 * bij + f64::from(self.v[i]) + f64::from(self.v[j]);
            let t = if curv > 0.0 {
                (gap / curv).min(wd[j])
            } else {
                wd[j]
            };
            wd[i] += t;
            wd[j] -= t;
        }
        for (x, &d) in w[..n].iter_mut().zip(&wd) {
            *x = d as f32;
        }
        it
    }
}

/// One row's colour, variance, skipped pixels and iterations.
type RowOut = (Vec<f32>, Vec<f32>, Skipped, Vec<u32>);

/// Runs the filter over a level; returns the filtered colour, its variance, the pixels
/// skipped and each pixel's solver iterations (0 when skipped), row-major.
///
/// A pixel whose whole window has zero colour and zero variance is skipped: its output is a
/// convex combination of zeros whatever the weights, so 0 (and variance 0) exactly, and the QP
/// is not solved (black backgrounds, letterboxing, masked-out regions). A converged pixel
/// (`level.converged`) keeps its colour and variance.
pub(crate) fn gradient_guided_filter(level: &QpLevel) -> (Image, Image, Skipped, Vec<u32>) {
    let (w, h) = level.img.size();
    let n_px = w * h;
    let r = level.radius as isize;
    let side = 2 * level.radius + 1;
    let n = side * side;
    // Rows for every present term: the start counts them all; the dropped ones are removed
    // before the solve.
    let al = level.present_alphas();
    let sq: [f32; 5] = al.map(f32::sqrt);
    let img = level.img.as_slice();
    let var = level.var.as_slice();
    let enh = level.enhanced.as_slice();
    let guide = level.guide.as_slice();
    let up = level.up.map(|(u, _)| u.as_slice());
    let up_var = level.up.map(|(_, v)| v.as_slice());
    let alb = level.albedo.map(Image::as_slice);
    let nrm = level.normal.map(Image::as_slice);
    let empty: Vec<bool> = (0..n_px)
        .into_par_iter()
        .map(|q| (0..3).all(|c| img[c * n_px + q] == 0.0 && var[c * n_px + q] == 0.0))
        .collect();
    let rows: Vec<RowOut> = (0..h)
        .into_par_iter()
        .map(|y| {
            let mut out = vec![0.0f32; 3 * w];
            let mut out_var = vec![0.0f32; 3 * w];
            let mut skipped = Skipped::default();
            let mut iters = vec![0u32; w];
            let mut b = [[0.0f32; MAX_N]; MAX_K];
            let mut v = [0.0f32; MAX_N];
            let mut wts = [0.0f32; MAX_N];
            let mut idx = [0usize; MAX_N];
            for x in 0..w {
                let p = y * w + x;
                let mut j = 0;
                for dy in -r..=r {
                    let yy = reflect(y as isize + dy, h);
                    for dx in -r..=r {
                        idx[j] = yy * w + reflect(x as isize + dx, w);
                        j += 1;
                    }
                }
                if idx[..n].iter().all(|&q| empty[q]) {
                    skipped.empty += 1;
                    continue;
                }
                if level.converged.is_some_and(|m| m[p]) {
                    for c in 0..3 {
                        out[c * w + x] = img[c * n_px + p];
                        out_var[c * w + x] = var[c * n_px + p];
                    }
                    skipped.converged += 1;
                    continue;
                }
                for (j, &q) in idx[..n].iter().enumerate() {
                    let mut vq = 0.0;
                    for c in 0..3 {
                        vq += var[c * n_px + q].max(0.0);
                        if let Some(uv) = up_var {
                            vq += uv[c * n_px + q].max(0.0);
                        }
                    }
                    v[j] = vq;
                }
                let mut k = 0;
                let mut push = |k: &mut usize, f: &dyn Fn(usize, usize) -> f32, a: usize| {
                    if al[a] == 0.0 {
                        return;
                    }
                    for c in 0..3 {
                        for (j, &q) in idx[..n].iter().enumerate() {
                            b[*k][j] = sq[a] * f(c, q);
                        }
                        *k += 1;
                    }
                };
                let resid = |c: usize, q: usize| match up {
                    Some(u) => img[c * n_px + q] - u[c * n_px + q],
                    None => 0.0,
                };
                push(&mut k, &|c, q| enh[c * n_px + q] - enh[c * n_px + p], 0);
                if let Some(a) = alb {
                    push(
                        &mut k,
                        &|c, q| a[c * n_px + q] - a[c * n_px + p] + resid(c, q),
                        1,
                    );
                }
                if let Some(f) = nrm {
                    push(
                        &mut k,
                        &|c, q| f[c * n_px + q] - f[c * n_px + p] + resid(c, q),
                        2,
                    );
                }
                push(&mut k, &|c, q| img[c * n_px + q] - guide[c * n_px + p], 3);
                if let Some(u) = up {
                    push(&mut k, &|c, q| u[c * n_px + q] - u[c * n_px + p], 4);
                }
                // Initial weights: inverse root of each neighbour's total (unweighted) cost.
                let mut total = 0.0;
                for j in 0..n {
                    let mut e = v[j] + 0.1;
                    for (row, a) in b[..k].iter().zip(0..) {
                        let s = sq[term_of(a, &al)];
                        let raw = if s > 0.0 { row[j] / s } else { 0.0 };
                        e += raw * raw;
                    }
                    wts[j] = 1.0 / e.sqrt();
                    total += wts[j];
                }
                for x in &mut wts[..n] {
                    *x /= total;
                }
                let mut kept = 0;
                for row in 0..k {
                    if !level.dropped[term_of(row, &al)] {
                        b[kept] = b[row];
                        kept += 1;
                    }
                }
                iters[x] = Simplex {
                    b: &b[..kept],
                    v: &v[..n],
                    n,
                }
                .solve(&mut wts, 3 * n + 1) as u32;
                for c in 0..3 {
                    let (mut o, mut ov) = (0.0f32, 0.0f32);
                    for (j, &q) in idx[..n].iter().enumerate() {
                        o += wts[j] * img[c * n_px + q];
                        ov += wts[j] * wts[j] * var[c * n_px + q];
                    }
                    out[c * w + x] = o;
                    out_var[c * w + x] = ov;
                }
            }
            (out, out_var, skipped, iters)
        })
        .collect();
    let mut out = Image::zeros(3, w, h);
    let mut out_var = Image::zeros(3, w, h);
    let skipped = rows.iter().fold(Skipped::default(), |a, r| Skipped {
        empty: a.empty + r.2.empty,
        converged: a.converged + r.2.converged,
    });
    for (y, (o, ov, _, _)) in rows.iter().enumerate() {
        for c in 0..3 {
            out.plane_mut(c)
                .row_mut(y)
                .as_slice_mut()
                .expect("contiguous")
                .copy_from_slice(&o[c * w..(c + 1) * w]);
            out_var
                .plane_mut(c)
                .row_mut(y)
                .as_slice_mut()
                .expect("contiguous")
                .copy_from_slice(&ov[c * w..(c + 1) * w]);
        }
    }
    let iters = rows.into_iter().flat_map(|r| r.3).collect();
    (out, out_var, skipped, iters)
}

/// Which of the five terms the `row`-th built row belongs to (rows come in threes, skipping
/// terms that are off).
fn term_of(row: usize, al: &[f32; 5]) -> usize {
    let mut seen = 0;
    for (a, &alpha) in al.iter().enumerate() {
        if alpha != 0.0 {
            if row < seen + 3 {
                return a;
            }
            seen += 3;
        }
    }
    4
}

#[test]
fn term_rows_map_back_to_their_terms() {
    let al = [1.0, 0.0, 0.5, 0.2, 0.0];
    let got: Vec<usize> = (0..9).map(|r| term_of(r, &al)).collect();
    assert_eq!(got, [0, 0, 0, 2, 2, 2, 3, 3, 3]);
}
