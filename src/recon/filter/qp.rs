//! Gradient-guided filtering: per pixel, one weight vector over a `(2r+1)^2` window, shared by
//! R, G, B, on the probability simplex, minimising `w^T Q w` with
//! `Q = sum_a alpha_a sum_c b_ac b_ac^T + diag(v)` (the release's formulation of the paper's
//! Eq. 21). The bias vectors over the window, for pixel `p` and neighbour `q`:
//! - `b0 = E(q) - E(p)`, `alpha = 1`: the enhanced image's differences estimate `mu_q - mu_p`;
//! - `b1 = albedo(q) - albedo(p) + (img(q) - up(q))`, `alpha = 16 / sqrt(N)`;
//! - `b2 = normal(q) - normal(p) + (img(q) - up(q))`, `alpha = 0.16 / sqrt(N)`;
//! - `b3 = img(q) - guide(p)`, `alpha = 8 / sqrt(N)`;
//! - `b4 = up(q) - up(p)`, finer levels only, `alpha = min(8 / sqrt(N), 1)`;
//!
//! where `img` is the noisy colour, `guide` the pre-denoised image and `up` the upsampled result
//! of the coarser level (`img` itself at the coarsest). `v_q` is the summed channel variance of
//! `img` (plus the upsampled variance at finer levels).
//!
//! The solver is the release's: start from weights proportional to
//! `1 / sqrt(v_q + sum of all b(q)^2 + 0.1)`; at iteration `k` move toward vertex `e_i`,
//! `i = k mod n`, with the exact line-search step `clamp(-d^T Q w / d^T Q d, 0, 1)`,
//! `d = e_i - w`; stop after `n` consecutive steps changing `w` by less than 1e-8, or after
//! `3n + 1` iterations. We exploit the low rank of `Q`: the projections `s = B w` (at most 15
//! values), `sum v w^2` and a global scale of `w` are updated in O(15) per iteration instead
//! of the O(15 n) of a direct evaluation. Terms whose weight is zero (no features, coarsest
//! level) are not built at all; terms whose weight vanishes at very high spp have no rows
//! ([`vanishing_terms`]) but still count in the start.
//!
//! Why it is fast (about 5x the one-pixel-at-a-time version at 1280 x 720): the arithmetic
//! per pixel is the release's, operation for operation and sum for sum, so the output is
//! bit-identical to that version, kept as the test reference (`qp/reference.rs`); but
//! [`LANES`] consecutive pixels of a row are solved in lockstep, one per SIMD lane
//! (`qp/lanes.rs`: plain arrays that LLVM vectorises, no `unsafe`). The lanes share the
//! iteration counter, hence the vertex and the sweeps; a lane that has stopped, or takes a tiny
//! step, is masked. All per-window arrays are lane-innermost and `K` is a const generic; the
//! update of `s` is fused with the next iteration's two sums over it; the initial weights,
//! column norms and projections are gathered while the rows are built; windows are read from
//! planes padded with the reflect-101 border band by band ([`BAND`] rows plus the halo, so the
//! copies stay small), with no `reflect` in the inner loops; the scratch is per band, not per
//! pixel. Bands run in parallel and no result depends on the thread count. A band's whole
//! solve is compiled for AVX2 as well and picked at run time (`multiversion`; 720p level 0:
//! 1.04 s -> 0.81 s, then 0.71 s with 16 lanes instead of 8).

use rayon::prelude::*;

use super::util::reflect;
use crate::image::Image;
pub(crate) use lanes::LANES;
use lanes::{F32x, I32x, Mask};

mod lanes;
#[cfg(test)]
mod reference;
#[cfg(test)]
mod tests;

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

/// The solver's O(K n) start: projections `s = B w`, `w^T diag(v) w` and the squared column
/// norms of `B`. Sums start from -0.0 like `Iterator::sum`, so that even signed zeros match the
/// scalar solver.
pub(crate) struct Start<const K: usize> {
    s: [F32x; K],
    svw: F32x,
    col2: [F32x; MAX_N],
}

impl<const K: usize> Start<K> {
    fn new() -> Self {
        Start {
            s: [F32x::splat(-0.0); K],
            svw: F32x::splat(-0.0),
            col2: [F32x::splat(0.0); MAX_N],
        }
    }
}

