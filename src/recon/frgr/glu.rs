//! Guided linear upsampling (GLU, Song et al. 2023) for 2x levels, as the FRGR release uses it.
//!
//! Downsampling starts from the 2 x 2 box average of the guide `J` (the pre-denoised colour
//! plus 0.1 x albedo and 0.1 x normal: 9 channels, 3 without features). Every fine pixel is then
//! fitted as `w J_c[a] + (1 - w) J_c[b]` with the best pair `(a, b)` among the 3 x 3 coarse
//! neighbours of its parent (36 pairs, `w` in [0, 1], least squares over the channels). Blocks
//! holding a pixel whose fit error exceeds 0.15 (raw HDR units) are point-sampled instead: the
//! coarse value becomes that block's highest-error fine pixel. (The release groups such pixels
//! into 8-connected clusters first; the blocks they touch are the same.) All pixels are then
//! refitted once.
//!
//! Every other buffer is downsampled the same way (box: mean, variance of the mean / 16; point:
//! the chosen pixel), and gradients as the mean, over the pairs of source and target samples,
//! of the fine differences summed along a path between them, so exact gradients stay exact.
//! Upsampling is `w D[a] + (1 - w) D[b]`, a variance `w^2 V[a] + (1 - w)^2 V[b]`.
//!
//! Sizes must be even: [`pad_even`] extends by reflect-101 and the caller crops afterwards.
//!
//! The fit, the stage's cost, runs 8 consecutive fine pixels of a row at once, one per f64
//! lane ([`best_pairs`], compiled for AVX-512 and AVX2 as well; the best pair kept by selects,
//! so that its loop is a vector loop), with the per-pixel arithmetic unchanged: the same fits
//! bit for bit (tested against the per-pixel version). Resampling runs over rows, and the
//! gradients between two box blocks in vector kernels ([`box_edges_x`], [`box_edges_y`]) that
//! sum the same paths in the same order as the generic code (tested bit for bit as well).

use std::borrow::Cow;

use rayon::prelude::*;

use super::util::reflect;
use crate::error::Result;
use crate::image::{try_vec, try_zeroed_vec, Image};
use crate::progress::Progress;

/// Fit error beyond which a block is point-sampled.
const ERROR_THRESHOLD: f32 = 0.15;

/// How each coarse pixel was made: the mean of its 2 x 2 block or one fine pixel of it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Sample {
    Box,
    /// Offset `(i, j)` of the chosen fine pixel inside the block.
    Point(u8, u8),
}

/// The result of fitting a fine level to a coarse one.
pub(crate) struct Glu {
    /// Fine size.
    pub fine: (usize, usize),
    /// Coarse size (half).
    pub coarse: (usize, usize),
    /// Per coarse pixel, how it was sampled.
    pub samples: Vec<Sample>,
    /// Per fine pixel: coarse indices `a`, `b` and weight `w` of `a`.
    pub fit: Vec<(u32, u32, f32)>,
}

/// Pads to even width and height by reflect-101; even sizes are borrowed as they are (no copy).
pub(crate) fn pad_even(img: &Image) -> Result<Cow<'_, Image>> {
    let (w, h) = img.size();
    let (pw, ph) = (w + w % 2, h + h % 2);
    if (pw, ph) == (w, h) {
        return Ok(Cow::Borrowed(img));
    }
    Image::try_par_from_fn(img.channels(), pw, ph, |(c, x, y)| {
        img.at(c, reflect(x as isize, w), reflect(y as isize, h))
    })
    .map(Cow::Owned)
}

/// Crops to `w` x `h` (the top-left corner); an image of that size is returned as it is.
pub(crate) fn crop(img: Image, w: usize, h: usize) -> Result<Image> {
    if img.size() == (w, h) {
        return Ok(img);
    }
    Image::try_par_from_fn(img.channels(), w, h, |(c, x, y)| img.at(c, x, y))
}

impl Glu {
    /// Fits the 2x level structure to the guide `j` (even size).
    #[cfg(test)]
    pub fn new(j: &Image) -> Self {
        Self::new_or_stop(j, &Progress::none()).expect("allocated")
    }

