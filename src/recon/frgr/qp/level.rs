//! What one level hands the QP: its images and term weights, and which optional bias terms
//! vanish.

use rayon::prelude::*;

use crate::image::Image;

/// Largest window: radius 4, 81 neighbours.
pub(crate) const MAX_N: usize = 81;
/// Most bias rows: 5 terms x 3 channels.
pub(crate) const MAX_K: usize = 15;

/// One level's inputs to the filter.
pub(crate) struct QpLevel<'a> {
    pub img: &'a Image,
    pub var: &'a Image,
    pub enhanced: &'a Image,
    pub guide: &'a Image,
    pub albedo: Option<&'a Image>,
    pub normal: Option<&'a Image>,
    /// The upsampled coarser result and its variance (finer levels).
    pub up: Option<(&'a Image, &'a Image)>,
    pub spp: f32,
    pub radius: usize,
    /// Converged pixels, whose output is their own colour and variance (finest level).
    pub converged: Option<&'a [bool]>,
    /// Bias terms left out of the objective although their input is present (see
    /// [`vanishing_terms`]); their costs still shape the initial weights.
    pub dropped: [bool; 5],
}

impl QpLevel<'_> {
    /// The weights of the terms whose input is present ([`alphas`]), dropped ones included.
    pub(crate) fn present_alphas(&self) -> [f32; 5] {
        alphas(
            self.spp,
            self.albedo.is_some(),
            self.normal.is_some(),
            self.up.is_some(),
        )
    }

    /// The weights of the terms in the objective: [`QpLevel::present_alphas`] with the dropped
    /// ones at 0.
    pub(crate) fn alphas(&self) -> [f32; 5] {
        let mut al = self.present_alphas();
        for (a, &off) in al.iter_mut().zip(&self.dropped) {
            if off {
                *a = 0.0;
            }
        }
        al
    }
}

/// Share of the QP objective below which an optional bias term is dropped.
pub(crate) const VANISHING: f64 = 1e-4;

/// Names of the bias terms `b0..b4`, for reports.
pub(crate) const TERM_NAMES: [&str; 5] = ["enhanced", "albedo", "normal", "guide", "coarser level"];

/// The optional terms (albedo, normal, coarser level: `b1`, `b2`, `b4`) whose weights vanish.
/// Their `alpha` scales with `1 / sqrt(spp)`; a term is dropped when `alpha_a S_a < VANISHING
/// (S_0 + V)`, with `S_a` the mean squared (unweighted) bias of term `a` between horizontal
/// neighbours, `S_0` that of the enhanced-image term (weight 1) and `V` the mean summed
/// variance (the objective's diagonal): its share of the objective is then below 1e-4, while
/// it costs 3 of the QP's 6 to 15 rows. The guide term `b3` is always kept. A dropped term's
/// cost still counts in the initial weights (the release's start uses every term's unweighted
/// cost), so the truncated solve starts where it would have.
pub(crate) fn vanishing_terms(level: &QpLevel) -> [bool; 5] {
    let al = level.present_alphas();
    let (w, h) = level.img.size();
    let n = w * h;
    if w < 2 || [1, 2, 4].iter().all(|&a| al[a] == 0.0) {
        return [false; 5];
    }
    let (img, var, enh) = (
        level.img.as_slice(),
        level.var.as_slice(),
        level.enhanced.as_slice(),
    );
    let up = level.up.map(|(u, _)| u.as_slice());
    let up_var = level.up.map(|(_, v)| v.as_slice());
    let (alb, nrm) = (
        level.albedo.map(Image::as_slice),
        level.normal.map(Image::as_slice),
    );
    // Per row: the sums of S_0, S_1, S_2, S_4 and V.
    let sums = (0..h)
        .into_par_iter()
        .map(|y| {
            let sq = |d: f32| f64::from(d) * f64::from(d);
            let mut acc = [0.0f64; 5];
            for c in 0..3 {
                for x in 0..w - 1 {
                    let (p, q) = (c * n + y * w + x, c * n + y * w + x + 1);
                    let residual = up.map_or(0.0, |u| img[q] - u[q]);
                    acc[0] += sq(enh[q] - enh[p]);
                    if let Some(f) = alb {
                        acc[1] += sq(f[q] - f[p] + residual);
                    }
                    if let Some(f) = nrm {
                        acc[2] += sq(f[q] - f[p] + residual);
                    }
                    if let Some(u) = up {
                        acc[3] += sq(u[q] - u[p]);
                    }
                    acc[4] += f64::from(var[p].max(0.0))
                        + up_var.map_or(0.0, |v| f64::from(v[p].max(0.0)));
                }
            }
            acc
        })
        .reduce(|| [0.0; 5], |a, b| std::array::from_fn(|i| a[i] + b[i]));
    let rest = sums[0] + sums[4];
    let mut dropped = [false; 5];
    for (a, s) in [(1, sums[1]), (2, sums[2]), (4, sums[3])] {
        dropped[a] = al[a] > 0.0 && f64::from(al[a]) * s < VANISHING * rest;
    }
    dropped
}

/// Pixels the QP did not solve.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct Skipped {
    /// Whole window black with zero variance: output 0.
    pub empty: u64,
    /// Converged: output the pixel's colour.
    pub converged: u64,
}

/// Term weights `alpha` of the five bias terms for `spp` samples (0 = term off).
pub(crate) fn alphas(spp: f32, has_albedo: bool, has_normal: bool, finer: bool) -> [f32; 5] {
    let s = spp.max(1e-6).sqrt();
    [
        1.0,
        if has_albedo { 16.0 / s } else { 0.0 },
        if has_normal { 0.16 / s } else { 0.0 },
        8.0 / s,
        if finer { (8.0 / s).min(1.0) } else { 0.0 },
    ]
}
