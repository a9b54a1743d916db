//! Gradient enhancement: an image whose pixel differences are valid (integrable) gradients,
//! close to the input gradients where they are reliable and smooth where the features are.
//!
//! Minimises, over an image `I` started from the guide (the pre-denoised image),
//! `sum_p m_x(p) |D_x I - dx|^2 + m_y(p) |D_y I - dy|^2 + lambda (a_x(p) |D_x I|^2 + a_y(p)
//! |D_y I|^2)` (squared norms over R, G, B), with, as in the authors' release,
//! `m = (g / t + 1 / g)^2` where `g = |d_R| + |d_G| + |d_B| + 0.01` and `t = 0.09` (large for
//! very small and very large gradients: flat regions and edges are kept),
//! `a = 1 / (|D albedo|_1 + |D normal|_1 + 0.01)^2` and `lambda = 8 / sqrt(spp)`. There is no
//! data term: early stopping and the start from the guide regularise the solve.
//!
//! `enhance_reference` (the tests' entry point) is the release's schedule, literally: 1000
//! gradient-descent iterations with a step starting at 1e-4; the loss is checked at iterations
//! below 20 and every 50th; when it rose above the best seen, the step halves and the image (and
//! the best loss) revert to the start. One addition: the steps after the last check are checked
//! too, and if they raised the energy the result is the start (the release would return them). The
//! energy is evaluated from the steps' own edge terms ([`edge_energy`]), in the pass that produces
//! the image: it is the release's energy up to the f32 rounding of the weights.
//!
//! By default the steps after the last revert are not taken one by one: once the step is below
//! Gershgorin's stability bound no revert can follow, and the remaining steps are one
//! polynomial of the energy's Hessian, evaluated as a Chebyshev series in a quarter of the
//! products or fewer ([`chebyshev`]; the series truncated at 1e-4 of its largest gain, the
//! image within 2.5e-4 of its peak of the steps' own on every validation frame and the 720p
//! demo frame). Where the bound does not hold (the bound exceeds the step's limit), every step
//! is taken, as before.

use ndarray::Array3;
use rayon::prelude::*;

use crate::error::Result;
use crate::image::{try_vec, try_zeroed_vec, Image};
use crate::progress::Progress;

mod chebyshev;

/// Per-edge weights, shared by R, G, B: `m` (fidelity) and `lambda * a` (smoothness).
pub(crate) struct EnhanceWeights {
    w: usize,
    h: usize,
    mx: Vec<f32>,
    my: Vec<f32>,
    sx: Vec<f32>,
    sy: Vec<f32>,
}

const T: f32 = 0.09;
const EPS: f32 = 0.01;

/// `out[x] = sum_c |f_c[at + x + step] - f_c[at + x]|` for `x < out.len()`: the L1 difference
/// of a feature across the edges of a row (`step` 1: horizontal, the width: vertical), its
/// channels summed in order from -0.0, as `Iterator::sum` sums them.
fn edge_l1(img: &Image, at: usize, step: usize, out: &mut [f32]) {
    let n = img.width() * img.height();
    let s = img.as_slice();
    let len = out.len();
    out.fill(-0.0);
    for c in 0..img.channels() {
        let (lo, hi) = (&s[c * n + at..][..len], &s[c * n + at + step..][..len]);
        for ((o, &a), &b) in out.iter_mut().zip(lo).zip(hi) {
            *o += (b - a).abs();
        }
    }
}

/// The fidelity weights `m = (g / t + 1 / g)^2`, `g = |d_R| + |d_G| + |d_B| + 0.01`, of the
/// `out.len()` edges of a gradient image's row starting at `at`.
fn fidelity_row(g: &Image, at: usize, out: &mut [f32]) {
    let n = g.width() * g.height();
    let s = g.as_slice();
    let len = out.len();
    let (r, gr, b) = (
        &s[at..][..len],
        &s[n + at..][..len],
        &s[2 * n + at..][..len],
    );
    for (x, o) in out.iter_mut().enumerate() {
        let g = r[x].abs() + gr[x].abs() + b[x].abs() + EPS;
        let m = g / T + 1.0 / g;
        *o = m * m;
    }
}

/// The smoothness weights `lambda / (d + 0.01)^2` of a row's `out.len()` edges, `d` the
/// albedo's L1 difference across the edge plus the normal's ([`edge_l1`]), whichever the
/// frame has (at least one); `scratch` holds twice the row.
fn smoothness_row(
    features: [Option<&Image>; 2],
    (at, step): (usize, usize),
    lambda: f32,
    scratch: &mut [f32],
    out: &mut [f32],
) {
    let len = out.len();
    let (d, e) = scratch.split_at_mut(len);
    let e = &mut e[..len];
    let mut first = true;
    for f in features.into_iter().flatten() {
        if first {
            edge_l1(f, at, step, d);
            first = false;
        } else {
            edge_l1(f, at, step, e);
            for (d, &e) in d.iter_mut().zip(&*e) {
                *d += e;
            }
        }
    }
    for (o, &d) in out.iter_mut().zip(&*d) {
        *o = lambda / ((d + EPS) * (d + EPS));
    }
}

impl EnhanceWeights {
    /// Weights from the (outlier-free) gradients and, when present, the features.
    pub fn new(
        dx: &Image,
        dy: &Image,
        albedo: Option<&Image>,
        normal: Option<&Image>,
        lambda: f32,
    ) -> Result<Self> {
        let (w, h) = dx.size();
        let n = w * h;
        let mut wts = EnhanceWeights {
            w,
            h,
            mx: try_zeroed_vec(n)?,
            my: try_zeroed_vec(n)?,
            sx: try_zeroed_vec(n)?,
            sy: try_zeroed_vec(n)?,
        };
        let features = [albedo, normal];
        let smooth = albedo.is_some() || normal.is_some();
        // Row by row over slices, so that the weights vectorise (they are the per-edge
        // formulas above, the same values): the last column has no horizontal edge and the
        // last row no vertical one (their weights stay 0), and without features the
        // smoothness weights are 0.
        wts.mx
            .par_chunks_mut(w)
            .zip(wts.sx.par_chunks_mut(w))
            .zip(wts.my.par_chunks_mut(w).zip(wts.sy.par_chunks_mut(w)))
            .enumerate()
            .for_each_init(
                || vec![0.0f32; 2 * w],
                |scratch, (y, ((mx, sx), (my, sy)))| {
                    let at = y * w;
                    let across = w - 1;
                    fidelity_row(dx, at, &mut mx[..across]);
                    if smooth {
                        smoothness_row(features, (at, 1), lambda, scratch, &mut sx[..across]);
                    }
                    if y + 1 < h {
                        fidelity_row(dy, at, my);
                        if smooth {
                            smoothness_row(features, (at, w), lambda, scratch, sy);
                        }
                    }
                },
            );
        Ok(wts)
    }
}