    /// The fit to the guide `j` (even size); an unusable fit, returned early, once `stop` is
    /// cancelled (the caller checks `stop`).
    pub fn new_or_stop(j: &Image, stop: &Progress) -> Result<Self> {
        let (w, h) = j.size();
        assert!(
            w % 2 == 0 && h % 2 == 0,
            "GLU needs even sizes, got {w} x {h}"
        );
        let (cw, ch) = (w / 2, h / 2);
        let mut glu = Glu {
            fine: (w, h),
            coarse: (cw, ch),
            samples: try_vec(cw * ch, Sample::Box)?,
            fit: Vec::new(),
        };
        let coarse = glu.downsample(j, false)?;
        let errors = glu.refit(j, &coarse, None)?;
        if stop.stopped() {
            return Ok(glu);
        }
        let mut changed = try_vec(cw * ch, false)?;
        glu.samples
            .par_chunks_mut(cw)
            .zip(changed.par_chunks_mut(cw))
            .enumerate()
            .for_each(|(by, (samples, changed))| {
                for (bx, (sample, changed)) in samples.iter_mut().zip(changed).enumerate() {
                    let mut worst = (ERROR_THRESHOLD, None);
                    for jj in 0..2 {
                        for ii in 0..2 {
                            let e = errors[(2 * by + jj) * w + 2 * bx + ii];
                            if e > worst.0 {
                                worst = (e, Some((ii as u8, jj as u8)));
                            }
                        }
                    }
                    if let (_, Some((ii, jj))) = worst {
                        (*sample, *changed) = (Sample::Point(ii, jj), true);
                    }
                }
            });
        if changed.contains(&true) {
            // Only the fine pixels with a point-sampled block among their 9 candidates can fit
            // differently: the box blocks' values did not change.
            let coarse = glu.downsample(j, false)?;
            glu.refit(j, &coarse, Some(&changed))?;
        }
        Ok(glu)
    }

    /// The 9 coarse candidates of fine pixel `(x, y)`: the 3 x 3 neighbours of its parent
    /// (reflect-101), row by row; the per-pixel form of what [`Glu::refit`] builds per row.
    #[cfg(test)]
    fn candidates(&self, x: usize, y: usize) -> [usize; 9] {
        let (rows, columns) = (self.candidate_rows(y), self.candidate_columns(x));
        std::array::from_fn(|k| rows[k / 3] + columns[k % 3])
    }

    /// The offsets (`row * coarse width`) of the candidates' coarse rows for fine row `y`.
    fn candidate_rows(&self, y: usize) -> [usize; 3] {
        let (cw, ch) = self.coarse;
        std::array::from_fn(|d| reflect((y / 2 + d) as isize - 1, ch) * cw)
    }

    /// The candidates' coarse columns for fine column `x`.
    fn candidate_columns(&self, x: usize) -> [usize; 3] {
        std::array::from_fn(|d| reflect((x / 2 + d) as isize - 1, self.coarse.0))
    }

    /// Fits the fine pixels to the coarse guide (all of them, or those with a candidate in
    /// `only`, the others keeping their fit); returns the fit errors (0 where not refitted).
    fn refit(&mut self, j: &Image, coarse: &Image, only: Option<&[bool]>) -> Result<Vec<f32>> {
        let (w, h) = self.fine;
        let (cw, ch) = self.coarse;
        let nc = j.channels();
        let (fs, cs) = (j.as_slice(), coarse.as_slice());
        let (n, cn) = (w * h, cw * ch);
        let mut errors = try_zeroed_vec::<f32>(n)?;
        let mut fit = std::mem::take(&mut self.fit);
        if fit.len() != n {
            fit = try_vec(n, (0, 0, 0.0))?;
        }
        let glu = &*self;
        fit.par_chunks_mut(w)
            .zip(errors.par_chunks_mut(w))
            .enumerate()
            .for_each(|(y, (fit, errors))| {
                // Scratch for the row (every entry read is written first for each lane group).
                let mut u = [[[0.0f64; LANES]; 9]; 9];
                let mut g = [[[0.0f64; LANES]; 9]; 9];
                let rows = glu.candidate_rows(y);
                for x0 in (0..w).step_by(LANES) {
                    // Lanes past the row's end repeat its last pixel and are not written.
                    let cand: [[usize; 9]; LANES] = std::array::from_fn(|l| {
                        let columns = glu.candidate_columns((x0 + l).min(w - 1));
                        std::array::from_fn(|k| rows[k / 3] + columns[k % 3])
                    });
                    let todo: [bool; LANES] = std::array::from_fn(|l| {
                        x0 + l < w && only.is_none_or(|o| cand[l].iter().any(|&q| o[q]))
                    });
                    if !todo.contains(&true) {
                        continue;
                    }
                    // u_k = t - J[cand k], lane-innermost (the targets `t` read once).
                    let mut t = [[0.0f64; LANES]; 9];
                    for (c, tc) in t[..nc].iter_mut().enumerate() {
                        for (l, v) in tc.iter_mut().enumerate() {
                            *v = f64::from(fs[c * n + y * w + (x0 + l).min(w - 1)]);
                        }
                    }
                    let inner = x0 >= 2 && x0 / 2 + LANES / 2 < cw;
                    differences(&mut u, &t, (cs, cn), &cand, nc, inner);
                    let (pairs, wgt, err) = best_pairs(&u, nc, &mut g);
                    for l in (0..LANES).filter(|&l| todo[l]) {
                        let [ia, ib] = pairs[l].map(|k| cand[l][usize::from(k)] as u32);
                        (fit[x0 + l], errors[x0 + l]) = ((ia, ib, wgt[l]), err[l].sqrt() as f32);
                    }
                }
            });
        self.fit = fit;
        Ok(errors)
    }

