//! The pre-denoiser: the first pass of RDFC (Rousselle et al. 2013), as the FRGR release uses
//! it to make the guide image.
//!
//! Three candidate non-local-means filters over a 21 x 21 window, each joint with a bilateral
//! term on albedo and normal: `(k_c, f) = (0.45, 1)`, `(0.45, 3)` and `(inf, 3)` (colour term
//! off), feature bandwidth `k_f = 0.6`. Distances (per channel, averaged over channels):
//! - colour, Eq. 5-6: `((c_p - c_q)^2 - (v_p + min(v_p, v_q))) / (1e-10 + k_c^2 (v_p + v_q))`,
//!   averaged over a `(2f+1)^2` patch;
//! - feature, Eq. 7: `(f_p - f_q)^2 / (k_f^2 D_p)`, `D_p = max(var_f, |grad f|^2, 1e-3)` with
//!   the feature variance taken as 0 (bundles carry none; the features are rendered with many
//!   samples).
//!
//! The weight is `min(w_colour, w_albedo, w_normal)` = `exp(-max(d_c, d_a, d_n, 0))`; the
//! centre pixel takes the largest neighbour weight (at least 1e-3). Per candidate, SURE
//! `sum_c (F_c - c_c)^2 - v_c + 2 v_c w_centre / sum w` estimates the error; the SURE maps are
//! smoothed (3 x 3 box: our choice, the release's smoothing is unspecified), the per-pixel
//! argmin makes a one-hot selection map, which is smoothed by the same kind of filter (7 x 7
//! window, 3 x 3 patch, `k_c = 0.5`, `k_f = 0.6`) and used to blend the candidates.
//!
//! Cost: per window offset and pixel, three weights (one `exp` each) and their accumulation
//! into the three candidates' sums, plus the colour and feature distances and the patch sums,
//! all vectorised. The image is cut into 256 x 16 tiles, filtered in parallel; each tile loops
//! over the offsets and, per offset, over its rows, so that its inputs (with the window's
//! margin) and accumulators stay in the core's cache instead of one full-image pass per step
//! and offset. Inputs are padded by the window radius (reflect-101) so that a neighbour row is
//! a slice; the colour distance is computed once per offset for the tile and a `patch` margin
//! (reflected beyond the image's borders, columns and rows, so that no sum needs `reflect`),
//! then patch-summed by shifted-slice sums over the whole tile at once (up to 8 rows per pass;
//! with the release's radii 1 and 3, the radius-3 sums reuse radius-1 sums in both directions:
//! three terms instead of seven), so a candidate costs about the same for any patch size;
//! offsets are weighed in pairs (one pass over the accumulators for two offsets, the same sums
//! in the same order), and their colour and feature distances are computed in pairs too (the
//! row's own pixels read once for both, the two features' distances in one pass: the same
//! values, tested bit for bit); the exponential is a branch-free polynomial (`fastmath`), which
//! vectorises where libm's `expf` does not. The row kernels are also compiled for AVX-512 and
//! for AVX2 + FMA, picked at run time (`multiversion`); the exponential's polynomial, the
//! accumulations and the squared differences are `fastmath::madd`s, one FMA instruction in
//! those two builds (the same bits in both), a multiply and an add in the baseline build for a
//! CPU without FMA (Rust never fuses them on its own). The colour, variance and features are
//! padded once for both filters (the candidates' and the selection's; the first reads the
//! colour as its data), and each tile writes its part of the output rows itself instead of
//! returning a tile to be copied into place. What each of these gained is in
//! `docs/benchmarks.md`. The previous implementation is kept in the tests as the reference.

use rayon::prelude::*;

use super::fastmath::{exp_nonpositive, fused, madd, max, min};
use super::util::{reflect, reflect_borders, PaddedRows};
use crate::error::Result;
use crate::image::{try_vec, try_zeroed_vec, Image};
use crate::progress::Progress;

/// One candidate filter: patch radius `f` and colour bandwidth (`None`: colour term off).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Candidate {
    pub patch: usize,
    pub kc: Option<f32>,
}

/// The release's three candidates.
pub(crate) const CANDIDATES: [Candidate; 3] = [
    Candidate {
        patch: 1,
        kc: Some(0.45),
    },
    Candidate {
        patch: 3,
        kc: Some(0.45),
    },
    Candidate { patch: 3, kc: None },
];

const KF: f32 = 0.6;

/// A feature buffer with its per-pixel normaliser `k_f^2 D_p`.
pub(crate) struct Feature<'a> {
    img: &'a Image,
    norm: Vec<f32>,
}

impl<'a> Feature<'a> {
    /// Prepares a feature: `D_p = max(|grad f|^2 (central differences, mean over channels), 1e-3)`.
    /// Row by row, over slices (reflect-101 only at a row's two ends and in the choice of the
    /// rows above and below), so that the interior vectorises; the sums are those of the
    /// pixel-by-pixel form, in its order (tested bit for bit).
    pub fn new(img: &'a Image) -> Result<Self> {
        let (w, h) = img.size();
        let ch = img.channels();
        let n = w * h;
        let s = img.as_slice();
        let mut norm = try_zeroed_vec::<f32>(n)?;
        if n == 0 {
            return Ok(Feature { img, norm });
        }
        norm.par_chunks_mut(w).enumerate().for_each(|(y, g2)| {
            let (up, down) = (reflect(y as isize - 1, h), reflect(y as isize + 1, h));
            for c in 0..ch {
                let plane = &s[c * n..(c + 1) * n];
                let row = &plane[y * w..(y + 1) * w];
                let (above, below) = (&plane[up * w..][..w], &plane[down * w..][..w]);
                let add = |g2: &mut f32, right: f32, left: f32, lower: f32, upper: f32| {
                    let gx = 0.5 * (right - left);
                    let gy = 0.5 * (lower - upper);
                    *g2 += gx * gx + gy * gy;
                };
                // The two end columns (one when the row has one pixel) read across the border.
                let at = |x: isize| row[reflect(x, w)];
                for x in std::iter::once(0).chain((w > 1).then_some(w - 1)) {
                    let xi = x as isize;
                    add(&mut g2[x], at(xi + 1), at(xi - 1), below[x], above[x]);
                }
                if w > 2 {
                    let (g2, right, left) = (&mut g2[1..w - 1], &row[2..], &row[..w - 2]);
                    let (below, above) = (&below[1..w - 1], &above[1..w - 1]);
                    for x in 0..w - 2 {
                        add(&mut g2[x], right[x], left[x], below[x], above[x]);
                    }
                }
            }
            for g2 in g2.iter_mut() {
                *g2 = KF * KF * (*g2 / ch as f32).max(1e-3);
            }
        });
        Ok(Feature { img, norm })
    }
}