/// A deterministic image of small values of both signs, the tests' gradients, features and
/// planes (`k` shifts the pattern).
#[cfg(test)]
fn wave(channels: usize, w: usize, h: usize, k: usize) -> Image {
    Image::from_fn(channels, w, h, |(c, x, y)| {
        (((x * 7 + y * 3 + c * 5 + k) % 11) as f32 - 5.0) * 0.037
    })
}

/// Edge flux, the derivative of the edge's energy by its difference `d`:
/// `2 (m (d - t) + s d) = a d - b` with `a = 2 (m + s)`, `b = 2 m t` precomputed per edge
/// ([`Sweeper::new`]), so a step costs 3 operations per edge instead of 6.
#[inline(always)]
fn flux(a: f32, b: f32, d: f32) -> f32 {
    a * d - b
}

/// Partial sums per lane of [`edge_energy`]: independent chains of f64 additions, so that the
/// sum vectorises instead of waiting on one chain of dependent adds.
const ENERGY_LANES: usize = 8;

/// The variable part of the edges' energy, `sum_x d (a d / 2 - b)` with `d = hi - lo`, in f64:
/// per lane `x mod 8` in order of `x` over the whole chunks of 8, then the lanes in order, then
/// the remainder (a fixed order: the schedule compares energies exactly).
///
/// An edge's energy `m (d - t)^2 + s d^2` is `(a / 2) d^2 - b d + m t^2` with the flux's
/// `a = 2 (m + s)` and `b = 2 m t` ([`flux`]); `m t^2` does not depend on the image
/// ([`Sweeper::constant`]). So the energy needs only what a step reads anyway, and is exactly
/// the one whose gradient the steps follow (the f32 `a` and `b` included). Written over
/// fixed-size chunks, the remainder summed apart, so that it vectorises (indexing by `x` with
/// the remainder in the lanes kept it scalar, a measurable share of the method's time).
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn edge_energy(a: &[f32], b: &[f32], lo: &[f32], hi: &[f32]) -> f64 {
    const L: usize = ENERGY_LANES;
    let n = a.len();
    let (b, lo, hi) = (&b[..n], &lo[..n], &hi[..n]);
    let e = |a: f32, b: f32, lo: f32, hi: f32| {
        let d = f64::from(hi - lo);
        d * (0.5 * f64::from(a) * d - f64::from(b))
    };
    let mut acc = [0.0f64; L];
    let chunks = a
        .chunks_exact(L)
        .zip(b.chunks_exact(L))
        .zip(lo.chunks_exact(L).zip(hi.chunks_exact(L)));
    for ((a, b), (lo, hi)) in chunks {
        let terms: [f64; L] = std::array::from_fn(|l| e(a[l], b[l], lo[l], hi[l]));
        for (acc, t) in acc.iter_mut().zip(terms) {
            *acc += t;
        }
    }
    let tail: f64 = (n - n % L..n).map(|i| e(a[i], b[i], lo[i], hi[i])).sum();
    acc.iter().sum::<f64>() + tail
}

/// `sum_x m t^2` over a row of edges, in f64 (once per level).
fn fidelity_constant(m: &[f32], t: &[f32]) -> f64 {
    m.iter()
        .zip(t)
        .map(|(&m, &t)| f64::from(m) * f64::from(t) * f64::from(t))
        .sum()
}

/// One row's energy terms, in the order the total adds them: per channel, the horizontal
/// edges, then the vertical edges to the next row (0 on the last row, which has none).
type RowEnergy = [f64; 6];

/// One gradient-descent step, `dst = src - step * grad E(src)`, pixel by pixel: the literal
/// form, kept as the oracle of [`Sweeper`] (which must equal it bit for bit).
#[cfg(test)]
fn descend(src: &[f32], dst: &mut [f32], e: &Sweeper, step: f32) {
    let (w, h) = (e.w, e.h);
    let n = w * h;
    dst.par_chunks_mut(w).enumerate().for_each(|(r, row)| {
        let (c, y) = (r / h, r % h);
        let o = c * n + y * w;
        for (x, out) in row.iter_mut().enumerate() {
            let (i, k) = (o + x, y * w + x);
            let mut g = 0.0;
            if x + 1 < w {
                g -= flux(e.ax[k], e.bx[i], src[i + 1] - src[i]);
            }
            if x >= 1 {
                g += flux(e.ax[k - 1], e.bx[i - 1], src[i] - src[i - 1]);
            }
            if y + 1 < h {
                g -= flux(e.ay[k], e.by[i], src[i + w] - src[i]);
            }
            if y >= 1 {
                g += flux(e.ay[k - w], e.by[i - w], src[i] - src[i - w]);
            }
            *out = flush(src[i] - step * g);
        }
    });
}

/// Flushes subnormals to zero: diffusion into a black region leaves values decaying through
/// the subnormal range, where every operation is ~100x slower (measured: the finest level's
/// 1000 steps took 3.45 s instead of 1.56 s on a half-black 640 x 180 frame). Below 1.2e-38
/// nothing is visible. Any zero comes out as +0.
#[inline(always)]
fn flush(v: f32) -> f32 {
    if v.abs() < f32::MIN_POSITIVE {
        0.0
    } else {
        v
    }
}

/// Most descent steps fused into one pass over the image.
const MAX_FUSED: usize = 16;

/// Steps fused per pass for rows of `w` pixels: a pass keeps ~100 bytes per pixel of a row
/// live per step (its 3-row ring, the fluxes above, and the input rows in flight), which
/// should stay within ~1 MiB of a core's L2 (1280 wide: 8 steps).
fn fused_steps(w: usize) -> usize {
    ((1 << 20) / (100 * w.max(1))).clamp(2, MAX_FUSED)
}

/// Gradient-descent steps fused in row pipelines (temporal blocking). The 1000 sweeps of the
/// schedule are memory-bound when done one full image at a time (each reads ~64 bytes per
/// pixel); here a pass runs up to [`fused_steps`] steps: step `k` computes row `r` as soon as
/// step `k - 1` has rows `r - 1..=r + 1`, so each step keeps only 3 rows live (a ring) and the
/// inputs are read once per pass while they are in cache. Each edge flux is computed once and
/// shared by its two pixels. Bands of rows run in parallel, each recomputing a halo of
/// `steps` rows, so results do not depend on the thread count; every value is computed with
/// the same operations in the same order as `descend` (the tests' literal step), so the result
/// equals it bit for bit.
pub(crate) struct Sweeper {
    w: usize,
    h: usize,
    /// `a` of the horizontal and vertical edges (shared by the channels).
    ax: Vec<f32>,
    ay: Vec<f32>,
    /// `b` of the horizontal and vertical edges, per channel.
    bx: Vec<f32>,
    by: Vec<f32>,
    /// The energy's part that does not depend on the image, `sum m t^2` over the edges and
    /// channels (rows in parallel, then summed in order).
    constant: f64,
    /// A bound on the largest eigenvalue of the energy's Hessian (per channel), [`edge_bound`]:
    /// a step `s` with `s * lambda_bound < 2` lowers the energy at every step.
    lambda_bound: f64,
}

