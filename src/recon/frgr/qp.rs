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
//! values), `|s|^2`, `sum v w^2` and a global scale of `w` are updated in O(15) per iteration
//! instead of the O(15 n) of a direct evaluation, and the once-per-sweep renormalisation
//! scales them instead of recomputing them (O(15) instead of O(15 n) again). Terms whose
//! weight is zero (no features, coarsest level) are not built at all; terms whose weight
//! vanishes at very high spp have no rows ([`vanishing_terms`]) but still count in the start.
//!
//! Why it is fast (its measured speed-ups are in `docs/benchmarks.md`): the arithmetic per
//! pixel is the release's up to the order of some sums (the updates above; `b . s` summed in
//! three chains; the initial costs from the unscaled differences), so the output is within 1e-5
//! of that version's, kept as the test reference (`qp/reference.rs`; measured: 9.5e-7 at most
//! on a 720p frame of peak 0.93, relMSE the same to 6 digits on every validation and test
//! frame); but [`LANES`] consecutive pixels of a row are solved in lockstep, one per SIMD lane
//! (`qp/lanes.rs`: plain arrays that LLVM vectorises, no `unsafe`). The lanes share the
//! iteration counter, hence the vertex and the sweeps; a lane that has stopped, or takes a tiny
//! step, is masked. All per-window arrays are lane-innermost and `K` is a const generic; the
//! update of `s` is fused with the next iteration's sum over it; the initial weights,
//! column norms and projections are gathered while the rows are built; windows are read from
//! planes padded with the reflect-101 border band by band ([`BAND`] rows plus the halo, so the
//! copies stay small), with no `reflect` in the inner loops; the scratch is per band, not per
//! pixel. Bands run in parallel and no result depends on the thread count (nor on the CPU, but
//! for FMA: below). A band's whole solve is compiled for AVX-512 and AVX2 as well and picked at
//! run time (`multiversion`). The sums of products (`b . s`, the update of `s`, the rows' norms and costs, the output's
//! weighted sums) are `madd`s: one FMA instruction in those builds, a multiply and an add in
//! the baseline one (a CPU without FMA), so the result is the same on every CPU with FMA, and on
//! one without it is the unfused arithmetic (measured: the forty-third session's bits).
//!
//! The module's parts: `level.rs` (a level's inputs, term weights, vanishing terms),
//! `band.rs` (padded bands of rows and the bias terms read from them), `simplex.rs` (the
//! lane-parallel solver), `lanes.rs` (the SIMD lane types); this file drives the bands.

use rayon::prelude::*;

use super::fastmath::fused;
use crate::error::Result;
use crate::image::{try_vec, Image};
use crate::progress::Progress;
use band::{Padded, Planes, Term, BAND};
pub(crate) use lanes::LANES;
use lanes::{F32x, Mask};
pub(crate) use level::*;
use simplex::{Simplex, Start};

mod band;
mod lanes;
mod level;
#[cfg(test)]
mod reference;
mod simplex;
#[cfg(test)]
mod tests;

/// Per-worker buffers of one lane group.
struct Scratch<const K: usize> {
    b: Vec<[F32x; K]>,
    v: Vec<F32x>,
    w: Vec<F32x>,
}

/// [`filter_or_stop`], never stopped (the tests' entry point).
#[cfg(test)]
pub(crate) fn gradient_guided_filter(level: &QpLevel) -> (Image, Image, Skipped) {
    filter_or_stop(level, &Progress::none()).expect("allocated")
}

/// Runs the filter over a level; returns the filtered colour, its variance, and the pixels
/// skipped. Once `stop` is cancelled the bands not yet started are skipped (the result is then
/// incomplete; the caller checks `stop`). Fails only with
/// [`Error::OutOfMemory`](crate::Error::OutOfMemory).
///
/// A pixel whose whole window has zero colour and zero variance is skipped: its output is a
/// convex combination of zeros whatever the weights, so 0 (and variance 0) exactly, and the QP
/// is not solved (black backgrounds, letterboxing, masked-out regions). A converged pixel
/// (`level.converged`) keeps its colour and variance.
pub(crate) fn filter_or_stop(level: &QpLevel, stop: &Progress) -> Result<(Image, Image, Skipped)> {
    let al = level.alphas();
    // `b0` and `b3` are always on, so 6, 9, 12 or 15 rows.
    match 3 * al.iter().filter(|&&a| a != 0.0).count() {
        6 => filter_rows::<6>(level, &al, stop),
        9 => filter_rows::<9>(level, &al, stop),
        12 => filter_rows::<12>(level, &al, stop),
        _ => filter_rows::<MAX_K>(level, &al, stop),
    }
}