/// A per-channel box average of radius `r` of a variance image.
pub(crate) fn smooth_variance(var: &Image, r: usize) -> Result<Image> {
    let (w, h) = var.size();
    let mut out = Image::try_zeros(var.channels(), w, h)?;
    let mut tmp = Vec::new();
    for c in 0..var.channels() {
        let src = var.plane(c).to_slice().expect("contiguous");
        let dst = out.plane_mut(c).into_slice().expect("contiguous");
        box_mean(src, w, h, r, &mut tmp, dst)?;
    }
    Ok(out)
}

/// Box sum of radius `r` over rows then columns (reflect-101), divided by the area; `tmp`
/// is scratch (grown to `w * h`).
fn box_mean(
    src: &[f32],
    w: usize,
    h: usize,
    r: usize,
    tmp: &mut Vec<f32>,
    dst: &mut [f32],
) -> Result<()> {
    let area = ((2 * r + 1) * (2 * r + 1)) as f32;
    if tmp.len() < w * h {
        *tmp = try_vec(w * h, 0.0)?;
    }
    let tmp = &mut tmp[..w * h];
    tmp.par_chunks_mut(w)
        .enumerate()
        .for_each(|(y, row)| box_row(&src[y * w..(y + 1) * w], r, row));
    let tmp = &*tmp;
    // Row after row into the output row (from 0.0, in the order of `d`: the sums of a
    // pixel-by-pixel loop, which would not vectorise).
    dst.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        row.fill(0.0);
        for d in -(r as isize)..=r as isize {
            let src = &tmp[reflect(y as isize + d, h) * w..][..w];
            for (out, &v) in row.iter_mut().zip(src) {
                *out += v;
            }
        }
        for out in row.iter_mut() {
            *out /= area;
        }
    });
    Ok(())
}

/// The running box sums of radius `r` along one row `s` (reflect-101) into `out`.
fn box_row(s: &[f32], r: usize, out: &mut [f32]) {
    let w = s.len();
    let mut acc: f32 = (-(r as isize)..=r as isize).map(|d| s[reflect(d, w)]).sum();
    for (x, out) in out.iter_mut().enumerate() {
        *out = acc;
        acc += s[reflect(x as isize + r as isize + 1, w)] - s[reflect(x as isize - r as isize, w)];
    }
}

/// Side lengths (columns, rows) of the tiles [`filter`] works on: a tile's inputs
/// (with the window's margin) and accumulators stay in a core's L2 cache for all offsets.
/// Measured at 720p (RDFC, s): 128 x 32 1.31, 128 x 16 1.34, 64 x 16 1.48, 256 x 16 1.17,
/// 256 x 32 1.21, 512 x 16 1.22, 1280 x 8 1.48: longer rows amortise the per-row calls.
const TILE: (usize, usize) = (256, 16);

/// Window offsets weighed together (see [`weigh_rows`]): pairs, faster than single offsets;
/// groups of 4 were no faster than pairs.
const GROUP: usize = 2;
// The paired distance kernels (`colour_distance_pair`, `feature_distance_pair`) take two.
const _: () = assert!(
    GROUP == 2,
    "the distance kernels are written for pairs of offsets"
);

/// Colour distance row (Eq. 5-6 without the bandwidth), summed over the 3 channels:
/// `sum_c ((c_p - c_q)^2 - (v_p + min(v_p, v_q))) / (1e-10 + v_p + v_q)`.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn colour_distance_row(
    out: &mut [f32],
    [cp0, cp1, cp2]: [&[f32]; 3],
    [cq0, cq1, cq2]: [&[f32]; 3],
    [vp0, vp1, vp2]: [&[f32]; 3],
    [vq0, vq1, vq2]: [&[f32]; 3],
) {
    let n = out.len();
    let (cp0, cp1, cp2) = (&cp0[..n], &cp1[..n], &cp2[..n]);
    let (cq0, cq1, cq2) = (&cq0[..n], &cq1[..n], &cq2[..n]);
    let (vp0, vp1, vp2) = (&vp0[..n], &vp1[..n], &vp2[..n]);
    let (vq0, vq1, vq2) = (&vq0[..n], &vq1[..n], &vq2[..n]);
    const F: bool = fused!();
    let term = colour_term::<F>;
    for i in 0..n {
        let t0 = term(cp0[i], cq0[i], vp0[i], vq0[i]);
        let t1 = term(cp1[i], cq1[i], vp1[i], vq1[i]);
        let t2 = term(cp2[i], cq2[i], vp2[i], vq2[i]);
        out[i] = t0 + t1 + t2;
    }
}

/// The first `n` values of each of three rows. Written out: `[T; N]::map` in a kernel's
/// prologue is a call (with one more per element to the closure) that the multiversioned
/// copies do not inline, and the kernels run once a row and window offset.
#[inline(always)]
fn cut3(rows: [&[f32]; 3], n: usize) -> [&[f32]; 3] {
    let [a, b, c] = rows;
    [&a[..n], &b[..n], &c[..n]]
}

/// One channel's term of [`colour_distance_row`].
#[inline(always)]
fn colour_term<const F: bool>(a: f32, b: f32, va: f32, vb: f32) -> f32 {
    let diff = a - b;
    madd::<F>(diff, diff, -(va + min(va, vb))) / (1e-10 + va + vb)
}