/// A bound on the largest eigenvalue of the Hessian `H = D^T diag(a) D` of the edges' energy
/// (a weighted graph Laplacian, the edges' `a` its weights: `ax`, `ay` per pixel, zero for the
/// edges past the last column and row): `max over edges (p, q) with a > 0 of d_p + d_q`, `d_p`
/// the sum of `a` over `p`'s edges (Anderson and Morley's bound, which holds for weights: with
/// `x` the Perron vector of `D + W`, `u` its largest entry and `v` its largest neighbour,
/// `(lambda - d_u)(lambda - d_v) <= d_u d_v`; and `lambda_max(L) <= lambda_max(D + W)`). At
/// most Gershgorin's `max_p 2 d_p`, and lower wherever the heaviest pixel's neighbours are
/// lighter: on the validation frames it certifies the schedule's last step on 41 of 48 levels
/// against Gershgorin's 40 (the 7 others, on the studio, dusk and sunsky frames, take every step).
fn edge_bound(w: usize, h: usize, ax: &[f32], ay: &[f32]) -> Result<f64> {
    let n = w * h;
    let mut d = try_zeroed_vec::<f64>(n)?;
    d.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let k = y * w;
        for (x, d) in row.iter_mut().enumerate() {
            let mut s = f64::from(ax[k + x]) + f64::from(ay[k + x]);
            if x > 0 {
                s += f64::from(ax[k + x - 1]);
            }
            if y > 0 {
                s += f64::from(ay[k + x - w]);
            }
            *d = s;
        }
    });
    let d = &d;
    Ok((0..h)
        .into_par_iter()
        .map(|y| {
            let k = y * w;
            let mut m = 0.0f64;
            for x in 0..w {
                if x + 1 < w && ax[k + x] > 0.0 {
                    m = m.max(d[k + x] + d[k + x + 1]);
                }
                if y + 1 < h && ay[k + x] > 0.0 {
                    m = m.max(d[k + x] + d[k + x + w]);
                }
            }
            m
        })
        .reduce(|| 0.0, f64::max))
}

/// Rows `r - 1`, `r`, `r + 1` (the outer ones `None` outside the image) of one channel.
struct Rows<'a> {
    up: Option<&'a [f32]>,
    mid: &'a [f32],
    down: Option<&'a [f32]>,
}

/// Per-band scratch of one fused pass.
struct Scratch {
    /// Steps `1..steps` (the last writes the output): 3 rows x 3 channels each.
    ring: Vec<f32>,
    /// Per step and channel, the vertical fluxes of the edges above the row being computed.
    above: Vec<Vec<f32>>,
    /// The vertical fluxes below the row (then swapped into `above`).
    below: Vec<f32>,
    /// Horizontal fluxes with a zero on either side: `e[x + 1]` is edge `x -> x + 1`.
    across: Vec<f32>,
}

impl Sweeper {
    /// The affine edge terms of the weights and target gradients `gx`, `gy`.
    pub fn new(gx: &[f32], gy: &[f32], wt: &EnhanceWeights) -> Result<Self> {
        let n = wt.w * wt.h;
        let a = |m: &[f32], s: &[f32]| -> Result<Vec<f32>> {
            let mut a = try_vec(m.len(), 0.0)?;
            a.par_iter_mut()
                .zip(m.par_iter().zip(s))
                .for_each(|(a, (&m, &s))| *a = 2.0 * (m + s));
            Ok(a)
        };
        let b = |m: &[f32], t: &[f32]| -> Result<Vec<f32>> {
            let mut b = try_vec(t.len(), 0.0)?;
            b.par_iter_mut()
                .zip(t.par_iter())
                .enumerate()
                .for_each(|(i, (b, &t))| *b = 2.0 * m[i % n] * t);
            Ok(b)
        };
        let (w, h) = (wt.w, wt.h);
        let rows: Vec<f64> = (0..h)
            .into_par_iter()
            .map(|y| {
                let k = y * w;
                let mut acc = 0.0;
                for c in 0..3 {
                    let o = c * n + k;
                    acc += fidelity_constant(&wt.mx[k..k + w - 1], &gx[o..o + w - 1]);
                    if y + 1 < h {
                        acc += fidelity_constant(&wt.my[k..k + w], &gy[o..o + w]);
                    }
                }
                acc
            })
            .collect();
        let (ax, ay) = (a(&wt.mx, &wt.sx)?, a(&wt.my, &wt.sy)?);
        let lambda_bound = edge_bound(w, h, &ax, &ay)?;
        Ok(Sweeper {
            w,
            h,
            ax,
            ay,
            bx: b(&wt.mx, gx)?,
            by: b(&wt.my, gy)?,
            constant: rows.iter().sum(),
            lambda_bound,
        })
    }

    /// Channel `c`'s energy terms of row `y` (`mid`) along its horizontal edges.
    fn across_energy(&self, c: usize, y: usize, mid: &[f32]) -> f64 {
        let (w, n) = (self.w, self.w * self.h);
        let o = y * w;
        edge_energy(
            &self.ax[o..o + w - 1],
            &self.bx[c * n + o..][..w - 1],
            &mid[..w - 1],
            &mid[1..w],
        )
    }

    /// Channel `c`'s energy terms of the vertical edges from row `y` (`mid`) down to `down`.
    fn down_energy(&self, c: usize, y: usize, mid: &[f32], down: &[f32]) -> f64 {
        let (w, n) = (self.w, self.w * self.h);
        let o = y * w;
        edge_energy(&self.ay[o..o + w], &self.by[c * n + o..][..w], mid, down)
    }

    /// The energy from its rows' terms: each row's in order, the rows in order, then the
    /// constant.
    fn total(&self, rows: &[RowEnergy]) -> f64 {
        let h = self.h;
        let per_row = rows.iter().enumerate().map(|(y, r)| {
            let mut acc = 0.0;
            for c in 0..3 {
                acc += r[2 * c];
                if y + 1 < h {
                    acc += r[2 * c + 1];
                }
            }
            acc
        });
        per_row.sum::<f64>() + self.constant
    }

    /// The enhancement energy of `img`, in f64 (the schedule compares energies exactly, and
    /// f32 rounding of a large energy can fake a rise, and a revert, when the step is small).
    /// The summation order is fixed, so the value does not depend on the threads; a pass that
    /// computes it on the way ([`Sweeper::run`]) gets the same bits.
    pub fn loss(&self, img: &[f32]) -> Result<f64> {
        let (w, h) = (self.w, self.h);
        let n = w * h;
        let mut rows: Vec<RowEnergy> = try_vec(h, [0.0; 6])?;
        rows.par_iter_mut().enumerate().for_each(|(y, r)| {
            for c in 0..3 {
                let o = c * n + y * w;
                let mid = &img[o..o + w];
                r[2 * c] = self.across_energy(c, y, mid);
                if y + 1 < h {
                    r[2 * c + 1] = self.down_energy(c, y, mid, &img[o + w..o + 2 * w]);
                }
            }
        });
        Ok(self.total(&rows))
    }