/// [`LANES`] independent simplex QPs, lane `l` with `Q_l = B_l^T B_l + diag(v_l)`, `K` bias
/// rows each (rows of zeros are allowed).
pub(crate) struct Simplex<'a, const K: usize> {
    /// `b[q][r]`: entry `q` of bias row `r`, per lane.
    pub b: &'a [[F32x; K]],
    /// `v[q]`: the diagonal, per lane.
    pub v: &'a [F32x],
    pub n: usize,
}

impl<const K: usize> Simplex<'_, K> {
    /// Runs the cyclic vertex line search from `w` (`w[q]`, each lane on the simplex) on the
    /// lanes in `active`, in O(K) per iteration; returns each lane's number of iterations.
    ///
    /// Every lane follows exactly the scalar release iteration: the lanes share the iteration
    /// counter (so the vertex `it mod n` and the once-per-sweep renormalisation), and a lane
    /// whose stopping rule fired, or that takes a tiny step, is masked out of the updates.
    #[cfg(test)]
    pub fn solve(&self, w: &mut [F32x], active: Mask, max_iter: usize) -> [u32; LANES] {
        self.solve_from(self.start(w), w, active, max_iter)
    }

    /// The O(K n) start of [`Simplex::solve`] from `w` (the filter gathers it while building
    /// the rows).
    #[cfg(test)]
    pub fn start(&self, w: &[F32x]) -> Start<K> {
        let mut st = Start::new();
        for (col2, bq) in st.col2.iter_mut().zip(&self.b[..self.n]) {
            for &br in bq {
                *col2 = *col2 + br * br;
            }
        }
        (st.s, st.svw) = self.project(w);
        st
    }

    /// `(B w, w^T diag(v) w)`, every sum over the neighbours in order from -0.0 (as
    /// `Iterator::sum`).
    #[inline(always)]
    fn project(&self, w: &[F32x]) -> ([F32x; K], F32x) {
        let (n, b, v) = (self.n, self.b, self.v);
        let mut s = [F32x::splat(-0.0); K];
        for (bq, &wq) in b[..n].iter().zip(&w[..n]) {
            for (sr, &br) in s.iter_mut().zip(bq) {
                *sr = *sr + br * wq;
            }
        }
        let mut svw = F32x::splat(-0.0);
        for (&vq, &wq) in v[..n].iter().zip(&w[..n]) {
            svw = svw + vq * wq * wq;
        }
        (s, svw)
    }

    /// [`Simplex::solve`] from its start (which must be `self.start(w)`, bit for bit).
    #[inline(always)]
    pub fn solve_from(
        &self,
        start: Start<K>,
        w: &mut [F32x],
        active: Mask,
        max_iter: usize,
    ) -> [u32; LANES] {
        let (n, b, v) = (self.n, self.b, self.v);
        let Start {
            mut s,
            mut svw,
            col2,
        } = start;
        let mut scale = F32x::splat(1.0);
        let mut quiet = I32x::default();
        let mut iters = I32x::default();
        let mut live = active;
        // `(Qw)_i` and `|s|^2` for the coming iteration, when the previous one computed them
        // while updating `s` (one pass over `s` per iteration instead of two).
        let mut ahead = None;
        let next = |i: usize| if i + 1 == n { 0 } else { i + 1 };
        let (mut it, mut i) = (0, 0);
        while it < max_iter {
            live = live & quiet.lt(n as i32);
            if !live.any() {
                break;
            }
            iters = iters.inc(live);
            it += 1;
            i = next(i);
            if i == 0 {
                self.renormalise(w, &mut s, &mut svw, &mut scale, live);
                ahead = None;
            }
            let (bi, vi) = (&b[i], v[i]);
            let wi = scale * w[i];
            let (qw, ss) = ahead.take().unwrap_or_else(|| {
                let mut qw = vi * wi;
                let mut ss = F32x::splat(0.0);
                for (&br, &sr) in bi.iter().zip(&s) {
                    qw = qw + br * sr;
                    ss = ss + sr * sr;
                }
                (qw, ss)
            });
            let wqw = ss + svw;
            let dqw = qw - wqw;
            let dqd = col2[i] + vi - F32x::splat(2.0) * qw + wqw;
            let step = -dqw / dqd;
            let t = F32x::select(step.is_finite(), step.clamp01(), F32x::splat(0.0));
            let tiny = t.lt(F32x::splat(1e-8));
            let moving = live.and_not(tiny);
            quiet = quiet.inc_or_reset(live & tiny, moving);
            if !moving.any() {
                continue;
            }
            let keep = F32x::splat(1.0) - t;
            svw = F32x::select(moving, quadratic_step(svw, t, vi, wi), svw);
            let new_scale = keep * scale;
            let collapse = moving & new_scale.lt(F32x::splat(1e-12));
            let grow = moving.and_not(collapse);
            w[i] = F32x::select(grow, w[i] + t / new_scale, w[i]);
            scale = F32x::select(grow, new_scale, scale);
            if collapse.any() {
                // All weight on vertex i (the scale underflowed): rare.
                for wq in &mut w[..n] {
                    *wq = F32x::select(collapse, F32x::splat(0.0), *wq);
                }
                w[i] = F32x::select(collapse, F32x::splat(1.0), w[i]);
                scale = F32x::select(collapse, F32x::splat(1.0), scale);
            }
            // s <- keep s + t b_i, and the next iteration's sums of the new s, in the order
            // that iteration would use (unless it renormalises first). The lanes that do not
            // move take `1 s + 0 b_i` instead of a masked select: that is `s` again (up to the
            // sign of a zero `s`, which no magnitude, `t` or `w` ever depends on), and saves a
            // third of the loop.
            let t_s = F32x::select(moving, t, F32x::splat(0.0));
            let keep_s = F32x::splat(1.0) - t_s;
            let j = next(i);
            let (bj, wj) = (&b[j], scale * w[j]);
            let mut qw = v[j] * wj;
            let mut ss = F32x::splat(0.0);
            for ((sr, &br), &bn) in s.iter_mut().zip(bi).zip(bj) {
                *sr = keep_s * *sr + t_s * br;
                qw = qw + bn * *sr;
                ss = ss + *sr * *sr;
            }
            ahead = Some((qw, ss));
        }
        for wq in &mut w[..n] {
            *wq = *wq * scale;
        }
        iters.0.map(|x| x as u32)
    }

    /// Once per sweep (amortised O(K)) on the `live` lanes: fold the scale in, renormalise the
    /// sum to 1 and recompute the projections, so that f32 drift cannot accumulate.
    #[inline(always)]
    fn renormalise(
        &self,
        w: &mut [F32x],
        s: &mut [F32x; K],
        svw: &mut F32x,
        scale: &mut F32x,
        live: Mask,
    ) {
        let n = self.n;
        let mut total = F32x::splat(-0.0);
        for &wq in &w[..n] {
            total = total + wq;
        }
        let factor = *scale / (total * *scale);
        for wq in &mut w[..n] {
            *wq = F32x::select(live, *wq * factor, *wq);
        }
        let (fresh, fresh_svw) = self.project(w);
        for (sr, fr) in s.iter_mut().zip(fresh) {
            *sr = F32x::select(live, fr, *sr);
        }
        *svw = F32x::select(live, fresh_svw, *svw);
        *scale = F32x::select(live, F32x::splat(1.0), *scale);
    }
}