/// A row of a colour image and of its variance (3 channels each).
type ColourRows<'a> = ([&'a [f32]; 3], [&'a [f32]; 3]);

/// [`colour_distance_row`] for the two offsets of a group at once (`own`: the row's colour and
/// variance, `other[s]`: offset `s`'s), the same values, the row's own pixels read once.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn colour_distance_pair(
    out0: &mut [f32],
    out1: &mut [f32],
    own: ColourRows,
    other: [ColourRows; 2],
) {
    const F: bool = fused!();
    let n = out0.len();
    let out1 = &mut out1[..n];
    let (cp, vp) = (cut3(own.0, n), cut3(own.1, n));
    let [o0, o1] = other;
    let (cq, vq) = (
        [cut3(o0.0, n), cut3(o1.0, n)],
        [cut3(o0.1, n), cut3(o1.1, n)],
    );
    for i in 0..n {
        let (c0, c1, c2) = (cp[0][i], cp[1][i], cp[2][i]);
        let (v0, v1, v2) = (vp[0][i], vp[1][i], vp[2][i]);
        let t0 = colour_term::<F>(c0, cq[0][0][i], v0, vq[0][0][i]);
        let t1 = colour_term::<F>(c1, cq[0][1][i], v1, vq[0][1][i]);
        let t2 = colour_term::<F>(c2, cq[0][2][i], v2, vq[0][2][i]);
        out0[i] = t0 + t1 + t2;
        let t0 = colour_term::<F>(c0, cq[1][0][i], v0, vq[1][0][i]);
        let t1 = colour_term::<F>(c1, cq[1][1][i], v1, vq[1][1][i]);
        let t2 = colour_term::<F>(c2, cq[1][2][i], v2, vq[1][2][i]);
        out1[i] = t0 + t1 + t2;
    }
}

/// `fd = max(fd, inv * sum_c (f_p - f_q)^2)` over a row, for a 3-channel feature (`inv`:
/// `1 / (3 k_f^2 D_p)`), `fd` read as 0 when `fresh` (the first feature: no zeroing pass). A NaN
/// distance leaves `fd` unchanged.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn feature_distance_row3(
    fd: &mut [f32],
    [p0, p1, p2]: [&[f32]; 3],
    [q0, q1, q2]: [&[f32]; 3],
    inv: &[f32],
    fresh: bool,
) {
    let n = fd.len();
    let (p0, p1, p2, q0, q1, q2) = (&p0[..n], &p1[..n], &p2[..n], &q0[..n], &q1[..n], &q2[..n]);
    let inv = &inv[..n];
    const F: bool = fused!();
    // Two loops rather than a closure: a closure is not inlined into the multiversioned
    // copies, which then do not vectorise.
    if fresh {
        for i in 0..n {
            let (p, q) = ([p0[i], p1[i], p2[i]], [q0[i], q1[i], q2[i]]);
            fd[i] = max(feature_term::<F>(p, q, inv[i]), 0.0);
        }
    } else {
        for i in 0..n {
            let (p, q) = ([p0[i], p1[i], p2[i]], [q0[i], q1[i], q2[i]]);
            fd[i] = max(feature_term::<F>(p, q, inv[i]), fd[i]);
        }
    }
}

/// `|p - q|^2 * inv` for one pixel of a 3-channel feature, as [`feature_distance_row3`] forms it.
#[inline(always)]
fn feature_term<const F: bool>(p: [f32; 3], q: [f32; 3], inv: f32) -> f32 {
    let (d0, d1, d2) = (p[0] - q[0], p[1] - q[1], p[2] - q[2]);
    madd::<F>(d2, d2, madd::<F>(d1, d1, d0 * d0)) * inv
}

/// [`feature_distance_row3`] for two 3-channel features (`p[f]`, `inv[f]`: the row's own
/// pixels and their `1 / (3 k_f^2 D_p)`) and the two offsets of a group at once (`q[s][f]`:
/// offset `s`'s neighbours): `fd_s = max(term_1, max(term_0, 0))`, the values of two calls
/// per offset, but the row's own pixels and normalisers read once for both offsets and each
/// distance written once instead of written, read and written again.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn feature_distance_pair(
    fd0: &mut [f32],
    fd1: &mut [f32],
    p: [[&[f32]; 3]; 2],
    q: [[[&[f32]; 3]; 2]; 2],
    inv: [&[f32]; 2],
) {
    const F: bool = fused!();
    let n = fd0.len();
    let fd1 = &mut fd1[..n];
    let p = [cut3(p[0], n), cut3(p[1], n)];
    let [[qa0, qb0], [qa1, qb1]] = q;
    let q = [[cut3(qa0, n), cut3(qb0, n)], [cut3(qa1, n), cut3(qb1, n)]];
    let inv = [&inv[0][..n], &inv[1][..n]];
    for i in 0..n {
        let pa = [p[0][0][i], p[0][1][i], p[0][2][i]];
        let pb = [p[1][0][i], p[1][1][i], p[1][2][i]];
        let (ia, ib) = (inv[0][i], inv[1][i]);
        let qa0 = [q[0][0][0][i], q[0][0][1][i], q[0][0][2][i]];
        let qb0 = [q[0][1][0][i], q[0][1][1][i], q[0][1][2][i]];
        let qa1 = [q[1][0][0][i], q[1][0][1][i], q[1][0][2][i]];
        let qb1 = [q[1][1][0][i], q[1][1][1][i], q[1][1][2][i]];
        let d0 = max(feature_term::<F>(pa, qa0, ia), 0.0);
        fd0[i] = max(feature_term::<F>(pb, qb0, ib), d0);
        let d1 = max(feature_term::<F>(pa, qa1, ia), 0.0);
        fd1[i] = max(feature_term::<F>(pb, qb1, ib), d1);
    }
}

/// The inputs of [`weigh_rows`]: a row of patch sums and its scale, the feature distance
/// `fd >= 0` and the neighbours' data (3 channels).
struct WeighInputs<'a> {
    patch: &'a [f32],
    scale: f32,
    fd: &'a [f32],
    data: [&'a [f32]; 3],
}