    /// Runs `steps` descent steps from `src` into `dst`; with `energy`, returns the energy of
    /// `dst`, computed as its rows are written (the same bits as [`Sweeper::loss`], without
    /// reading the image again). At 720p the 24 checks of level 0 took 0.17 s as separate
    /// passes (7 ms each); computed on the way, the level's enhancement went 0.37 -> 0.23 s.
    pub fn run(
        &self,
        src: &[f32],
        dst: &mut [f32],
        step: f32,
        steps: usize,
        energy: bool,
    ) -> Result<Option<f64>> {
        let (w, h) = (self.w, self.h);
        let n = w * h;
        assert!(steps >= 1 && src.len() == 3 * n && dst.len() == 3 * n);
        // One band per worker, unless the halo would dwarf it.
        let bands = rayon::current_num_threads()
            .min(h / (4 * steps).max(1))
            .max(1);
        let band = h.div_ceil(bands);
        let mut rows: Vec<RowEnergy> = if energy {
            try_vec(h, [0.0; 6])?
        } else {
            Vec::new()
        };
        {
            let (d0, rest) = dst.split_at_mut(n);
            let (d1, d2) = rest.split_at_mut(n);
            let mut parts: Vec<&mut [RowEnergy]> = rows.chunks_mut(band).collect();
            parts.resize_with(h.div_ceil(band), Default::default);
            d0.par_chunks_mut(band * w)
                .zip(d1.par_chunks_mut(band * w))
                .zip(d2.par_chunks_mut(band * w))
                .zip(parts.into_par_iter())
                .enumerate()
                .try_for_each(|(b, (((o0, o1), o2), e))| {
                    let y0 = b * band;
                    let y1 = (y0 + band).min(h);
                    let e = energy.then_some(e);
                    self.band(src, [o0, o1, o2], e, step, steps, y0, y1)
                })?;
        }
        if !energy {
            return Ok(None);
        }
        // The vertical edges from each band's last row into the next band's first.
        for y in (band - 1..h - 1).step_by(band) {
            for c in 0..3 {
                let o = c * n + y * w;
                let (mid, down) = (&dst[o..o + w], &dst[o + w..o + 2 * w]);
                rows[y][2 * c + 1] = self.down_energy(c, y, mid, down);
            }
        }
        Ok(Some(self.total(&rows)))
    }

    /// One band: output rows `y0..y1`, from input rows `y0 - steps..y1 + steps`; with
    /// `energy`, each output row's terms (the vertical edges into the next band are left to
    /// the caller).
    #[allow(clippy::too_many_arguments)]
    fn band(
        &self,
        src: &[f32],
        out: [&mut [f32]; 3],
        mut energy: Option<&mut [RowEnergy]>,
        step: f32,
        steps: usize,
        y0: usize,
        y1: usize,
    ) -> Result<()> {
        let (w, h) = (self.w, self.h);
        let n = w * h;
        let lo = y0.saturating_sub(steps);
        let hi = (y1 + steps).min(h);
        // Rows step k can compute: the band shrinks by one row per step, except at the image
        // border.
        let first = |k: usize| if lo == 0 { 0 } else { lo + k };
        let end = |k: usize| if hi == h { h } else { hi - k };
        let mut s = Scratch {
            ring: try_vec(steps.saturating_sub(1) * 9 * w, 0.0)?,
            above: (0..steps * 3)
                .map(|_| try_vec(w, 0.0))
                .collect::<Result<_>>()?,
            below: vec![0.0; w],
            across: vec![0.0; w + 1],
        };
        for j in lo..hi + steps {
            for k in 1..=steps {
                let Some(r) = j.checked_sub(k) else { break };
                if r < first(k) || r >= end(k) || (k == steps && (r < y0 || r >= y1)) {
                    continue;
                }
                // The previous step's rings (or the source) are read, this step's written.
                let (prev, cur) = s.ring.split_at_mut(k.saturating_sub(1) * 9 * w);
                let prev: &[f32] = if k >= 2 {
                    &prev[(k - 2) * 9 * w..]
                } else {
                    &[]
                };
                for c in 0..3 {
                    let row = |rr: usize| -> &[f32] {
                        if k == 1 {
                            &src[c * n + rr * w..c * n + (rr + 1) * w]
                        } else {
                            let o = ((rr % 3) * 3 + c) * w;
                            &prev[o..o + w]
                        }
                    };
                    let rows = Rows {
                        up: (r > 0).then(|| row(r - 1)),
                        mid: row(r),
                        down: (r + 1 < h).then(|| row(r + 1)),
                    };
                    let dst: &mut [f32] = if k == steps {
                        let o = (r - y0) * w;
                        &mut out[c][o..o + w]
                    } else {
                        let o = ((r % 3) * 3 + c) * w;
                        &mut cur[o..o + w]
                    };
                    let above = &mut s.above[(k - 1) * 3 + c];
                    if r == first(k) {
                        self.vertical_fluxes(c, r.wrapping_sub(1), rows.up, Some(rows.mid), above);
                    }
                    self.vertical_fluxes(c, r, Some(rows.mid), rows.down, &mut s.below);
                    self.row(c, r, &rows, above, &s.below, &mut s.across, dst, step);
                    std::mem::swap(above, &mut s.below);
                }
                if let (true, Some(e)) = (k == steps, energy.as_deref_mut()) {
                    // Row r is written: its horizontal edges, and the vertical ones from r - 1.
                    let i = r - y0;
                    for (c, plane) in out.iter().enumerate() {
                        let mid = &plane[i * w..(i + 1) * w];
                        e[i][2 * c] = self.across_energy(c, r, mid);
                        if i > 0 {
                            let up = &plane[(i - 1) * w..i * w];
                            e[i - 1][2 * c + 1] = self.down_energy(c, r - 1, up, mid);
                        }
                    }
                }
            }
        }
        Ok(())
    }

    /// Fluxes of the vertical edges `r -> r + 1` (zero when either row is missing).
    fn vertical_fluxes(
        &self,
        c: usize,
        r: usize,
        a: Option<&[f32]>,
        b: Option<&[f32]>,
        out: &mut [f32],
    ) {
        let w = self.w;
        match (a, b) {
            (Some(lo), Some(hi)) => {
                let o = r * w;
                let bias = &self.by[c * w * self.h + o..][..w];
                edge_fluxes(&self.ay[o..o + w], bias, lo, hi, out);
            }
            _ => out.fill(0.0),
        }
    }

    /// One row of one step, with the same operations in the same order as `descend`.
    #[allow(clippy::too_many_arguments)]
    fn row(
        &self,
        c: usize,
        r: usize,
        rows: &Rows,
        above: &[f32],
        below: &[f32],
        across: &mut [f32],
        dst: &mut [f32],
        step: f32,
    ) {
        let w = self.w;
        let o = r * w;
        let bias = &self.bx[c * w * self.h + o..][..w - 1];
        let mid = rows.mid;
        across[0] = 0.0;
        across[w] = 0.0;
        edge_fluxes(
            &self.ax[o..o + w - 1],
            bias,
            &mid[..w - 1],
            &mid[1..],
            &mut across[1..w],
        );
        update(mid, &across[1..], &across[..w], below, above, dst, step);
    }
}