/// `w^T diag(v) w` after the step `w <- (1 - t) w + t e_i`, with `wi` the old `w_i`: the
/// release's expression, operation for operation. Not inlined: inside the solver loop, LLVM's
/// SLP vectoriser splits this four-factor product into scalar lanes (measured: ~250
/// instructions per iteration instead of ~30).
#[inline(never)]
fn quadratic_step(svw: F32x, t: F32x, vi: F32x, wi: F32x) -> F32x {
    let keep = F32x::splat(1.0) - t;
    keep * keep * svw + F32x::splat(2.0) * t * keep * vi * wi + t * t * vi
}

/// Image rows per band. A band pads its own rows (plus the windows' halo) of every plane it
/// reads, so that the padded copies stay small whatever the frame size.
const BAND: usize = 16;

/// Rows of a few channels with a reflect-101 border of `r` pixels on every side and
/// `LANES - 1` more columns on the right, so that a lane group's windows are plain slices.
struct Padded {
    data: Vec<f32>,
    stride: usize,
    plane: usize,
}

impl Padded {
    /// Pads rows `y0 - r .. y0 + rows + r` of `channels` planes of a `w` x `h` image given as
    /// `f(c, pixel index)`; `cols[px]` is the image column of padded column `px`.
    fn new(
        channels: usize,
        (w, h): (usize, usize),
        cols: &[usize],
        r: usize,
        (y0, rows): (usize, usize),
        f: impl Fn(usize, usize) -> f32,
    ) -> Padded {
        let (stride, padded_rows) = (cols.len(), rows + 2 * r);
        let mut data = vec![0.0f32; channels * padded_rows * stride];
        for (row, out) in data.chunks_exact_mut(stride).enumerate() {
            let (c, py) = (row / padded_rows, row % padded_rows);
            let y = reflect((y0 + py) as isize - r as isize, h);
            for (o, &x) in out.iter_mut().zip(cols) {
                *o = f(c, y * w + x);
            }
        }
        Padded {
            data,
            stride,
            plane: padded_rows * stride,
        }
    }