/// Weights of one candidate over a row for `P` window offsets, `w = exp(-max(scale * patch,
/// fd))` (`exp(-fd)` for a candidate without colour term, `COLOUR` false), accumulated offset after offset: `den += w`, `maxw = max(maxw, w)`, `num_c += w *
/// data_c` (the same sums in the same order as one offset at a time, with one read and write
/// of the accumulators instead of `P`). Each output is its own `&mut` argument: the compiler
/// then knows they do not overlap, and vectorises.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn weigh_rows<const P: usize, const COLOUR: bool>(
    inp: [&WeighInputs; P],
    den: &mut [f32],
    maxw: &mut [f32],
    n0: &mut [f32],
    n1: &mut [f32],
    n2: &mut [f32],
) {
    const F: bool = fused!();
    let n = den.len();
    let patch = inp.map(|o| &o.patch[..n]);
    let fd = inp.map(|o| &o.fd[..n]);
    let scale = inp.map(|o| o.scale);
    let d0 = inp.map(|o| &o.data[0][..n]);
    let d1 = inp.map(|o| &o.data[1][..n]);
    let d2 = inp.map(|o| &o.data[2][..n]);
    let maxw = &mut maxw[..n];
    let (n0, n1, n2) = (&mut n0[..n], &mut n1[..n], &mut n2[..n]);
    for i in 0..n {
        let (mut s, mut m) = (den[i], maxw[i]);
        let (mut a0, mut a1, mut a2) = (n0[i], n1[i], n2[i]);
        for o in 0..P {
            // Without a colour term (`COLOUR` false) the patch is 0 and `max(0, fd) = fd`
            // (`fd >= 0`, not NaN): the same weight without reading the patch row.
            let dist = if COLOUR {
                max(patch[o][i] * scale[o], fd[o][i])
            } else {
                fd[o][i]
            };
            let wgt = exp_nonpositive::<F>(-dist);
            s += wgt;
            m = max(m, wgt);
            a0 = madd::<F>(wgt, d0[o][i], a0);
            a1 = madd::<F>(wgt, d1[o][i], a1);
            a2 = madd::<F>(wgt, d2[o][i], a2);
        }
        (den[i], maxw[i]) = (s, m);
        (n0[i], n1[i], n2[i]) = (a0, a1, a2);
    }
}

/// Where index `j` of a padded row (or column) of a tile reads from: padded index `j` is image
/// coordinate `start + j - p` (`start` the tile's first, `p` the padding), reflected (reflect-101)
/// into `0..len` and given back as a padded index.
fn reflected(j: usize, start: usize, p: usize, len: usize) -> usize {
    reflect((j + start) as isize - p as isize, len) + p - start
}

/// The patch sums of one window offset's colour distances over a tile, per radius in `radii`
/// (their largest is `p`): `delta` holds the distances of `rows` image rows, each `dw` wide (the
/// tile's columns and `p` more either side, reflected past the image's borders); `hsum[j]`
/// gets the horizontal sums of radius `radii[j]` of those rows, placed from row `offy` of a
/// block of `th + 2p` rows whose others are then filled by reflection (`reflect_row(j)`: the
/// block row whose sums row `j` takes); `vsum[j]` gets the vertical sums of `hsum[j]` over the
/// tile's `th` rows. Every block has rows `dw` wide, and every sum runs over whole blocks at
/// once: a column near a row's ends mixes two rows, and only the tile's columns, `p ..
/// p + tw`, are read. With radii 1 and 3 (the release's) the radius-3 sums reuse radius-1
/// sums in both directions, `h_3(x) = h_1(x - 2) + d(x) + h_1(x + 2)`: three terms instead of
/// seven (a different rounding from seven in a row, within the tests' tolerance); `wsum` is
/// scratch of at least `(th + 4) dw`.
fn patch_sums(
    delta: &[f32],
    (dw, rows, offy, th): (usize, usize, usize, usize),
    radii: &[usize],
    reflect_row: impl Fn(usize) -> usize,
    hsum: &mut [Vec<f32>],
    vsum: &mut [Vec<f32>],
    wsum: &mut [f32],
) {
    let p = radii.last().copied().unwrap_or(0);
    let (n, at) = (rows * dw, offy * dw);
    let composite = radii == [1, 3];
    for (j, (hs, &r)) in hsum.iter_mut().zip(radii).enumerate() {
        if !(composite && j == 1) {
            add_rows(
                &mut hs[at + r..at + n - r],
                (0..=2 * r).map(|t| &delta[t..]),
            );
        }
    }
    if composite {
        // The radius-3 sums from the radius-1 ones.
        let (h1, h3) = hsum.split_at_mut(1);
        add_row_batch(
            &mut h3[0][at + 3..at + n - 3],
            &[&h1[0][at + 1..], &delta[3..], &h1[0][at + 5..]],
            true,
        );
    }
    for hs in hsum.iter_mut() {
        for j in (0..offy).chain(offy + rows..th + 2 * p) {
            let from = reflect_row(j);
            hs.copy_within(from * dw..(from + 1) * dw, j * dw);
        }
    }
    let tn = th * dw;
    for (j, ((v, hs), &r)) in vsum.iter_mut().zip(&*hsum).zip(radii).enumerate() {
        if composite && j == 1 {
            let w = &mut wsum[..tn + 4 * dw];
            add_rows(w, (0..3).map(|t| &hs[t * dw..]));
            add_rows(
                &mut v[..tn],
                [&w[..], &hs[3 * dw..], &w[4 * dw..]].into_iter(),
            );
        } else {
            add_rows(&mut v[..tn], (0..=2 * r).map(|t| &hs[(p - r + t) * dw..]));
        }
    }
}

/// `out = sum of the rows` (at least one, each at least `out.len()` long), added in order:
/// up to [`ROW_BATCH`] rows per pass over `out` (a 7 x 7 patch sum is one pass, not six).
fn add_rows<'a>(out: &mut [f32], rows: impl Iterator<Item = &'a [f32]>) {
    let mut batch: [&[f32]; ROW_BATCH] = [&[]; ROW_BATCH];
    let (mut len, mut first) = (0, true);
    for row in rows {
        batch[len] = row;
        len += 1;
        if len == ROW_BATCH {
            add_row_batch(out, &batch, first);
            (len, first) = (0, false);
        }
    }
    assert!(len > 0 || !first, "a row");
    if len > 0 {
        add_row_batch(out, &batch[..len], first);
    }
}