/// `out = flux(a, b, hi - lo)` element-wise. The two kernels below are also compiled for AVX-512
/// and for AVX2, picked at run time: the same bits (Rust never fuses a multiply-add); AVX-512
/// is the faster of the two here.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn edge_fluxes(a: &[f32], b: &[f32], lo: &[f32], hi: &[f32], out: &mut [f32]) {
    let n = out.len();
    let (a, b, lo, hi) = (&a[..n], &b[..n], &lo[..n], &hi[..n]);
    for x in 0..n {
        out[x] = flux(a[x], b[x], hi[x] - lo[x]);
    }
}

/// `dst = flush(mid - step * g)` with `g = 0 - right + left - below + above`, as the literal
/// sweep accumulates it (a missing edge contributes an exact zero, which can only change the
/// sign of a zero `g`, which the flush makes irrelevant).
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn update(
    mid: &[f32],
    right: &[f32],
    left: &[f32],
    below: &[f32],
    above: &[f32],
    dst: &mut [f32],
    step: f32,
) {
    let n = dst.len();
    let (mid, right, left, below, above) =
        (&mid[..n], &right[..n], &left[..n], &below[..n], &above[..n]);
    for x in 0..n {
        let g = 0.0 - right[x] + left[x] - below[x] + above[x];
        dst[x] = flush(mid[x] - step * g);
    }
}

/// What the reference schedule did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct EnhanceOutcome {
    /// Step halvings (each reverted the image to the start).
    pub reverts: u32,
    /// Energy at the start and at the end.
    pub loss_start: f64,
    /// Energy of the result.
    pub loss_end: f64,
    /// When the last steps were taken as one Chebyshev polynomial ([`chebyshev`]): how many,
    /// and the polynomial's degree (the products with the Hessian it took).
    pub polynomial: Option<(u32, usize)>,
}

/// [`enhance_or_stop`], never stopped (the tests' entry point).
#[cfg(test)]
pub(crate) fn enhance_reference(
    guide: &Image,
    dx: &Image,
    dy: &Image,
    wt: &EnhanceWeights,
    iterations: u32,
) -> (Image, EnhanceOutcome) {
    enhance_or_stop(guide, dx, dy, wt, iterations, false, &Progress::none()).expect("allocated")
}