/// [`filter_or_stop`] with `K` bias rows.
fn filter_rows<const K: usize>(
    level: &QpLevel,
    al: &[f32; 5],
    stop: &Progress,
) -> Result<(Image, Image, Skipped)> {
    let (w, h) = level.img.size();
    let mut out = Image::try_zeros(3, w, h)?;
    let mut out_var = Image::try_zeros(3, w, h)?;
    if w == 0 || h == 0 {
        return Ok((out, out_var, Skipped::default()));
    }
    // Each band's rows of the six output planes (colour, then variance, channel by channel),
    // cut before the bands start: a band writes its pixels in place.
    let mut planes: Vec<_> = [&mut out, &mut out_var]
        .into_iter()
        .flat_map(|img| img.as_mut_slice().chunks_mut(w * h))
        .map(|plane| plane.chunks_mut(BAND * w))
        .collect();
    let rows: Vec<[&mut [f32]; 6]> = (0..h.div_ceil(BAND))
        .map(|_| std::array::from_fn(|s| planes[s].next().expect("a band's rows")))
        .collect();
    let skipped = rows
        .into_par_iter()
        .enumerate()
        .map_init(Worker::default, |worker, (band, rows)| {
            if stop.stopped() {
                Ok(Skipped::default()) // its rows stay 0
            } else {
                filter_band::<K>(level, al, band, worker, rows)
            }
        })
        .try_reduce(Skipped::default, |a, b| {
            Ok(Skipped {
                empty: a.empty + b.empty,
                converged: a.converged + b.converged,
            })
        })?;
    Ok((out, out_var, skipped))
}

/// What a worker keeps from one band to its next: the scratch of a lane group and the padded
/// planes' buffers (allocated once per worker, not per band; every value is written before it
/// is read).
#[derive(Default)]
struct Worker<const K: usize> {
    scratch: Option<Scratch<K>>,
    spare: Vec<Vec<f32>>,
}