    /// Padded row `py` of channel `c` (image row `y0 + py - r`) from padded column `x0`.
    fn row(&self, c: usize, py: usize, x0: usize) -> &[f32] {
        let start = c * self.plane + py * self.stride;
        &self.data[start + x0..start + self.stride]
    }
}

/// The padded planes of one band.
struct Planes {
    img: Padded,
    var: Padded,
    /// `v`: the summed clamped variances.
    v: Padded,
    enhanced: Padded,
    albedo: Option<Padded>,
    normal: Option<Padded>,
    up: Option<Padded>,
}

impl Planes {
    fn new(level: &QpLevel, cols: &[usize], band: (usize, usize)) -> Planes {
        let dims = level.img.size();
        let (n_px, r) = (dims.0 * dims.1, level.radius);
        let plain = |img: &Image| {
            let s = img.as_slice();
            Padded::new(3, dims, cols, r, band, |c, q| s[c * n_px + q])
        };
        let var = level.var.as_slice();
        let up_var = level.up.map(|(_, v)| v.as_slice());
        Planes {
            img: plain(level.img),
            var: plain(level.var),
            v: Padded::new(1, dims, cols, r, band, |_, q| {
                let mut vq = 0.0;
                for c in 0..3 {
                    vq += var[c * n_px + q].max(0.0);
                    if let Some(uv) = up_var {
                        vq += uv[c * n_px + q].max(0.0);
                    }
                }
                vq
            }),
            enhanced: plain(level.enhanced),
            albedo: level.albedo.map(plain),
            normal: level.normal.map(plain),
            up: level.up.map(|(u, _)| plain(u)),
        }
    }

    /// The bias terms whose input is present, in the release's order: those in the objective
    /// (`al`, `k / 3` of them, padded with zero-weight ones if fewer: never needed) have rows;
    /// dropped ones (`level.dropped`) only count in the initial weights.
    fn terms<'a>(&'a self, level: &'a QpLevel, al: &[f32; 5], k: usize) -> Vec<Term<'a>> {
        let present = level.present_alphas();
        let term = |src, centre: &'a Image, residual, a: usize| {
            let sq = present[a].sqrt();
            Term {
                src,
                centre: centre.as_slice(),
                residual,
                sq: F32x::splat(sq),
                unscale: Unscale::new(sq),
                row: al[a] != 0.0,
            }
        };
        let feature_residual = match self.up {
            Some(_) => Residual::ImgMinusUp,
            None => Residual::Zero,
        };
        let mut terms = vec![term(&self.enhanced, level.enhanced, Residual::None, 0)];
        for (a, p, f) in [
            (1, &self.albedo, level.albedo),
            (2, &self.normal, level.normal),
        ] {
            if let (Some(p), Some(f), true) = (p, f, present[a] != 0.0) {
                terms.push(term(p, f, feature_residual, a));
            }
        }
        terms.push(term(&self.img, level.guide, Residual::None, 3));
        if let (Some(p), Some((u, _)), true) = (&self.up, level.up, present[4] != 0.0) {
            terms.push(term(p, u, Residual::None, 4));
        }
        while 3 * terms.iter().filter(|t| t.row).count() < k {
            terms.push(Term {
                sq: F32x::splat(0.0),
                unscale: Unscale::Zero,
                ..term(&self.img, level.img, Residual::None, 0)
            });
        }
        terms
    }
}