/// The release's schedule; returns the enhanced image. With `polynomial`, once the step is
/// small enough that no revert can follow (`step * lambda_bound < 2`, the image at the start),
/// the remaining steps are taken at once as a Chebyshev polynomial ([`chebyshev`]; the same
/// image up to its [`chebyshev::TOLERANCE`] and rounding), unless it would be no shorter;
/// without, every step is taken. Once `stop` is cancelled it ends early and returns the guide
/// (the caller checks `stop`). Fails only with [`Error::OutOfMemory`](crate::Error::OutOfMemory).
pub(crate) fn enhance_or_stop(
    guide: &Image,
    dx: &Image,
    dy: &Image,
    wt: &EnhanceWeights,
    iterations: u32,
    polynomial: bool,
    stop: &Progress,
) -> Result<(Image, EnhanceOutcome)> {
    let (gx, gy) = (dx.as_slice(), dy.as_slice());
    let start = guide.as_slice();
    // A cancel returns the guide.
    let cancelled = || Ok((guide.try_clone()?, EnhanceOutcome::default()));
    let mut cur = try_zeroed_vec(start.len())?;
    cur.copy_from_slice(start);
    let mut next = try_zeroed_vec::<f32>(start.len())?;
    let mut step = 1e-4f32;
    let sweeper = Sweeper::new(gx, gy, wt)?;
    let loss_start = sweeper.loss(start)?;
    let mut best = loss_start;
    // The energy of `cur`, when known.
    let mut cur_loss = Some(loss_start);
    let mut reverts = 0;
    let mut it = 0;
    // `cur` is the start (at iteration 0 and after each revert): where the polynomial may
    // take over, and where the steps restart should it not lower the energy.
    let (mut at_start, mut polynomial, mut taken) = (true, polynomial, None);
    while it < iterations {
        let z_max = f64::from(step) * sweeper.lambda_bound;
        if let Some(c) = (polynomial && at_start)
            .then(|| chebyshev::series((iterations - it) as usize, z_max))
            .flatten()
        {
            if !chebyshev::descend(&sweeper, &mut cur, &mut next, step, z_max, &c, stop) {
                return cancelled();
            }
            let l = sweeper.loss(&cur)?;
            if l.is_finite() && l <= best {
                (best, cur_loss) = (l, Some(l));
                taken = Some((iterations - it, c.len() - 1));
                break;
            }
            // Never seen: the steps take over from the start.
            cur.copy_from_slice(start);
            polynomial = false;
        }
        at_start = false;
        // Steps up to the next loss check (after each of the first 20, then every 50th),
        // fused into passes of at most fused_steps(w) steps; the pass that ends on a check
        // also computes the energy.
        let check = if it < 20 { it } else { it.div_ceil(50) * 50 };
        let last = check.min(iterations - 1);
        let mut todo = (last - it + 1) as usize;
        let passes = todo.div_ceil(fused_steps(guide.width()));
        for p in 0..passes {
            if stop.stopped() {
                break;
            }
            let steps = todo / (passes - p);
            let energy = p + 1 == passes && last == check;
            cur_loss = sweeper.run(&cur, &mut next, step, steps, energy)?;
            std::mem::swap(&mut cur, &mut next);
            todo -= steps;
        }
        if stop.stopped() {
            return cancelled();
        }
        it = last + 1;
        if let Some(l) = cur_loss {
            if l > best || !l.is_finite() {
                // Revert to the start, and with it the best loss: keeping the best of the
                // diverged attempt would make every slower restart look like a rise (seen on
                // coarse levels: the step halved 36 times and the level stayed unenhanced).
                step *= 0.5;
                reverts += 1;
                cur.copy_from_slice(start);
                best = loss_start;
                cur_loss = Some(loss_start);
                at_start = true;
            } else {
                best = l;
            }
        }
    }
    let mut loss_end = match cur_loss {
        Some(l) => l,
        None => sweeper.loss(&cur)?,
    };
    if loss_end > best || !loss_end.is_finite() {
        // The steps after the last check rose: the step was too large for them (seen on
        // garbage frames, where they overflowed). The release returns the diverged image; we
        // return the start, the guide. Every frame that descends to the end is unaffected.
        reverts += 1;
        cur.copy_from_slice(start);
        loss_end = loss_start;
    }
    // The image is `cur` itself, not a copy.
    let out = Array3::from_shape_vec(guide.planes().raw_dim(), cur).expect("the guide's shape");
    Ok((
        Image::from_planes(out),
        EnhanceOutcome {
            reverts,
            loss_start,
            loss_end,
            polynomial: taken,
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::super::util::with_threads;
    use super::*;

    fn ramp(w: usize, h: usize) -> Image {
        Image::from_fn(3, w, h, |(c, x, y)| {
            0.1 * x as f32 + 0.05 * y as f32 + 0.2 * c as f32
        })
    }

    /// The weights edge by edge, as the module's formulas state them (the form before the
    /// row kernels).
    fn literal_weights(
        dx: &Image,
        dy: &Image,
        features: [Option<&Image>; 2],
        lambda: f32,
    ) -> [Vec<f32>; 4] {
        let (w, h) = dx.size();
        let n = w * h;
        let fid = |g: &Image, i: usize| {
            let s = g.as_slice();
            let g = s[i].abs() + s[n + i].abs() + s[2 * n + i].abs() + EPS;
            let m = g / T + 1.0 / g;
            m * m
        };
        let l1 = |img: &Image, i: usize, j: usize| -> f32 {
            let s = img.as_slice();
            (0..img.channels())
                .map(|c| (s[c * n + j] - s[c * n + i]).abs())
                .sum()
        };
        let smooth = |i: usize, j: usize| {
            if features.iter().all(Option::is_none) {
                return 0.0;
            }
            let [a, f] = features;
            let d = a.map_or(0.0, |a| l1(a, i, j)) + f.map_or(0.0, |f| l1(f, i, j));
            lambda / ((d + EPS) * (d + EPS))
        };
        let mut out = [(); 4].map(|_| vec![0.0f32; n]);
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if x + 1 < w {
                    out[0][i] = fid(dx, i);
                    out[2][i] = smooth(i, i + 1);
                }
                if y + 1 < h {
                    out[1][i] = fid(dy, i);
                    out[3][i] = smooth(i, i + w);
                }
            }
        }
        out
    }

    #[test]
    fn row_weights_equal_the_per_edge_formulas_bit_for_bit() {
        for (w, h) in [(1, 1), (1, 5), (6, 1), (9, 7), (37, 4)] {
            let (dx, dy) = (wave(3, w, h, 1), wave(3, w, h, 2));
            let (alb, nrm) = (wave(3, w, h, 3), wave(3, w, h, 4));
            for features in [
                [None, None],
                [Some(&alb), None],
                [None, Some(&nrm)],
                [Some(&alb), Some(&nrm)],
            ] {
                let got = EnhanceWeights::new(&dx, &dy, features[0], features[1], 0.7).unwrap();
                let want = literal_weights(&dx, &dy, features, 0.7);
                for (k, got) in [&got.mx, &got.my, &got.sx, &got.sy].into_iter().enumerate() {
                    let bits = |v: &[f32]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(got), bits(&want[k]), "{w} x {h}, weight {k}");
                }
            }
        }
    }

    #[test]
    fn loss_and_descent_agree_with_a_finite_difference_of_the_energy() {
        let (w, h) = (6, 5);
        let img = Image::from_fn(3, w, h, |(c, x, y)| ((x * 7 + y * 3 + c) % 5) as f32 * 0.1);
        let (dx, dy) = ramp(w, h).forward_differences();
        let alb = Image::from_fn(
            3,
            w,
            h,
            |(c, x, _)| if x > 2 { 0.5 } else { 0.1 * c as f32 },
        );
        let wt = EnhanceWeights::new(&dx, &dy, Some(&alb), None, 0.7).unwrap();
        let step = 1e-3f32;
        let mut next = vec![0.0; img.as_slice().len()];
        let terms = Sweeper::new(dx.as_slice(), dy.as_slice(), &wt).unwrap();
        descend(img.as_slice(), &mut next, &terms, step);
        for k in [0usize, 7, 31, 58, 89] {
            let g = (img.as_slice()[k] - next[k]) / step;
            let mut plus = img.as_slice().to_vec();
            let e = 1e-2;
            plus[k] += e;
            let mut minus = img.as_slice().to_vec();
            minus[k] -= e;
            let fd =
                (terms.loss(&plus).unwrap() - terms.loss(&minus).unwrap()) / (2.0 * f64::from(e));
            assert!(
                (f64::from(g) - fd).abs() < 1e-2 * fd.abs().max(1.0),
                "k {k}: {g} vs {fd}"
            );
        }
    }

    /// The schedule with one literal sweep per step: the oracle of the fused passes.
    fn enhance_literal(
        guide: &Image,
        dx: &Image,
        dy: &Image,
        wt: &EnhanceWeights,
        iterations: u32,
    ) -> Vec<f32> {
        let (gx, gy) = (dx.as_slice(), dy.as_slice());
        let start = guide.as_slice();
        let mut cur = start.to_vec();
        let mut next = vec![0.0f32; cur.len()];
        let mut step = 1e-4f32;
        let terms = Sweeper::new(gx, gy, wt).unwrap();
        let loss_start = terms.loss(start).unwrap();
        let mut best = loss_start;
        for it in 0..iterations {
            descend(&cur, &mut next, &terms, step);
            std::mem::swap(&mut cur, &mut next);
            if it < 20 || it % 50 == 0 {
                let l = terms.loss(&cur).unwrap();
                if l > best || !l.is_finite() {
                    step *= 0.5;
                    cur.copy_from_slice(start);
                    best = loss_start;
                } else {
                    best = l;
                }
            }
        }
        let l = terms.loss(&cur).unwrap();
        if l > best || !l.is_finite() {
            cur.copy_from_slice(start);
        }
        cur
    }

    /// `steps` descent steps in f64 from `start` (the same `a`, `b` as the f32 steps): exact
    /// arithmetic, to see which of two f32 results is nearer it.
    fn descend_f64(start: &[f32], e: &Sweeper, step: f32, steps: u32) -> Vec<f64> {
        let (w, h) = (e.w, e.h);
        let n = w * h;
        let mut cur: Vec<f64> = start.iter().map(|&v| f64::from(v)).collect();
        let mut next = cur.clone();
        let f = |a: f32, b: f32, d: f64| f64::from(a) * d - f64::from(b);
        for _ in 0..steps {
            for (i, out) in next.iter_mut().enumerate() {
                let k = i % n;
                let (x, y) = (k % w, k / w);
                let mut g = 0.0;
                if x + 1 < w {
                    g -= f(e.ax[k], e.bx[i], cur[i + 1] - cur[i]);
                }
                if x >= 1 {
                    g += f(e.ax[k - 1], e.bx[i - 1], cur[i] - cur[i - 1]);
                }
                if y + 1 < h {
                    g -= f(e.ay[k], e.by[i], cur[i + w] - cur[i]);
                }
                if y >= 1 {
                    g += f(e.ay[k - w], e.by[i - w], cur[i] - cur[i - w]);
                }
                *out = cur[i] - f64::from(step) * g;
            }
            std::mem::swap(&mut cur, &mut next);
        }
        cur
    }

    fn textured(w: usize, h: usize, seed: usize) -> Image {
        Image::from_fn(3, w, h, |(c, x, y)| {
            let k = (x * 7919 + y * 104_729 + c * 1_299_709 + seed * 15_485_863) % 1000;
            let base = if x > w / 2 { 0.8 } else { 0.2 } + 0.05 * c as f32;
            base + 0.3 * (k as f32 / 1000.0 - 0.5)
        })
    }

    /// A noisy textured start, the exact gradients of another texture and the weights
    /// (albedo on, lambda 0.7).
    fn problem(w: usize, h: usize) -> (Image, Image, Image, EnhanceWeights) {
        let (dx, dy) = textured(w, h, 1).forward_differences();
        let wt = EnhanceWeights::new(&dx, &dy, Some(&textured(w, h, 3)), None, 0.7).unwrap();
        (textured(w, h, 2), dx, dy, wt)
    }

    #[test]
    fn fused_passes_equal_the_literal_sweeps_bit_for_bit() {
        // Odd sizes, a band split with halos (3 threads), features on, several schedule
        // segments (iterations 0..20 one by one, then fused passes up to 50, 100, 130), and a
        // half-black region that goes through the subnormal flush. Tall frames split into bands.
        for (w, h, iters, threads) in [
            (37, 29, 130, 3),
            (64, 90, 75, 2),
            (5, 3, 30, 1),
            (1, 40, 60, 2),
        ] {
            let (mut noisy, dx, dy, wt) = problem(w, h);
            noisy
                .as_mut_slice()
                .iter_mut()
                .enumerate()
                .for_each(|(i, v)| {
                    if (i % (w * h)) % w < w / 4 {
                        *v = 0.0
                    }
                });
            let want = enhance_literal(&noisy, &dx, &dy, &wt, iters);
            let (got, _) =
                with_threads(threads, || enhance_reference(&noisy, &dx, &dy, &wt, iters));
            let same = got
                .as_slice()
                .iter()
                .zip(&want)
                .all(|(a, b)| a.to_bits() == b.to_bits());
            assert!(same, "{w} x {h}, {iters} iterations, {threads} threads");
        }
    }

    #[test]
    fn the_energy_computed_in_a_pass_equals_the_loss_of_its_output() {
        // Bands of several sizes (1 to 3 threads), their seams, the image's last row, odd
        // widths, one-row and one-column images.
        for (w, h, steps, threads) in [
            (37, 29, 3, 3),
            (64, 90, 8, 2),
            (5, 3, 1, 1),
            (1, 40, 2, 2),
            (9, 1, 1, 2),
        ] {
            let (noisy, dx, dy, wt) = problem(w, h);
            let sweeper = Sweeper::new(dx.as_slice(), dy.as_slice(), &wt).unwrap();
            let mut out = vec![0.0; 3 * w * h];
            let energy = with_threads(threads, || {
                sweeper
                    .run(noisy.as_slice(), &mut out, 1e-3, steps, true)
                    .unwrap()
            });
            let want = sweeper.loss(&out).unwrap();
            assert_eq!(
                energy.map(f64::to_bits),
                Some(want.to_bits()),
                "{w} x {h}, {threads} threads"
            );
            // And the (a, b) form is the release's energy up to the f32 rounding of `a` and `b`
            // (relative 6e-8 each), which scales with the parts, `sum m t^2` among them.
            let literal = literal_energy(&out, dx.as_slice(), dy.as_slice(), &wt);
            assert!(
                (want - literal).abs() < 2e-7 * (literal + sweeper.constant),
                "{want} vs {literal}"
            );
        }
    }

    /// `sum m (d - t)^2 + s d^2` over the edges and channels, in f64, as the release writes it.
    fn literal_energy(img: &[f32], gx: &[f32], gy: &[f32], wt: &EnhanceWeights) -> f64 {
        let (w, h) = (wt.w, wt.h);
        let n = w * h;
        let mut e = 0.0;
        for c in 0..3 {
            for y in 0..h {
                for x in 0..w {
                    let (i, o) = (y * w + x, c * n + y * w + x);
                    let term = |m: f32, s: f32, d: f32, t: f32| {
                        let (m, s, d, t) = (f64::from(m), f64::from(s), f64::from(d), f64::from(t));
                        m * (d - t) * (d - t) + s * d * d
                    };
                    if x + 1 < w {
                        e += term(wt.mx[i], wt.sx[i], img[o + 1] - img[o], gx[o]);
                    }
                    if y + 1 < h {
                        e += term(wt.my[i], wt.sy[i], img[o + w] - img[o], gy[o]);
                    }
                }
            }
        }
        e
    }

    #[test]
    fn valid_gradients_of_the_start_are_a_fixed_point() {
        let img = ramp(8, 6);
        let (dx, dy) = img.forward_differences();
        let wt = EnhanceWeights::new(&dx, &dy, None, None, 0.0).unwrap();
        let (out, outcome) = enhance_reference(&img, &dx, &dy, &wt, 100);
        // 0 up to the f32 rounding of the edges' `a` and `b` (relative 6e-8 of the parts,
        // here sum m t^2 = 60).
        assert!(outcome.loss_end.abs() < 1e-5, "{outcome:?}");
        assert_eq!(outcome.reverts, 0);
        assert!(out
            .as_slice()
            .iter()
            .zip(img.as_slice())
            .all(|(a, b)| (a - b).abs() < 1e-5));
    }

    #[test]
    fn a_diverging_first_step_does_not_freeze_the_schedule() {
        // Zero target gradients give m = (0.01 / 0.09 + 100)^2 ~ 1e4: the initial step 1e-4 is
        // unstable, the schedule must halve it and then make progress from the start.
        let (w, h) = (40, 30);
        let noisy = Image::from_fn(3, w, h, |(c, x, y)| {
            0.5 + 0.1 * (((x * 7 + y * 13 + c * 5) % 11) as f32 / 11.0 - 0.5)
        });
        let zero = Image::zeros(3, w, h);
        let wt = EnhanceWeights::new(&zero, &zero, None, None, 0.0).unwrap();
        let (_, outcome) = enhance_reference(&noisy, &zero, &zero, &wt, 1000);
        assert!(outcome.reverts >= 1 && outcome.reverts < 10, "{outcome:?}");
        assert!(outcome.loss_end < 0.1 * outcome.loss_start, "{outcome:?}");
    }

    /// The schedule with the polynomial (`enhance_or_stop`, `polynomial`) on `threads`.
    fn enhance_polynomial(
        guide: &Image,
        (dx, dy): (&Image, &Image),
        wt: &EnhanceWeights,
        iterations: u32,
        threads: usize,
    ) -> (Image, EnhanceOutcome) {
        with_threads(threads, || {
            enhance_or_stop(guide, dx, dy, wt, iterations, true, &Progress::none()).unwrap()
        })
    }

    #[test]
    fn the_polynomial_gives_the_steps_image_within_its_tolerance() {
        // Sizes with one row, one and two columns, odd sizes, features on; 250 (the default)
        // and 1000 (the release's) iterations. The steps' image is the literal oracle's; the
        // polynomial's is within 4e-3 of the largest change the steps make (seen with the
        // series truncated at 1e-4: 3.1e-4 to 8.7e-4 at 250 steps, 6.5e-4 to 2.2e-3 at 1000;
        // at 1e-7, 1e-6 to 2.1e-5, f32 rounding).
        for (w, h) in [(37, 29), (64, 90), (1, 40), (2, 7), (40, 1)] {
            for iters in [250, 1000] {
                let (noisy, dx, dy, wt) = problem(w, h);
                let want = enhance_literal(&noisy, &dx, &dy, &wt, iters);
                let (got, outcome) = enhance_polynomial(&noisy, (&dx, &dy), &wt, iters, 3);
                let (steps, degree) = outcome.polynomial.expect("the polynomial was taken");
                assert!(
                    steps > iters - 20 && 4 * degree < steps as usize,
                    "{outcome:?}"
                );
                let change = want
                    .iter()
                    .zip(noisy.as_slice())
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0f32, f32::max);
                let err = got
                    .as_slice()
                    .iter()
                    .zip(&want)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0f32, f32::max);
                assert!(
                    change > 0.01,
                    "{w} x {h}: the steps change the image ({change})"
                );
                assert!(
                    err <= 4e-3 * change,
                    "{w} x {h}, {iters}: {err:e} of {change:e}"
                );
                // Against the same steps in exact arithmetic (f64) from the same start (the last
                // revert's): the f32 steps within 1e-5 of the image's largest value (seen: 3.2e-7
                // to 3.9e-6), the polynomial within 2e-3 (seen: 9.8e-5 to 2.3e-4 at 250 steps,
                // 3.3e-4 to 1.04e-3 at 1000, the largest on 2 x 7: the series' truncation; at a
                // truncation of 1e-7, 3.9e-7 to 1.3e-5, its rounding).
                let sweeper = Sweeper::new(dx.as_slice(), dy.as_slice(), &wt).unwrap();
                let step = 1e-4 * 0.5f32.powi(outcome.reverts as i32);
                let exact = descend_f64(noisy.as_slice(), &sweeper, step, steps);
                let off = |img: &[f32]| {
                    img.iter()
                        .zip(&exact)
                        .map(|(&a, b)| (f64::from(a) - b).abs())
                        .fold(0.0f64, f64::max)
                };
                let peak = exact.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                let (poly, literal) = (off(got.as_slice()), off(&want));
                assert!(
                    poly <= 2e-3 * peak,
                    "{w} x {h}, {iters}: {poly:e} of {peak}"
                );
                assert!(
                    literal <= 1e-5 * peak,
                    "{w} x {h}, {iters}: {literal:e} of {peak}"
                );
            }
        }
    }

    #[test]
    fn the_edge_bound_bounds_the_largest_eigenvalue_and_gershgorin_bounds_it() {
        // The largest eigenvalue of H by power iteration (a lower estimate, from below), on
        // the test problem and on weights with one heavy pixel (where the bound is tighter).
        let (_, dx, dy, wt) = problem(23, 17);
        let mut heavy = Sweeper::new(dx.as_slice(), dy.as_slice(), &wt).unwrap();
        let light = Sweeper::new(dx.as_slice(), dy.as_slice(), &wt).unwrap();
        let k = 8 * 23 + 11;
        for e in [k, k - 1] {
            heavy.ax[e] *= 100.0;
        }
        for e in [k, k - 23] {
            heavy.ay[e] *= 100.0;
        }
        heavy.lambda_bound = edge_bound(23, 17, &heavy.ax, &heavy.ay).unwrap();
        let mut bounds = Vec::new();
        for e in [&light, &heavy] {
            let (w, h) = (e.w, e.h);
            let hv = |v: &[f64]| -> Vec<f64> {
                let mut out = vec![0.0; w * h];
                for y in 0..h {
                    for x in 0..w {
                        let p = y * w + x;
                        if x + 1 < w {
                            let f = f64::from(e.ax[p]) * (v[p] - v[p + 1]);
                            out[p] += f;
                            out[p + 1] -= f;
                        }
                        if y + 1 < h {
                            let f = f64::from(e.ay[p]) * (v[p] - v[p + w]);
                            out[p] += f;
                            out[p + w] -= f;
                        }
                    }
                }
                out
            };
            let mut v: Vec<f64> = (0..w * h).map(|i| ((i * 7919) % 13) as f64 - 6.0).collect();
            let mut lambda = 0.0;
            for _ in 0..2000 {
                let u = hv(&v);
                let norm = u.iter().map(|a| a * a).sum::<f64>().sqrt();
                lambda = norm / v.iter().map(|a| a * a).sum::<f64>().sqrt();
                v = u.iter().map(|a| a / norm).collect();
            }
            let gershgorin = (0..w * h)
                .map(|p| {
                    let (x, y) = (p % w, p / w);
                    let mut d = f64::from(e.ax[p]) + f64::from(e.ay[p]);
                    if x > 0 {
                        d += f64::from(e.ax[p - 1]);
                    }
                    if y > 0 {
                        d += f64::from(e.ay[p - w]);
                    }
                    2.0 * d
                })
                .fold(0.0, f64::max);
            let b = e.lambda_bound;
            assert!(
                lambda <= b * (1.0 + 1e-9) && b <= gershgorin,
                "{lambda} {b} {gershgorin}"
            );
            bounds.push((b, gershgorin));
        }
        // The heavy pixel's neighbours are lighter (a star): the bound is well under 2 d_max.
        assert!(bounds[1].0 < 0.85 * bounds[1].1, "{bounds:?}");
    }

    #[test]
    fn the_polynomial_does_not_depend_on_the_thread_count() {
        let (noisy, dx, dy, wt) = problem(53, 70);
        let (one, _) = enhance_polynomial(&noisy, (&dx, &dy), &wt, 250, 1);
        for threads in [2, 3] {
            let (got, _) = enhance_polynomial(&noisy, (&dx, &dy), &wt, 250, threads);
            let same = got
                .as_slice()
                .iter()
                .zip(one.as_slice())
                .all(|(a, b)| a.to_bits() == b.to_bits());
            assert!(same, "{threads} threads");
        }
    }

    #[test]
    fn descent_lowers_the_energy_from_a_noisy_start() {
        let clean = ramp(16, 12);
        let (dx, dy) = clean.forward_differences();
        let noisy = Image::from_fn(3, 16, 12, |(c, x, y)| {
            clean.at(c, x, y) + if (x + y) % 2 == 0 { 0.05 } else { -0.05 }
        });
        let wt = EnhanceWeights::new(&dx, &dy, None, None, 0.0).unwrap();
        let (_, outcome) = enhance_reference(&noisy, &dx, &dy, &wt, 300);
        assert!(outcome.loss_end < 0.5 * outcome.loss_start, "{outcome:?}");
    }
}