/// Rows summed per pass by [`add_rows`].
const ROW_BATCH: usize = 8;

/// `out = rows[0] + rows[1] + ...` (`init`) or `out += rows[0] + ...`, left to right, for 1 to
/// [`ROW_BATCH`] rows.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn add_row_batch(out: &mut [f32], rows: &[&[f32]], init: bool) {
    match rows.len() {
        1 => sum_into::<1>(out, rows, init),
        2 => sum_into::<2>(out, rows, init),
        3 => sum_into::<3>(out, rows, init),
        4 => sum_into::<4>(out, rows, init),
        5 => sum_into::<5>(out, rows, init),
        6 => sum_into::<6>(out, rows, init),
        7 => sum_into::<7>(out, rows, init),
        _ => sum_into::<8>(out, rows, init),
    }
}

/// [`add_row_batch`] for exactly `K` rows (unrolled, so the loop over `out` vectorises).
#[inline(always)]
fn sum_into<const K: usize>(out: &mut [f32], rows: &[&[f32]], init: bool) {
    let n = out.len();
    let rows: [&[f32]; K] = std::array::from_fn(|k| &rows[k][..n]);
    if init {
        for (i, o) in out.iter_mut().enumerate() {
            let mut acc = rows[0][i];
            for r in &rows[1..] {
                acc += r[i];
            }
            *o = acc;
        }
    } else {
        for (i, o) in out.iter_mut().enumerate() {
            let mut acc = *o;
            for r in &rows {
                acc += r[i];
            }
            *o = acc;
        }
    }
}

/// What both of RDFC's filters read (the candidates' and the selection's), padded once for
/// the wider window: the colour, its variance, and each feature with `1 / (channels k_f^2 D_p)`
/// per pixel.
struct Inputs {
    colour: PaddedRows,
    var: PaddedRows,
    features: Vec<(PaddedRows, Vec<f32>)>,
}

impl Inputs {
    /// The inputs of filters with windows of radius up to `pad`.
    fn new(colour: &Image, var: &Image, features: &[Feature], pad: usize) -> Result<Self> {
        assert!(
            colour.channels() == 3 && var.channels() == 3,
            "colour and variance have 3 channels"
        );
        Ok(Inputs {
            colour: PaddedRows::new(colour, pad)?,
            var: PaddedRows::new(var, pad)?,
            features: features
                .iter()
                .map(|f| {
                    let ch = f.img.channels() as f32;
                    let mut inv = try_zeroed_vec::<f32>(f.norm.len())?;
                    inv.par_iter_mut().zip(&f.norm).for_each(|(inv, &d)| {
                        *inv = 1.0 / (ch * d);
                    });
                    Ok((PaddedRows::new(f.img, pad)?, inv))
                })
                .collect::<Result<_>>()?,
        })
    }
}

/// What every tile of one [`filter`] call shares.
struct Nlm<'a> {
    inputs: &'a Inputs,
    data: &'a PaddedRows,
    radius: usize,
    candidates: &'a [Candidate],
    /// The distinct patch radii of the candidates with a colour term, and the largest.
    radii: Vec<usize>,
    patch: usize,
    /// Per candidate: the index in `radii` of its patch and the scale of its patch sum,
    /// `1 / (3 area k_c^2)` (`None`: colour term off).
    patch_scale: Vec<Option<(usize, f32)>>,
}