/// How a bias term adds the coarser level's residual `img(q) - up(q)`.
#[derive(Clone, Copy)]
enum Residual {
    /// Not at all (`b0`, `b3`, `b4`): adds `-0`, which leaves every value as it is.
    None,
    /// Feature terms at the coarsest level: `+ 0` (turns a `-0` into `+0`, as the release).
    Zero,
    /// Feature terms at finer levels.
    ImgMinusUp,
}

impl Residual {
    /// Which of `[-0, +0, residual of R, G, B]` channel `c` adds.
    fn addend(self, c: usize) -> usize {
        match self {
            Residual::None => 0,
            Residual::Zero => 1,
            Residual::ImgMinusUp => 2 + c,
        }
    }
}

/// One active bias term: `sqrt(alpha) * (src(q) - centre(p) + residual(q))` per channel.
struct Term<'a> {
    src: &'a Padded,
    /// Unpadded planes, read at the pixel itself.
    centre: &'a [f32],
    residual: Residual,
    /// `sqrt(alpha)`.
    sq: F32x,
    unscale: Unscale,
    /// Whether the term has rows in the objective (false: dropped, see [`vanishing_terms`]).
    row: bool,
}

/// How the initial weights undo a row's `sqrt(alpha)` (the release divides).
#[derive(Clone, Copy)]
enum Unscale {
    /// A power of two: multiplying by its (exact) inverse rounds exactly as dividing does.
    Mul(F32x),
    Div(F32x),
    /// A term of weight 0 (never built, kept for the release's `if s > 0` guard).
    Zero,
}

impl Unscale {
    fn new(sq: f32) -> Unscale {
        let inverse = 1.0 / sq;
        let power_of_two = sq.is_normal() && inverse.is_normal() && sq.to_bits() & 0x007f_ffff == 0;
        match (sq > 0.0, power_of_two) {
            (false, _) => Unscale::Zero,
            (true, true) => Unscale::Mul(F32x::splat(inverse)),
            (true, false) => Unscale::Div(F32x::splat(sq)),
        }
    }
}

/// Per-worker buffers of one lane group.
struct Scratch<const K: usize> {
    b: Vec<[F32x; K]>,
    v: Vec<F32x>,
    w: Vec<F32x>,
}

/// Runs the filter over a level; returns the filtered colour and its variance.
/// The filtered image, its variance, and the pixels skipped.
///
/// A pixel whose whole window has zero colour and zero variance is skipped: its output is a
/// convex combination of zeros whatever the weights, so 0 (and variance 0) exactly, and the QP
/// is not solved (black backgrounds, letterboxing, masked-out regions). A converged pixel
/// (`level.converged`) keeps its colour and variance.
pub(crate) fn gradient_guided_filter(level: &QpLevel) -> (Image, Image, Skipped) {
    let al = level.alphas();
    // `b0` and `b3` are always on, so 6, 9, 12 or 15 rows.
    match 3 * al.iter().filter(|&&a| a != 0.0).count() {
        6 => filter_rows::<6>(level, &al),
        9 => filter_rows::<9>(level, &al),
        12 => filter_rows::<12>(level, &al),
        _ => filter_rows::<MAX_K>(level, &al),
    }
}

/// [`gradient_guided_filter`] with `K` bias rows.
fn filter_rows<const K: usize>(level: &QpLevel, al: &[f32; 5]) -> (Image, Image, Skipped) {
    let (w, h) = level.img.size();
    let mut out = Image::zeros(3, w, h);
    let mut out_var = Image::zeros(3, w, h);
    if w == 0 || h == 0 {
        return (out, out_var, Skipped::default());
    }
    let r = level.radius;
    let cols: Vec<usize> = (0..w + 2 * r + LANES - 1)
        .map(|px| reflect(px as isize - r as isize, w))
        .collect();
    let bands: Vec<(Vec<f32>, Skipped)> = (0..h.div_ceil(BAND))
        .into_par_iter()
        .map(|band| filter_band::<K>(level, al, &cols, band))
        .collect();
    let mut skipped = Skipped::default();
    for (band, (o, s)) in bands.iter().enumerate() {
        skipped.empty += s.empty;
        skipped.converged += s.converged;
        for (i, o) in o.chunks_exact(6 * w).enumerate() {
            for c in 0..3 {
                for (dst, src) in [(&mut out, c), (&mut out_var, 3 + c)] {
                    dst.plane_mut(c)
                        .row_mut(band * BAND + i)
                        .as_slice_mut()
                        .expect("contiguous")
                        .copy_from_slice(&o[src * w..(src + 1) * w]);
                }
            }
        }
    }
    (out, out_var, skipped)
}