    /// Downsamples a buffer (any channel count, fine size): block mean or chosen pixel; a
    /// variance (`variance = true`) of a box block is the variance of the mean, sum / 16.
    pub fn downsample(&self, img: &Image, variance: bool) -> Result<Image> {
        let (cw, ch) = self.coarse;
        let (w, h) = self.fine;
        assert_eq!(img.size(), self.fine, "GLU downsamples its fine size");
        let fs = img.as_slice();
        Image::try_par_from_rows(img.channels(), cw, ch, |c, y, row| {
            // The block's two fine rows.
            let rows = [c * w * h + 2 * y * w, c * w * h + (2 * y + 1) * w];
            let samples = &self.samples[y * cw..(y + 1) * cw];
            for (x, (v, sample)) in row.iter_mut().zip(samples).enumerate() {
                *v = match *sample {
                    Sample::Box => {
                        let s = fs[rows[0] + 2 * x]
                            + fs[rows[0] + 2 * x + 1]
                            + fs[rows[1] + 2 * x]
                            + fs[rows[1] + 2 * x + 1];
                        if variance {
                            s / 16.0
                        } else {
                            s / 4.0
                        }
                    }
                    Sample::Point(i, j) => fs[rows[usize::from(j)] + 2 * x + usize::from(i)],
                };
            }
        })
    }

    /// The fine pixels a coarse pixel stands for (the first `len` of the array).
    fn members(&self, x: usize, y: usize) -> ([(usize, usize); 4], usize) {
        let (fx, fy) = (2 * x, 2 * y);
        match self.samples[y * self.coarse.0 + x] {
            Sample::Box => ([(fx, fy), (fx + 1, fy), (fx, fy + 1), (fx + 1, fy + 1)], 4),
            Sample::Point(i, j) => ([(fx + i as usize, fy + j as usize); 4], 1),
        }
    }

    /// Downsamples gradients: each coarse difference is the mean, over source and target
    /// samples, of the fine differences summed along a path (horizontal, then vertical).
    pub fn downsample_gradients(&self, dx: &Image, dy: &Image) -> Result<(Image, Image)> {
        let (cw, ch) = self.coarse;
        let (w, h) = self.fine;
        assert!(
            dx.size() == self.fine && dy.size() == self.fine,
            "GLU downsamples gradients of its fine size"
        );
        let (dxs, dys, n) = (dx.as_slice(), dy.as_slice(), w * h);
        // The path from `s` to `t` in the channel plane at offset `o`: along `s`'s row, then
        // `t`'s column (sums in that order, which the tests' oracle repeats).
        let path = |o: usize, (sx, sy): (usize, usize), (tx, ty): (usize, usize)| -> f32 {
            let mut s = 0.0;
            let row = o + sy * w;
            let sign = if tx >= sx { 1.0 } else { -1.0 };
            for v in &dxs[row + sx.min(tx)..row + sx.max(tx)] {
                s += sign * v;
            }
            let sign = if ty >= sy { 1.0 } else { -1.0 };
            for y in sy.min(ty)..sy.max(ty) {
                s += sign * dys[o + y * w + tx];
            }
            s
        };
        let edge = |o: usize, a: (usize, usize), b: (usize, usize)| -> f32 {
            let ((ma, la), (mb, lb)) = (self.members(a.0, a.1), self.members(b.0, b.1));
            let mut s = 0.0;
            for &p in &ma[..la] {
                for &q in &mb[..lb] {
                    s += path(o, p, q);
                }
            }
            s / (la * lb) as f32
        };
        // The last column of `cdx` and the last row of `cdy` stay 0. Edges between two box
        // blocks (nearly all) first, over whole rows; edges with a point-sampled end again.
        let point = |x: usize, y: usize| self.samples[y * cw + x] != Sample::Box;
        let cdx = Image::try_par_from_rows(3, cw, ch, |c, y, row| {
            let (o, fy) = (c * n, 2 * y);
            let split = |s: &[f32], r: usize| Split::new(&s[o + r * w..][..w]);
            let dx = [fy, fy + 1].map(|r| split(dxs, r));
            box_edges_x(dx.each_ref(), &split(dys, fy), &mut row[..cw - 1]);
            for x in (0..cw - 1).filter(|&x| point(x, y) || point(x + 1, y)) {
                row[x] = edge(o, (x, y), (x + 1, y));
            }
        })?;
        let cdy = Image::try_par_from_rows(3, cw, ch, |c, y, row| {
            if y + 1 < ch {
                let (o, fy) = (c * n, 2 * y);
                let split = |s: &[f32], r: usize| Split::new(&s[o + r * w..][..w]);
                let dx = [fy, fy + 1].map(|r| split(dxs, r));
                let dy = [fy, fy + 1, fy + 2, fy + 3].map(|r| split(dys, r));
                box_edges_y(dx.each_ref(), dy.each_ref(), row);
                for x in (0..cw).filter(|&x| point(x, y) || point(x, y + 1)) {
                    row[x] = edge(o, (x, y), (x, y + 1));
                }
            }
        })?;
        Ok((cdx, cdy))
    }