impl Nlm<'_> {
    /// `fd` = the largest feature distance over the features, for the `len` pixels of row `y`
    /// from column `x0` against their neighbours at `(ox, qy)`; 0 without features. `acc` is
    /// scratch of the same length (features with other than 3 channels).
    fn feature_distance(
        &self,
        fd: &mut [f32],
        acc: &mut [f32],
        (x0, len): (usize, usize),
        (y, qy): (usize, usize),
        ox: isize,
    ) {
        let w = self.inputs.colour.w;
        // `fd` starts at 0: zeroed here unless the first feature's pass writes it whole.
        let mut fresh = self
            .inputs
            .features
            .first()
            .is_some_and(|(f, _)| f.channels == 3);
        if !fresh {
            fd.fill(0.0);
        }
        for (f, inv) in &self.inputs.features {
            let inv = &inv[y * w + x0..y * w + x0 + len];
            if f.channels == 3 {
                let (fp, fq) = (f.rows3(y, x0, 0, len), f.rows3(qy, x0, ox, len));
                feature_distance_row3(fd, fp, fq, inv, fresh);
                fresh = false;
                continue;
            }
            acc.fill(0.0);
            for k in 0..f.channels {
                let fp = f.row(k, y, x0, 0, len);
                let fq = f.row(k, qy, x0, ox, len);
                for ((a, &u), &v) in acc.iter_mut().zip(fp).zip(fq) {
                    let diff = u - v;
                    *a += diff * diff;
                }
            }
            for ((d, &a), &iv) in fd.iter_mut().zip(&*acc).zip(inv) {
                *d = max(a * iv, *d);
            }
        }
    }

    /// Filters the tile of columns `x0..x1`, rows `y0..y1` into `dest`, the tile's parts of the
    /// output rows: per candidate `k`, its filtered data channels `c` then its centre weight
    /// ratio, plane `q = k (channels + 1) + c`, row `t` of the tile at `dest[q * rows + t]`.
    fn tile(
        &self,
        (x0, x1): (usize, usize),
        (y0, y1): (usize, usize),
        dest: &mut [&mut [f32]],
    ) -> Result<()> {
        let (w, h) = (self.inputs.colour.w, self.inputs.colour.h);
        let (tw, th) = (x1 - x0, y1 - y0);
        let tn = tw * th;
        let (m, dch) = (self.candidates.len(), self.data.channels);
        // The colour distance is needed `patch` pixels around the tile (clipped to the image:
        // the patch sums reflect at its borders, as the distance image is reflected).
        let p = self.patch;
        let (xs, xe, ys, ye) = (
            x0.saturating_sub(p),
            (x1 + p).min(w),
            y0.saturating_sub(p),
            (y1 + p).min(h),
        );
        let dw = xe - xs;
        // Distance rows span the tile's columns and `p` more either side (beyond the image's
        // borders reflected), so that every patch sum is a sum of shifted slices; column `xs`
        // sits at `off`.
        let (dwp, off) = (tw + 2 * p, p - (x0 - xs));
        let mut delta = [
            try_vec(dwp * (ye - ys), 0.0f32)?,
            try_vec(dwp * (ye - ys), 0.0f32)?,
        ];
        // Per slot (the offsets of a group): horizontal and vertical patch sums per radius,
        // and a row's feature distances.
        let per_radius = |len| -> Result<Vec<Vec<f32>>> {
            self.radii.iter().map(|_| try_vec(len, 0.0f32)).collect()
        };
        // The horizontal sums' rows span the tile's rows and `p` more either side (beyond the
        // image's borders reflected), so that the vertical sums are sums of shifted blocks,
        // the whole tile at once; row `ys` sits at `offy`.
        let (dhp, offy) = (th + 2 * p, p - (y0 - ys));
        let mut hsum: Vec<Vec<Vec<f32>>> = (0..GROUP)
            .map(|_| per_radius(dwp * dhp))
            .collect::<Result<_>>()?;
        let mut vsum: Vec<Vec<Vec<f32>>> = (0..GROUP)
            .map(|_| per_radius(dwp * th))
            .collect::<Result<_>>()?;
        let mut wsum = try_vec(dwp * (th + 4), 0.0f32)?;
        let mut fd = [0; GROUP].map(|_| vec![0.0f32; tw]);
        let zeros = vec![0.0f32; tw];
        let mut acc = vec![0.0f32; tw];
        let mut num = try_vec(m * dch * tn, 0.0f32)?;
        let mut den = try_vec(m * tn, 0.0f32)?;
        let mut maxw = try_vec(m * tn, 0.0f32)?;
        let r = self.radius as isize;
        let offsets: Vec<(isize, isize)> = (-r..=r)
            .flat_map(|oy| (-r..=r).map(move |ox| (ox, oy)))
            .filter(|&o| o != (0, 0))
            .collect();
        // Offsets go in groups of GROUP, in order (every sum adds them as one at a time
        // would): a group reads and writes the accumulators once.
        for group in offsets.chunks(GROUP) {
            if !self.radii.is_empty() {
                // Colour distance rows per offset (the mean over channels' 1/3 is applied
                // later), then their patch sums.
                for (row, py) in (ys..ye).enumerate() {
                    let own = (
                        self.inputs.colour.rows3(py, xs, 0, dw),
                        self.inputs.var.rows3(py, xs, 0, dw),
                    );
                    let other = |(ox, oy): (isize, isize)| {
                        let qy = reflect(py as isize + oy, h);
                        (
                            self.inputs.colour.rows3(qy, xs, ox, dw),
                            self.inputs.var.rows3(qy, xs, ox, dw),
                        )
                    };
                    let at = row * dwp + off..row * dwp + off + dw;
                    if let ([d0, d1], &[o0, o1]) = (&mut delta, group) {
                        let (q0, q1) = (other(o0), other(o1));
                        let (out0, out1) = (&mut d0[at.clone()], &mut d1[at]);
                        colour_distance_pair(out0, out1, own, [q0, q1]);
                    } else {
                        for (d, &o) in delta.iter_mut().zip(group) {
                            let q = other(o);
                            colour_distance_row(&mut d[at.clone()], own.0, q.0, own.1, q.1);
                        }
                    }
                    // The border columns, only where the tile meets the image's edge: there
                    // reflecting in the row's `dw` columns is reflecting in the image's (all
                    // of them when the tile spans the width, else more than `p`).
                    for d in delta.iter_mut().take(group.len()) {
                        reflect_borders(&mut d[row * dwp..(row + 1) * dwp], off, dw);
                    }
                }
                for ((delta, hsum), vsum) in
                    delta.iter().zip(&mut hsum).zip(&mut vsum).take(group.len())
                {
                    patch_sums(
                        delta,
                        (dwp, ye - ys, offy, th),
                        &self.radii,
                        |j| reflected(j, y0, p, h),
                        hsum,
                        vsum,
                        &mut wsum,
                    );
                }
            }
            for (t, y) in (y0..y1).enumerate() {
                // The neighbour row of each offset of the group.
                let qys: [usize; GROUP] = std::array::from_fn(|s| {
                    group
                        .get(s)
                        .map_or(0, |&(_, oy)| reflect(y as isize + oy, h))
                });
                match (&self.inputs.features[..], group) {
                    // Albedo and normal, a pair of offsets: both distances in one pass.
                    ([(fa, ia), (fb, ib)], &[(ox0, _), (ox1, _)])
                        if fa.channels == 3 && fb.channels == 3 =>
                    {
                        let [fd0, fd1] = &mut fd;
                        let at = y * w + x0;
                        feature_distance_pair(
                            fd0,
                            fd1,
                            [fa.rows3(y, x0, 0, tw), fb.rows3(y, x0, 0, tw)],
                            [(qys[0], ox0), (qys[1], ox1)]
                                .map(|(qy, ox)| [fa, fb].map(|f| f.rows3(qy, x0, ox, tw))),
                            [&ia[at..at + tw], &ib[at..at + tw]],
                        );
                    }
                    _ => {
                        for (slot, &(ox, _)) in group.iter().enumerate() {
                            let qy = qys[slot];
                            self.feature_distance(&mut fd[slot], &mut acc, (x0, tw), (y, qy), ox);
                        }
                    }
                }
                // The neighbours' data rows of each slot, shared by the candidates.
                let data: [[&[f32]; 3]; GROUP] = std::array::from_fn(|s| {
                    let ox = group.get(s).map_or(0, |&(ox, _)| ox);
                    self.data.rows3(qys[s], x0, ox, tw)
                });
                for (k, &patch_scale) in self.patch_scale.iter().enumerate() {
                    // dist = max(patch mean / k_c^2, d_f, 0), or max(d_f, 0) without colour
                    // term; d_f >= 0 (not NaN) already.
                    let inputs = |slot: usize| {
                        let (patch, scale) = match patch_scale {
                            Some((j, scale)) => (&vsum[slot][j][t * dwp + p..][..tw], scale),
                            None => (&zeros[..], 0.0),
                        };
                        WeighInputs {
                            patch,
                            scale,
                            fd: &fd[slot],
                            data: data[slot],
                        }
                    };
                    let at = k * tn + t * tw;
                    let mut planes = num[k * 3 * tn..(k + 1) * 3 * tn].chunks_exact_mut(tn);
                    let mut next = || &mut planes.next().expect("3 planes")[t * tw..][..tw];
                    let (n0, n1, n2) = (next(), next(), next());
                    let (den, maxw) = (&mut den[at..at + tw], &mut maxw[at..at + tw]);
                    let (one, two) = ([&inputs(0)], [&inputs(0), &inputs(1)]);
                    match (group.len(), patch_scale.is_some()) {
                        (1, true) => weigh_rows::<1, true>(one, den, maxw, n0, n1, n2),
                        (1, false) => weigh_rows::<1, false>(one, den, maxw, n0, n1, n2),
                        (_, true) => weigh_rows::<2, true>(two, den, maxw, n0, n1, n2),
                        (_, false) => weigh_rows::<2, false>(two, den, maxw, n0, n1, n2),
                    }
                }
            }
        }
        // The centre takes the largest neighbour weight (at least 1e-3).
        for k in 0..m {
            let plane = |c: usize| (k * (dch + 1) + c) * th;
            for (t, y) in (y0..y1).enumerate() {
                let at = k * tn + t * tw;
                let ratio = &mut dest[plane(dch) + t][..tw];
                for (i, ratio) in (at..at + tw).zip(ratio) {
                    let wc = maxw[i].max(1e-3);
                    let total = den[i] + wc;
                    *ratio = wc / total;
                    den[i] = total;
                    maxw[i] = wc;
                }
                for ch in 0..dch {
                    let dp = self.data.row(ch, y, x0, 0, tw);
                    let a = (k * dch + ch) * tn + t * tw;
                    let out = &mut dest[plane(ch) + t][..tw];
                    for ((out, i), &v) in out.iter_mut().zip(a..a + tw).zip(dp) {
                        let j = i - a + at;
                        *out = (num[i] + maxw[j] * v) / den[j];
                    }
                }
            }
        }
        Ok(())
    }
}