/// Filters image rows `band * BAND ..` (at most [`BAND`] of them); returns per row colour then
/// variance, channel by channel, and the pixels skipped. Compiled for AVX2 too, picked at run
/// time: the whole solver is inlined into it, so its `F32x` arithmetic becomes 256-bit
/// instructions (measured 1.5x; AVX-512 was slower: the lanes are 8 wide). No FMA contraction
/// happens in Rust, so every version computes the same bits.
#[multiversion::multiversion(targets("x86_64+avx2+fma"))]
fn filter_band<const K: usize>(
    level: &QpLevel,
    al: &[f32; 5],
    cols: &[usize],
    band: usize,
) -> (Vec<f32>, Skipped) {
    let (w, h) = level.img.size();
    let (n_px, r) = (w * h, level.radius);
    let side = 2 * r + 1;
    let (img, var) = (level.img.as_slice(), level.var.as_slice());
    let (y0, rows) = (band * BAND, BAND.min(h - band * BAND));
    let planes = Planes::new(level, cols, (y0, rows));
    let terms = planes.terms(level, al, K);
    let ctx = Ctx::<K> {
        w,
        n_px,
        side,
        n: side * side,
        y0,
        terms: &terms,
        img: &planes.img,
        var: &planes.var,
        v: &planes.v,
        up: planes.up.as_ref(),
    };
    let mut scratch = Scratch::<K> {
        b: vec![[F32x::default(); K]; MAX_N],
        v: vec![F32x::default(); MAX_N],
        w: vec![F32x::default(); MAX_N],
    };
    // Per row: colour then variance, channel by channel.
    let mut out = vec![0.0f32; 6 * w * rows];
    let mut skipped = Skipped::default();
    for (y, out) in (y0..y0 + rows).zip(out.chunks_exact_mut(6 * w)) {
        for x0 in (0..w).step_by(LANES) {
            let mut solve = [false; LANES];
            for (l, sl) in solve.iter_mut().enumerate() {
                let (x, p) = (x0 + l, y * w + x0 + l);
                if x >= w {
                    continue;
                }
                if ctx.window_empty(x, y) {
                    skipped.empty += 1;
                } else if level.converged.is_some_and(|m| m[p]) {
                    for c in 0..3 {
                        out[c * w + x] = img[c * n_px + p];
                        out[(3 + c) * w + x] = var[c * n_px + p];
                    }
                    skipped.converged += 1;
                } else {
                    *sl = true;
                }
            }
            if solve.contains(&true) {
                ctx.solve_group(&mut scratch, x0, y, solve, out);
            }
        }
    }
    (out, skipped)
}

/// What every lane group of a level reads.
struct Ctx<'a, const K: usize> {
    w: usize,
    n_px: usize,
    side: usize,
    n: usize,
    /// The band's first image row (padded row `y - y0 + dy` holds window row `dy` of row `y`).
    y0: usize,
    terms: &'a [Term<'a>],
    img: &'a Padded,
    var: &'a Padded,
    v: &'a Padded,
    up: Option<&'a Padded>,
}