/// Filters image rows `band * BAND ..` (at most [`BAND`] of them) into `rows` (those rows of the
/// colour's planes, then of the variance's); returns the pixels skipped. Compiled for AVX-512 and
/// AVX2 too, picked at run time: the whole solver is inlined into it, so its `F32x` arithmetic
/// becomes 512-bit instructions (two registers per value) or 256-bit ones (four): independent
/// chains that hide the latency of the solver's dependent steps (see [`LANES`]). Rust never
/// contracts `a * b + c` on its own; the `madd`s fuse in both versions (they have FMA), so the two
/// compute the same bits; the baseline version does not fuse.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn filter_band<const K: usize>(
    level: &QpLevel,
    al: &[f32; 5],
    band: usize,
    worker: &mut Worker<K>,
    mut rows: [&mut [f32]; 6],
) -> Result<Skipped> {
    let (w, h) = level.img.size();
    let (n_px, r) = (w * h, level.radius);
    let side = 2 * r + 1;
    let (img, var) = (level.img.as_slice(), level.var.as_slice());
    let (y0, count) = (band * BAND, BAND.min(h - band * BAND));
    let planes = Planes::new(level, (y0, count), &mut worker.spare)?;
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
    let scratch = match &mut worker.scratch {
        Some(scratch) => scratch,
        none => none.insert(Scratch::<K> {
            b: try_vec(MAX_N, [F32x::default(); K])?,
            v: try_vec(MAX_N, F32x::default())?,
            w: try_vec(MAX_N, F32x::default())?,
        }),
    };
    let mut skipped = Skipped::default();
    for (t, y) in (y0..y0 + count).enumerate() {
        let mut out = rows.each_mut().map(|plane| &mut plane[t * w..(t + 1) * w]);
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
                        out[c][x] = img[c * n_px + p];
                        out[3 + c][x] = var[c * n_px + p];
                    }
                    skipped.converged += 1;
                } else {
                    *sl = true;
                }
            }
            if solve.contains(&true) {
                ctx.solve_group::<{ fused!() }>(scratch, x0, y, solve, &mut out);
            }
        }
    }
    planes.recycle(&mut worker.spare);
    Ok(skipped)
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
        // Loops with an early return: `Iterator::all`'s closures stayed calls here.
        for dy in 0..self.side {
            let py = y - self.y0 + dy;
            for c in 0..3 {
                let (i, v) = (self.img.row(c, py, x), self.var.row(c, py, x));
                for (&a, &b) in i[..self.side].iter().zip(&v[..self.side]) {
                    if a != 0.0 || b != 0.0 {
                        return false;
                    }
                }
            }
        }
        true
    }

    /// Builds, solves and applies the QPs of pixels `x0..x0 + LANES` of row `y` (the lanes in
    /// `solve`); writes colour to `out[c][x]` and variance to `out[3 + c][x]`.
    #[inline(always)]
    fn solve_group<const FUSED: bool>(
        &self,
        sc: &mut Scratch<K>,
        x0: usize,
        y: usize,
        solve: [bool; LANES],
        out: &mut [&mut [f32]; 6],
    ) {
        let (w, side, n) = (self.w, self.side, self.n);
        // Window entry q = dy * side + dx of lane l is padded (x0 + l + dx, y - y0 + dy). Neighbour
        // by neighbour: the bias entries, the initial weights' costs (inverse root of the total
        // unweighted cost) and the column norms, every sum in the release's order of rows.
        // Every present term, in order; dropped ones (no row) only add to the start's costs.
        // Plain loops, not `std::array::from_fn`: its closures are not inlined into the
        // multiversioned band, and ran as calls per value (measured: 3-4 % of the filter).
        let terms = self.terms;
        let nt = terms.len();
        let mut centres = [F32x::default(); MAX_K];
        for (r, centre) in centres.iter_mut().enumerate().take(3 * nt) {
            let plane = &terms[r / 3].centre[(r % 3) * self.n_px + y * w..][..w];
            if x0 + LANES <= w {
                centre.0.copy_from_slice(&plane[x0..x0 + LANES]);
            } else {
                for (l, c) in centre.0.iter_mut().enumerate() {
                    *c = plane[(x0 + l).min(w - 1)];
                }
            }
        }
        let mut st = Start::<K>::new();
        let mut total = F32x::splat(0.0);
        let width = side + LANES - 1;
        for dy in 0..side {
            let py = y - self.y0 + dy;
            let mut srcs: [&[f32]; MAX_K] = [&[]; MAX_K];
            for (r, src) in srcs.iter_mut().enumerate().take(3 * nt) {
                *src = &terms[r / 3].src.row(r % 3, py, x0)[..width];
            }
            let mut residual: [(&[f32], &[f32]); 3] = [(&[], &[]); 3];
            if let Some(up) = self.up {
                for (c, res) in residual.iter_mut().enumerate() {
                    *res = (
                        &self.img.row(c, py, x0)[..width],
                        &up.row(c, py, x0)[..width],
                    );
                }
            }
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
                        let raw = d + addends[term.residual.addend(c)];
                        let br = term.sq * raw;
                        if term.counts {
                            e = raw.madd::<FUSED>(raw, e);
                        }
                        if term.row {
                            bq[row] = br;
                            col2 = br.madd::<FUSED>(br, col2);
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
        let inverse = F32x::splat(1.0) / total;
        for q in 0..n {
            let wq = sc.w[q] * inverse;
            sc.w[q] = wq;
            for (sr, &br) in st.s.iter_mut().zip(&sc.b[q]) {
                *sr = br.madd::<FUSED>(wq, *sr);
            }
            st.svw = (sc.v[q] * wq).madd::<FUSED>(wq, st.svw);
        }
        let problem = Simplex::<K> {
            b: &sc.b[..n],
            v: &sc.v[..n],
            n,
        };
        problem.solve_from::<FUSED>(st, &mut sc.w, Mask::from_bools(solve), 3 * n + 1);
        for c in 0..3 {
            let (mut o, mut ov) = (F32x::splat(0.0), F32x::splat(0.0));
            for dy in 0..side {
                let py = y - self.y0 + dy;
                let (im, va) = (self.img.row(c, py, x0), self.var.row(c, py, x0));
                for (dx, &wq) in sc.w[dy * side..(dy + 1) * side].iter().enumerate() {
                    o = wq.madd::<FUSED>(F32x::load(&im[dx..]), o);
                    ov = (wq * wq).madd::<FUSED>(F32x::load(&va[dx..]), ov);
                }
            }
            for l in 0..LANES {
                if solve[l] {
                    out[c][x0 + l] = o.0[l];
                    out[3 + c][x0 + l] = ov.0[l];
                }
            }
        }
    }
}