/// [`filter`] on images, padded for this one call (the form the tests compare and swap).
#[cfg(test)]
pub(crate) fn nlm_candidates(
    colour: &Image,
    var: &Image,
    features: &[Feature],
    data: &Image,
    radius: usize,
    candidates: &[Candidate],
    stop: &Progress,
) -> Result<Vec<(Image, Vec<f32>)>> {
    let inputs = Inputs::new(colour, var, features, radius)?;
    filter(&inputs, Some(data), radius, candidates, stop)
}

/// Joint NLM / bilateral filtering of `data` (`None`: the colour itself, as RDFC's first
/// filter) guided by the colour (with its per-channel variance) and the features of `inputs`
/// (padded by at least `radius`), for each candidate; returns per candidate the filtered data
/// and the centre weight ratio `w_centre / sum w` per pixel. Colour, variance and data have 3
/// channels. Once `stop` is cancelled the tiles not yet started are skipped (the result is
/// then incomplete; the caller checks `stop`).
///
/// Tiles (in parallel) loop over the window offsets, and per offset over their rows; a tile's
/// result depends on nothing but its pixels, so the output does not depend on the threads.
/// Each tile writes its part of the output rows (slices cut before the tiles start), not a
/// tile-sized result copied into place afterwards.
fn filter(
    inputs: &Inputs,
    data: Option<&Image>,
    radius: usize,
    candidates: &[Candidate],
    stop: &Progress,
) -> Result<Vec<(Image, Vec<f32>)>> {
    let (w, h) = (inputs.colour.w, inputs.colour.h);
    let n = w * h;
    let padded;
    let data = match data {
        Some(img) => {
            assert!(img.channels() == 3, "data has 3 channels");
            padded = PaddedRows::new(img, radius)?;
            &padded
        }
        None => &inputs.colour,
    };
    let dch = data.channels;
    let m = candidates.len();
    let mut out: Vec<(Image, Vec<f32>)> = (0..m)
        .map(|_| Ok((Image::try_zeros(dch, w, h)?, try_zeroed_vec(n)?)))
        .collect::<Result<_>>()?;
    if n == 0 {
        return Ok(out);
    }
    let mut radii: Vec<usize> = candidates
        .iter()
        .filter(|c| c.kc.is_some())
        .map(|c| c.patch)
        .collect();
    radii.sort_unstable();
    radii.dedup();
    let nlm = Nlm {
        inputs,
        data,
        radius,
        candidates,
        patch: radii.last().copied().unwrap_or(0),
        patch_scale: candidates
            .iter()
            .map(|c| {
                let j = radii.iter().position(|&q| q == c.patch);
                let area = ((2 * c.patch + 1) * (2 * c.patch + 1)) as f32;
                c.kc.map(|kc| (j.expect("radius listed"), 1.0 / (3.0 * area * kc * kc)))
            })
            .collect(),
        radii,
    };
    let tiles: Vec<((usize, usize), (usize, usize))> = (0..h)
        .step_by(TILE.1)
        .flat_map(|y0| {
            (0..w)
                .step_by(TILE.0)
                .map(move |x0| ((x0, (x0 + TILE.0).min(w)), (y0, (y0 + TILE.1).min(h))))
        })
        .collect();
    // Each tile's parts of the output rows, in the order `Nlm::tile` takes them: plane by
    // plane (a candidate's channels, then its ratio), row by row.
    let columns = w.div_ceil(TILE.0);
    let mut dest: Vec<Vec<&mut [f32]>> = tiles.iter().map(|_| Vec::new()).collect();
    for (img, ratio) in &mut out {
        let planes = img.as_mut_slice().chunks_exact_mut(n);
        for plane in planes.chain(std::iter::once(ratio.as_mut_slice())) {
            for (y, row) in plane.chunks_exact_mut(w).enumerate() {
                for (tx, part) in row.chunks_mut(TILE.0).enumerate() {
                    dest[y / TILE.1 * columns + tx].push(part);
                }
            }
        }
    }
    tiles
        .par_iter()
        .zip(dest)
        .try_for_each(|(&(xr, yr), mut dest)| {
            if stop.stopped() {
                Ok(())
            } else {
                nlm.tile(xr, yr, &mut dest)
            }
        })?;
    Ok(out)
}