impl<const K: usize> Ctx<'_, K> {
    /// Whether the window of pixel `(x, y)` has zero colour and variance throughout.
    #[inline(always)]
    fn window_empty(&self, x: usize, y: usize) -> bool {
        (0..self.side).all(|dy| {
            let py = y - self.y0 + dy;
            (0..3).all(|c| {
                let (i, v) = (self.img.row(c, py, x), self.var.row(c, py, x));
                i[..self.side].iter().all(|&a| a == 0.0) && v[..self.side].iter().all(|&a| a == 0.0)
            })
        })
    }

    /// Builds, solves and applies the QPs of pixels `x0..x0 + LANES` of row `y` (the lanes in
    /// `solve`); writes colour to `out[c * w + x]` and variance to `out[(3 + c) * w + x]`.
    #[inline(always)]
    fn solve_group(
        &self,
        sc: &mut Scratch<K>,
        x0: usize,
        y: usize,
        solve: [bool; LANES],
        out: &mut [f32],
    ) {
        let (w, side, n) = (self.w, self.side, self.n);
        // Window entry q = dy * side + dx of lane l is padded (x0 + l + dx, y - y0 + dy). Neighbour
        // by neighbour: the bias entries, the initial weights' costs (inverse root of the total
        // unweighted cost) and the column norms, every sum in the release's order of rows.
        // Every present term, in order; dropped ones (no row) only add to the start's costs.
        let terms = self.terms;
        let nt = terms.len();
        let centres: [F32x; MAX_K] = std::array::from_fn(|r| {
            let at = (r % 3) * self.n_px + y * w;
            match terms.get(r / 3) {
                Some(t) => F32x(std::array::from_fn(|l| t.centre[at + (x0 + l).min(w - 1)])),
                None => F32x::default(),
            }
        });
        let mut st = Start::<K>::new();
        let mut total = F32x::splat(0.0);
        let width = side + LANES - 1;
        for dy in 0..side {
            let py = y - self.y0 + dy;
            let srcs: [&[f32]; MAX_K] = std::array::from_fn(|r| match terms.get(r / 3) {
                Some(t) => &t.src.row(r % 3, py, x0)[..width],
                None => &[][..],
            });
            let residual: [(&[f32], &[f32]); 3] = std::array::from_fn(|c| match self.up {
                Some(up) => (
                    &self.img.row(c, py, x0)[..width],
                    &up.row(c, py, x0)[..width],
                ),
                None => (&[][..], &[][..]),
            });
            let vr = &self.v.row(0, py, x0)[..width];
            for dx in 0..side {
                let q = dy * side + dx;
                // What each row adds to its difference (see `Residual`).
                let mut addends = [
                    F32x::splat(-0.0),
                    F32x::splat(0.0),
                    F32x::default(),
                    F32x::default(),
                    F32x::default(),
                ];
                if self.up.is_some() {
                    for (a, (im, up)) in addends[2..].iter_mut().zip(residual) {
                        *a = F32x::load(&im[dx..dx + LANES]) - F32x::load(&up[dx..dx + LANES]);
                    }
                }
                let vq = F32x::load(&vr[dx..dx + LANES]);
                sc.v[q] = vq;
                let mut e = vq + F32x::splat(0.1);
                let mut col2 = F32x::splat(0.0);
                let bq = &mut sc.b[q];
                let mut row = 0;
                for (ti, term) in terms[..nt].iter().enumerate() {
                    for c in 0..3 {
                        let r = 3 * ti + c;
                        let d = F32x::load(&srcs[r][dx..dx + LANES]) - centres[r];
                        let br = term.sq * (d + addends[term.residual.addend(c)]);
                        let raw = match term.unscale {
                            Unscale::Mul(m) => br * m,
                            Unscale::Div(s) => br / s,
                            Unscale::Zero => F32x::splat(0.0),
                        };
                        e = e + raw * raw;
                        if term.row {
                            bq[row] = br;
                            col2 = col2 + br * br;
                            row += 1;
                        }
                    }
                }
                st.col2[q] = col2;
                sc.w[q] = F32x::splat(1.0) / e.sqrt();
                total = total + sc.w[q];
            }
        }
        // Normalised, and projected on the way (the sums of `Simplex::project`, same order).
        for q in 0..n {
            let wq = sc.w[q] / total;
            sc.w[q] = wq;
            for (sr, &br) in st.s.iter_mut().zip(&sc.b[q]) {
                *sr = *sr + br * wq;
            }
            st.svw = st.svw + sc.v[q] * wq * wq;
        }
        let problem = Simplex::<K> {
            b: &sc.b[..n],
            v: &sc.v[..n],
            n,
        };
        problem.solve_from(st, &mut sc.w, Mask::from_bools(solve), 3 * n + 1);
        for c in 0..3 {
            let (mut o, mut ov) = (F32x::splat(0.0), F32x::splat(0.0));
            for dy in 0..side {
                let py = y - self.y0 + dy;
                let (im, va) = (self.img.row(c, py, x0), self.var.row(c, py, x0));
                for (dx, &wq) in sc.w[dy * side..(dy + 1) * side].iter().enumerate() {
                    o = o + wq * F32x::load(&im[dx..]);
                    ov = ov + wq * wq * F32x::load(&va[dx..]);
                }
            }
            for l in (0..LANES).filter(|&l| solve[l]) {
                out[c * w + x0 + l] = o.0[l];
                out[(3 + c) * w + x0 + l] = ov.0[l];
            }
        }
    }
}