    /// Upsamples a coarse image (and optionally its variance) with the fitted weights.
    pub fn upsample(
        &self,
        img: &Image,
        variance: Option<&Image>,
    ) -> Result<(Image, Option<Image>)> {
        let (w, h) = self.fine;
        let (cw, ch) = self.coarse;
        let cn = cw * ch;
        let s = img.as_slice();
        let up = Image::try_par_from_rows(img.channels(), w, h, |c, y, row| {
            let cs = &s[c * cn..(c + 1) * cn];
            for (v, &(a, b, wt)) in row.iter_mut().zip(&self.fit[y * w..(y + 1) * w]) {
                *v = wt * cs[a as usize] + (1.0 - wt) * cs[b as usize];
            }
        })?;
        let var = variance
            .map(|v| {
                let vs = v.as_slice();
                Image::try_par_from_rows(v.channels(), w, h, |c, y, row| {
                    let cs = &vs[c * cn..(c + 1) * cn];
                    for (v, &(a, b, wt)) in row.iter_mut().zip(&self.fit[y * w..(y + 1) * w]) {
                        *v = wt * wt * cs[a as usize] + (1.0 - wt) * (1.0 - wt) * cs[b as usize];
                    }
                })
            })
            .transpose()?;
        Ok((up, var))
    }
}

/// A fine row split into its even and odd columns (the left and right columns of the blocks),
/// so that the box-edge kernels read consecutive values.
struct Split {
    even: Vec<f32>,
    odd: Vec<f32>,
}

impl Split {
    fn new(row: &[f32]) -> Self {
        let (even, odd) = row.chunks_exact(2).map(|p| (p[0], p[1])).unzip();
        Split { even, odd }
    }
}

/// Calls `$f::<a, b, c, d>` for every member pair of two box blocks, source member `(a, b)`
/// outer and target member `(c, d)` inner, each in [`Glu::members`]' order (that of the sums).
macro_rules! each_box_pair {
    ($f:ident, $args:tt) => {
        each_box_pair!(@source $f, $args, (0, 0), (1, 0), (0, 1), (1, 1))
    };
    (@source $f:ident, $args:tt, $(($a:literal, $b:literal)),*) => {
        $(each_box_pair!(@target $f, $args, $a, $b, (0, 0), (1, 0), (0, 1), (1, 1));)*
    };
    (@target $f:ident, $args:tt, $a:literal, $b:literal, $(($c:literal, $d:literal)),*) => {
        $($f::<$a, $b, $c, $d> $args;)*
    };
}

/// [`Glu::downsample_gradients`]' horizontal edges of one coarse row, every block a box:
/// `out[x]` from block `x` to block `x + 1`, given the block row's two fine rows of `dx` and
/// the first of `dy`. The same sums in the same order as the generic edge: per member pair
/// (one pass over the row each, so that the pixels are the vector lanes), along the source's
/// row, then down or up the target's column; then the mean.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn box_edges_x(dx: [&Split; 2], dy: &Split, out: &mut [f32]) {
    let m = out.len() + 1;
    let dx = dx.map(|r| [&r.even[..m], &r.odd[..m]]);
    let dy = [&dy.even[..m], &dy.odd[..m]];
    out.fill(0.0);
    each_box_pair!(box_path_x, (dx, dy, out));
    out.iter_mut().for_each(|v| *v /= 16.0);
}

/// One member pair's paths for [`box_edges_x`]: from `(2x + A, B)` to `(2x + 2 + C, D)`.
#[inline(always)]
fn box_path_x<const A: usize, const B: usize, const C: usize, const D: usize>(
    dx: [[&[f32]; 2]; 2],
    dy: [&[f32]; 2],
    out: &mut [f32],
) {
    let [e, o] = dx[B];
    for (x, v) in out.iter_mut().enumerate() {
        // Fine columns 2x .. 2x + 3: block x, then block x + 1.
        let h = [e[x], o[x], e[x + 1], o[x + 1]];
        let mut s = 0.0f32;
        for &u in &h[A..2 + C] {
            s += u;
        }
        let t = dy[C][x + 1];
        if D > B {
            s += t;
        } else if D < B {
            s += -t;
        }
        *v += s;
    }
}

/// [`box_edges_x`] for vertical edges: `out[x]` from block `(x, y)` to block `(x, y + 1)`,
/// given the two fine rows of `dx` of the upper block and the four of `dy` of both.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn box_edges_y(dx: [&Split; 2], dy: [&Split; 4], out: &mut [f32]) {
    let m = out.len();
    let dx = dx.map(|r| &r.even[..m]);
    let dy = dy.map(|r| [&r.even[..m], &r.odd[..m]]);
    out.fill(0.0);
    each_box_pair!(box_path_y, (dx, dy, out));
    out.iter_mut().for_each(|v| *v /= 16.0);
}