/// The signature of the tests' `nlm_candidates` (they also run RDFC with a straightforward
/// version of it).
type NlmFn = fn(
    &Image,
    &Image,
    &[Feature],
    &Image,
    usize,
    &[Candidate],
    &Progress,
) -> Result<Vec<(Image, Vec<f32>)>>;

/// The window radius of the release's candidate filters: 21 x 21.
pub(crate) const RADIUS: usize = 10;

/// The window radius of the filter that smooths the candidates' selection: 7 x 7.
const SELECTION_RADIUS: usize = 3;

/// The RDFC pre-denoised guide of `colour` (variance of the mean `var`), its candidate
/// filters over windows of `radius` ([`RADIUS`] in the release); incomplete when `stop` is
/// cancelled (the caller checks it).
pub(crate) fn rdfc(
    colour: &Image,
    var: &Image,
    albedo: Option<&Image>,
    normal: Option<&Image>,
    radius: usize,
    stop: &Progress,
) -> Result<Image> {
    rdfc_with(colour, var, albedo, normal, radius, None, stop)
}

fn rdfc_with(
    colour: &Image,
    var: &Image,
    albedo: Option<&Image>,
    normal: Option<&Image>,
    radius: usize,
    reference: Option<NlmFn>,
    stop: &Progress,
) -> Result<Image> {
    let (w, h) = colour.size();
    let n = w * h;
    if n == 0 {
        return colour.try_clone(); // the row passes below chunk by the width
    }
    let features: Vec<Feature> = albedo
        .into_iter()
        .chain(normal)
        .map(Feature::new)
        .collect::<Result<_>>()?;
    // Both filters read the colour, variance and features padded once (the selection's
    // window is the narrower); a reference implementation (tests) takes the images instead.
    enum Filters {
        Own(Inputs),
        Reference(NlmFn),
    }
    let filters = match reference {
        None => {
            let pad = radius.max(SELECTION_RADIUS);
            Filters::Own(Inputs::new(colour, var, &features, pad)?)
        }
        Some(reference) => Filters::Reference(reference),
    };
    let nlm = |data: Option<&Image>, radius: usize, candidates: &[Candidate]| match &filters {
        Filters::Own(inputs) => filter(inputs, data, radius, candidates, stop),
        Filters::Reference(reference) => {
            let data = data.unwrap_or(colour);
            reference(colour, var, &features, data, radius, candidates, stop)
        }
    };
    let filtered = nlm(None, radius, &CANDIDATES)?;
    if stop.stopped() {
        return colour.try_clone();
    }
    // SURE per candidate, smoothed by a 3 x 3 box.
    let (c, v) = (colour.as_slice(), var.as_slice());
    let (mut raw, mut tmp) = (try_zeroed_vec::<f32>(n)?, Vec::new());
    let sure: Vec<Vec<f32>> = filtered
        .iter()
        .map(|(f, ratio)| {
            let fs = f.as_slice();
            raw.par_chunks_mut(w).enumerate().for_each(|(y, raw)| {
                let row = y * w..(y + 1) * w;
                let ratio = &ratio[row.clone()];
                // From -0.0 (as `Iterator::sum`), the channels in order.
                raw.fill(-0.0);
                for ch in 0..3 {
                    let plane = ch * n + row.start..ch * n + row.end;
                    let (fs, c, v) = (&fs[plane.clone()], &c[plane.clone()], &v[plane]);
                    for (x, raw) in raw.iter_mut().enumerate() {
                        let (e, vv) = (fs[x] - c[x], v[x]);
                        *raw += e * e - vv + 2.0 * vv * ratio[x];
                    }
                }
            });
            let mut smooth = try_vec(n, 0.0)?;
            box_mean(&raw, w, h, 1, &mut tmp, &mut smooth)?;
            Ok(smooth)
        })
        .collect::<Result<_>>()?;
    let m = filtered.len();
    // Per pixel the candidate of least SURE (the first of equals, as `min_by`), one-hot.
    const _: () = assert!(CANDIDATES.len() <= 256, "candidate indices are u8");
    let mut best = try_zeroed_vec::<u8>(n)?;
    best.par_chunks_mut(w).enumerate().for_each(|(y, best)| {
        let row = y * w..(y + 1) * w;
        for (k, sk) in sure.iter().enumerate().skip(1) {
            for (b, (x, &e)) in best.iter_mut().zip(sk[row.clone()].iter().enumerate()) {
                if e.total_cmp(&sure[usize::from(*b)][row.start + x]).is_lt() {
                    *b = k as u8;
                }
            }
        }
    });
    let onehot = Image::try_par_from_rows(m, w, h, |k, y, row| {
        for (v, &b) in row.iter_mut().zip(&best[y * w..(y + 1) * w]) {
            *v = f32::from(u8::from(usize::from(b) == k));
        }
    })?;
    let sel = nlm(
        Some(&onehot),
        SELECTION_RADIUS,
        &[Candidate {
            patch: 1,
            kc: Some(0.5),
        }],
    )?
    .remove(0)
    .0;
    let s = sel.as_slice();
    Image::try_par_from_rows(3, w, h, |ch, y, out| {
        let (row, plane) = (y * w, ch * n + y * w);
        // `out` (zeros) and `tot` accumulate, candidate by candidate as before.
        let mut tot = vec![0.0f32; w];
        for (k, (f, _)) in filtered.iter().enumerate() {
            let (sk, fk) = (&s[k * n + row..][..w], &f.as_slice()[plane..][..w]);
            for ((acc, t), (&a, &b)) in out.iter_mut().zip(&mut tot).zip(sk.iter().zip(fk)) {
                *acc += a * b;
                *t += a;
            }
        }
        for ((o, &t), &c) in out.iter_mut().zip(&tot).zip(&c[plane..][..w]) {
            *o = if t > 0.0 { *o / t } else { c };
        }
    })
}

#[cfg(test)]
mod tests;