/// One member pair's paths for [`box_edges_y`]: from `(2x + A, B)` to `(2x + C, 2 + D)`.
#[inline(always)]
fn box_path_y<const A: usize, const B: usize, const C: usize, const D: usize>(
    dx: [&[f32]; 2],
    dy: [[&[f32]; 2]; 4],
    out: &mut [f32],
) {
    for (x, v) in out.iter_mut().enumerate() {
        let mut s = 0.0f32;
        let h = dx[B][x];
        if C > A {
            s += h;
        } else if C < A {
            s += -h;
        }
        for r in &dy[B..2 + D] {
            s += r[C][x];
        }
        *v += s;
    }
}

/// Fine pixels fitted together, one per lane (f64: one AVX-512 register, two AVX2 ones).
const LANES: usize = 8;

/// `u[k][c][l] = t[c][l] - J_c[cand[l][k]]` for the first `nc` channels, `J` the coarse guide
/// (`coarse`: its values and plane size). With `inner` (the lanes away from the coarse image's
/// sides, no reflection), lanes 2i and 2i + 1 share a parent: candidate k of lane l is
/// `cand[0][k] + l / 2`, the same values read as 4 consecutive ones. Compiled for AVX-512 and
/// AVX2 as well (the refit's closure itself is compiled for the baseline CPU).
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn differences(
    u: &mut [[[f64; LANES]; 9]; 9],
    t: &[[f64; LANES]; 9],
    (cs, cn): (&[f32], usize),
    cand: &[[usize; 9]; LANES],
    nc: usize,
    inner: bool,
) {
    for (k, uk) in u.iter_mut().enumerate() {
        for ((c, uc), tc) in uk[..nc].iter_mut().enumerate().zip(t) {
            if inner {
                let near = &cs[c * cn + cand[0][k]..][..LANES / 2];
                for (l, v) in uc.iter_mut().enumerate() {
                    *v = tc[l] - f64::from(near[l / 2]);
                }
            } else {
                for (l, v) in uc.iter_mut().enumerate() {
                    *v = tc[l] - f64::from(cs[c * cn + cand[l][k]]);
                }
            }
        }
    }
}

/// The best of the 36 pairs for each lane, from its differences `u[k][c][l] = t_c - J_c[cand
/// k]` (the first `nc` channels): per lane the pair `(a, b)` as indices into the 9 candidates,
/// the weight `w` of `a` and the squared error. With the Gram matrix `g` of the `u_k` (45 dot
/// products instead of 45 x 2 passes over the channels): `num = u_b . (u_b - u_a)`, `den = |u_b
/// - u_a|^2`, `err = |u_b|^2 - 2 w num + w^2 den`, in f64, since `den` and `err` are differences
/// of nearly equal dot products (`g`: scratch, its upper triangle written here); the first pair
/// with the smallest error wins. Every lane does
/// the scalar operations in the scalar order (the oracle in the tests: bit for bit); compiled
/// for AVX-512 and AVX2 as well, picked at run time.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn best_pairs(
    u: &[[[f64; LANES]; 9]; 9],
    nc: usize,
    g: &mut [[[f64; LANES]; 9]; 9],
) -> ([[u8; 2]; LANES], [f32; LANES], [f64; LANES]) {
    for ka in 0..9 {
        for kb in ka..9 {
            // From -0.0, as `Iterator::sum`.
            let mut d = [-0.0f64; LANES];
            for (ua, ub) in u[ka][..nc].iter().zip(&u[kb][..nc]) {
                for l in 0..LANES {
                    d[l] += ua[l] * ub[l];
                }
            }
            g[ka][kb] = d;
        }
    }
    // Per lane the best pair as `9 a + b`, its weight and error, kept by selects rather than
    // branches (all f64, so that the lane loops are vector loops).
    let mut code = [(4 * 9 + 4) as f64; LANES];
    let mut best_w = [1.0f64; LANES];
    let mut best = [f64::INFINITY; LANES];
    for ia in 0..9 {
        for ib in ia..9 {
            let (gaa, gbb, gab) = (&g[ia][ia], &g[ib][ib], &g[ia][ib]);
            let (mut wgt, mut err) = ([0.0f64; LANES], [0.0f64; LANES]);
            for l in 0..LANES {
                let num = gbb[l] - gab[l];
                let den = gaa[l] + gbb[l] - 2.0 * gab[l];
                let ratio = num / den;
                // `ratio.clamp(0.0, 1.0)`, spelt out.
                let clamped = if ratio < 0.0 { 0.0 } else { ratio };
                let clamped = if clamped > 1.0 { 1.0 } else { clamped };
                let w = if den > 0.0 { clamped } else { 1.0 };
                let e = gbb[l] - 2.0 * w * num + w * w * den;
                // `e.max(0.0)`, spelt out (0 for a negative or NaN `e`).
                (wgt[l], err[l]) = (w, if e >= 0.0 { e } else { 0.0 });
            }
            let pair = (9 * ia + ib) as f64;
            for l in 0..LANES {
                let better = err[l] < best[l];
                code[l] = if better { pair } else { code[l] };
                best_w[l] = if better { wgt[l] } else { best_w[l] };
                best[l] = if better { err[l] } else { best[l] };
            }
        }
    }
    let pairs = code.map(|c| {
        let c = c as u8;
        [c / 9, c % 9]
    });
    (pairs, best_w.map(|w| w as f32), best)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn piecewise_constant_guide_is_reconstructed_exactly() {
        // A guide that is constant on every 2 x 2 block: downsampling loses nothing and each
        // fine pixel is fitted by its own parent with weight 1.
        let (w, h) = (12, 8);
        let j = Image::from_fn(9, w, h, |(c, x, y)| {
            ((x / 2) * 7 + (y / 2) * 3 + c) as f32 * 0.1
        });
        let glu = Glu::new(&j);
        assert!(glu.samples.iter().all(|s| *s == Sample::Box));
        let coarse = glu.downsample(&j, false).unwrap();
        let (up, _) = glu.upsample(&coarse, None).unwrap();
        let d = up.max_abs_diff(&j);
        assert!(d < 1e-5, "{d}");
    }

    #[test]
    fn exact_gradients_downsample_to_the_exact_gradients_of_the_downsampled_image() {
        let (w, h) = (10, 8);
        let img = Image::from_fn(3, w, h, |(c, x, y)| {
            ((x * x + 3 * y + c) % 11) as f32 * 0.3 + if x > 5 { 2.0 } else { 0.0 }
        });
        let mut guide = img.clone();
        // Make a few blocks point-sampled: huge values in single pixels.
        guide.planes_mut()[[0, 3, 4]] += 50.0;
        let glu = Glu::new(&pad_even(&guide).unwrap());
        assert!(glu.samples.iter().any(|s| matches!(s, Sample::Point(..))));
        let (dx, dy) = img.forward_differences();
        let coarse = glu.downsample(&img, false).unwrap();
        let (cdx, cdy) = glu.downsample_gradients(&dx, &dy).unwrap();
        let (edx, edy) = coarse.forward_differences();
        for (a, b) in [(&cdx, &edx), (&cdy, &edy)] {
            let d = a
                .as_slice()
                .iter()
                .zip(b.as_slice())
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f32::max);
            assert!(d < 1e-4, "{d}");
        }
    }

    /// The per-pixel fit as it was written before the lanes: the oracle of [`best_pairs`].
    fn fit_literal(glu: &Glu, j: &Image, coarse: &Image, p: usize) -> ((u32, u32, f32), f32) {
        let (w, h) = glu.fine;
        let (cw, ch) = glu.coarse;
        let (nc, n, cn) = (j.channels(), w * h, cw * ch);
        let (fs, cs) = (j.as_slice(), coarse.as_slice());
        let cand = glu.candidates(p % w, p / w);
        let mut u = [[0.0f64; 9]; 9];
        for (k, uk) in u.iter_mut().enumerate() {
            for (c, v) in uk[..nc].iter_mut().enumerate() {
                *v = f64::from(fs[c * n + p]) - f64::from(cs[c * cn + cand[k]]);
            }
        }
        let mut g = [[0.0f64; 9]; 9];
        for ka in 0..9 {
            for kb in ka..9 {
                let d: f64 = (0..nc).map(|c| u[ka][c] * u[kb][c]).sum();
                g[ka][kb] = d;
                g[kb][ka] = d;
            }
        }
        let mut best = ((cand[4] as u32, cand[4] as u32, 1.0f32), f64::INFINITY);
        for ia in 0..9 {
            for ib in ia..9 {
                let num = g[ib][ib] - g[ia][ib];
                let den = g[ia][ia] + g[ib][ib] - 2.0 * g[ia][ib];
                let wgt = if den > 0.0 {
                    (num / den).clamp(0.0, 1.0)
                } else {
                    1.0
                };
                let err = (g[ib][ib] - 2.0 * wgt * num + wgt * wgt * den).max(0.0);
                if err < best.1 {
                    best = ((cand[ia] as u32, cand[ib] as u32, wgt as f32), err);
                }
            }
        }
        (best.0, best.1.sqrt() as f32)
    }

    #[test]
    fn lane_fits_equal_the_per_pixel_fits_bit_for_bit() {
        // Widths that are and are not multiples of the lanes, 9 and 3 channels, values large
        // enough that some blocks are point-sampled (the refit of only some pixels included),
        // and exact ties (a constant region).
        let mut points = 0;
        for (w, h, nc) in [(22, 10, 9), (16, 6, 3), (2, 2, 9), (34, 8, 3)] {
            let j = Image::from_fn(nc, w, h, |(c, x, y)| {
                if x < 4 && y < 4 {
                    return 0.5;
                }
                let k = (x * 7919 + y * 104_729 + c * 1_299_709) % 1000;
                (k as f32 / 1000.0) * if c < 3 { 4.0 } else { 0.3 }
            });
            let mut glu = Glu::new(&j);
            points += glu.samples.iter().filter(|s| **s != Sample::Box).count();
            let coarse = glu.downsample(&j, false).unwrap();
            let before = glu.fit.clone();
            let only: Vec<bool> = (0..glu.coarse.0 * glu.coarse.1)
                .map(|q| q % 3 == 0)
                .collect();
            for sel in [None, Some(&only[..])] {
                glu.fit = before.clone();
                let errors = glu.refit(&j, &coarse, sel).unwrap();
                for p in 0..w * h {
                    let cand = glu.candidates(p % w, p / w);
                    if sel.is_some_and(|o| !cand.iter().any(|&q| o[q])) {
                        assert_eq!((glu.fit[p], errors[p]), (before[p], 0.0));
                        continue;
                    }
                    let (fit, err) = fit_literal(&glu, &j, &coarse, p);
                    let got = (glu.fit[p], errors[p]);
                    assert_eq!(
                        (got.0 .0, got.0 .1, got.0 .2.to_bits(), got.1.to_bits()),
                        (fit.0, fit.1, fit.2.to_bits(), err.to_bits()),
                        "{w} x {h} x {nc}, pixel {p}"
                    );
                }
            }
        }
        assert!(points > 0, "no block was point-sampled");
    }

    #[test]
    fn each_fine_pixel_gets_the_best_of_the_36_pairs() {
        // Brute force in f64: for every pair of the parent's 3 x 3 neighbours, the least-squares
        // weight in [0, 1] and its error; the Gram-matrix fit must reach the minimum.
        let (w, h) = (14, 10);
        let j = Image::from_fn(9, w, h, |(c, x, y)| {
            let k = (x * 7919 + y * 104_729 + c * 1_299_709) % 1000;
            (k as f32 / 1000.0) * if c < 3 { 4.0 } else { 0.3 }
        });
        let glu = Glu::new(&j);
        let coarse = glu.downsample(&j, false).unwrap();
        let (cw, ch) = glu.coarse;
        let at = |q: usize, c: usize| f64::from(coarse.as_slice()[c * cw * ch + q]);
        let err = |p: usize, a: usize, b: usize, wt: f64| -> f64 {
            (0..9)
                .map(|c| {
                    let t = f64::from(j.as_slice()[c * w * h + p]);
                    let e = t - (wt * at(a, c) + (1.0 - wt) * at(b, c));
                    e * e
                })
                .sum()
        };
        for p in 0..w * h {
            let (px, py) = ((p % w / 2) as isize, (p / w / 2) as isize);
            let cand: Vec<usize> = (-1..=1)
                .flat_map(|dy| (-1..=1).map(move |dx| (dx, dy)))
                .map(|(dx, dy)| reflect(py + dy, ch) * cw + reflect(px + dx, cw))
                .collect();
            let mut best = f64::INFINITY;
            for &a in &cand {
                for &b in &cand {
                    let (mut num, mut den) = (0.0, 0.0);
                    for c in 0..9 {
                        let t = f64::from(j.as_slice()[c * w * h + p]);
                        let d = at(a, c) - at(b, c);
                        num += (t - at(b, c)) * d;
                        den += d * d;
                    }
                    let wt = if den > 0.0 {
                        (num / den).clamp(0.0, 1.0)
                    } else {
                        1.0
                    };
                    best = best.min(err(p, a, b, wt));
                }
            }
            let (a, b, wt) = glu.fit[p];
            let got = err(p, a as usize, b as usize, f64::from(wt));
            assert!(
                got <= best * (1.0 + 1e-5) + 1e-9,
                "pixel {p}: {got} vs {best}"
            );
        }
    }

    /// Downsampling, gradient downsampling and upsampling as they were written per pixel (one
    /// closure call a pixel, `Image::at`): the oracle of the row kernels.
    fn resample_literal(glu: &Glu, img: &Image, dx: &Image, dy: &Image) -> [Image; 6] {
        let (cw, ch) = glu.coarse;
        let (w, h) = glu.fine;
        let down = |variance: bool| {
            Image::from_fn(img.channels(), cw, ch, |(c, x, y)| {
                match glu.samples[y * cw + x] {
                    Sample::Box => {
                        let s = img.at(c, 2 * x, 2 * y)
                            + img.at(c, 2 * x + 1, 2 * y)
                            + img.at(c, 2 * x, 2 * y + 1)
                            + img.at(c, 2 * x + 1, 2 * y + 1);
                        if variance {
                            s / 16.0
                        } else {
                            s / 4.0
                        }
                    }
                    Sample::Point(i, j) => img.at(c, 2 * x + i as usize, 2 * y + j as usize),
                }
            })
        };
        let path = |c: usize, (sx, sy): (usize, usize), (tx, ty): (usize, usize)| -> f32 {
            let mut s = 0.0;
            let sign = if tx >= sx { 1.0 } else { -1.0 };
            for x in sx.min(tx)..sx.max(tx) {
                s += sign * dx.at(c, x, sy);
            }
            let sign = if ty >= sy { 1.0 } else { -1.0 };
            for y in sy.min(ty)..sy.max(ty) {
                s += sign * dy.at(c, tx, y);
            }
            s
        };
        let edge = |c: usize, a: (usize, usize), b: (usize, usize)| -> f32 {
            let ((ma, la), (mb, lb)) = (glu.members(a.0, a.1), glu.members(b.0, b.1));
            let mut s = 0.0;
            for &p in &ma[..la] {
                for &q in &mb[..lb] {
                    s += path(c, p, q);
                }
            }
            s / (la * lb) as f32
        };
        let cdx = Image::from_fn(3, cw, ch, |(c, x, y)| {
            if x + 1 < cw {
                edge(c, (x, y), (x + 1, y))
            } else {
                0.0
            }
        });
        let cdy = Image::from_fn(3, cw, ch, |(c, x, y)| {
            if y + 1 < ch {
                edge(c, (x, y), (x, y + 1))
            } else {
                0.0
            }
        });
        let coarse = down(false);
        let cs = coarse.as_slice();
        let up = |square: bool| {
            Image::from_fn(img.channels(), w, h, |(c, x, y)| {
                let (a, b, wt) = glu.fit[y * w + x];
                let (a, b) = (cs[c * cw * ch + a as usize], cs[c * cw * ch + b as usize]);
                if square {
                    wt * wt * a + (1.0 - wt) * (1.0 - wt) * b
                } else {
                    wt * a + (1.0 - wt) * b
                }
            })
        };
        [down(false), down(true), cdx, cdy, up(false), up(true)]
    }

    #[test]
    fn row_kernels_equal_the_per_pixel_resampling_bit_for_bit() {
        // Box and point-sampled blocks, gradients whose paths cross both, 9 and 3 channels,
        // rows long enough for the box-edge kernels' vector loops (16 lanes) and short ones.
        let mut points = 0;
        for (w, h, nc) in [(22, 10, 9), (16, 6, 3), (2, 2, 9), (78, 8, 3)] {
            let value = |c: usize, x: usize, y: usize, salt: usize| {
                let k = (x * 7919 + y * 104_729 + c * 1_299_709 + salt * 15_485_863) % 1000;
                (k as f32 / 1000.0 - 0.3) * if c < 3 { 4.0 } else { 0.3 }
            };
            let j = Image::from_fn(nc, w, h, |(c, x, y)| value(c, x, y, 0));
            let glu = Glu::new(&j);
            points += glu.samples.iter().filter(|s| **s != Sample::Box).count();
            let [dx, dy] =
                [1, 2].map(|salt| Image::from_fn(3, w, h, |(c, x, y)| value(c, x, y, salt)));
            let want = resample_literal(&glu, &j, &dx, &dy);
            let coarse = glu.downsample(&j, false).unwrap();
            let (cdx, cdy) = glu.downsample_gradients(&dx, &dy).unwrap();
            let (up, var) = glu.upsample(&coarse, Some(&coarse)).unwrap();
            let got = [
                coarse,
                glu.downsample(&j, true).unwrap(),
                cdx,
                cdy,
                up,
                var.unwrap(),
            ];
            for (k, (g, e)) in got.iter().zip(&want).enumerate() {
                let bits = |i: &Image| i.as_slice().iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                assert_eq!(
                    (g.size(), bits(g)),
                    (e.size(), bits(e)),
                    "{w} x {h} x {nc}, output {k}"
                );
            }
        }
        assert!(points > 0, "no block was point-sampled");
    }

    #[test]
    fn upsampled_variance_uses_squared_weights() {
        let j = Image::from_fn(3, 4, 4, |(c, x, y)| (x + 2 * y + c) as f32);
        let glu = Glu::new(&j);
        let v = Image::from_fn(3, 2, 2, |_| 1.0);
        let (_, var) = glu.upsample(&v, Some(&v)).unwrap();
        for (p, &(_, _, wt)) in glu.fit.iter().enumerate() {
            let expect = wt * wt + (1.0 - wt) * (1.0 - wt);
            assert!((var.as_ref().unwrap().as_slice()[p] - expect).abs() < 1e-6);
        }
    }

    #[test]
    fn odd_sizes_pad_and_crop_back() {
        let img = Image::from_fn(3, 7, 5, |(c, x, y)| (x + 10 * y + c) as f32);
        let p = pad_even(&img).unwrap();
        assert_eq!(p.size(), (8, 6));
        assert_eq!(p.at(0, 7, 0), img.at(0, 5, 0));
        assert_eq!(crop(p.into_owned(), 7, 5).unwrap(), img);
    }
}
