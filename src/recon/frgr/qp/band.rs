//! Bands of rows padded with the reflect-101 border, so that the windows of a lane group are
//! plain slices, and the bias terms read from them.

use super::lanes::{F32x, LANES};
use super::level::QpLevel;
use crate::error::Result;
use crate::image::{try_resize, Image};
use crate::recon::frgr::util::{reflect, reflect_borders};

/// Image rows per band. A band pads its own rows (plus the windows' halo) of every plane it
/// reads, so that the padded copies stay small whatever the frame size.
pub(super) const BAND: usize = 16;

/// Rows of a few channels with a reflect-101 border of `r` pixels on every side and
/// `LANES - 1` more columns on the right, so that a lane group's windows are plain slices.
pub(super) struct Padded {
    pub(super) data: Vec<f32>,
    pub(super) stride: usize,
    pub(super) plane: usize,
}

impl Padded {
    /// Pads rows `y0 - r .. y0 + rows + r` of `channels` planes of a `w` x `h` image into
    /// `data` (a worker's buffer from an earlier band, or empty); `fill(c, y, row)` writes
    /// image row `y` of channel `c` (`w` values) into `row`. Row by row: the image's columns
    /// are written once, in place, and the border copied from them; every value is written, so
    /// a reused buffer is neither cleared nor zeroed.
    pub(super) fn new(
        mut data: Vec<f32>,
        channels: usize,
        (w, h): (usize, usize),
        r: usize,
        (y0, rows): (usize, usize),
        fill: impl Fn(usize, usize, &mut [f32]),
    ) -> Result<Padded> {
        let (stride, padded_rows) = (w + 2 * r + LANES - 1, rows + 2 * r);
        try_resize(&mut data, channels * padded_rows * stride, 0.0)?;
        for (row, out) in data.chunks_exact_mut(stride).enumerate() {
            let (c, py) = (row / padded_rows, row % padded_rows);
            let y = reflect((y0 + py) as isize - r as isize, h);
            fill(c, y, &mut out[r..r + w]);
            reflect_borders(out, r, w);
        }
        Ok(Padded {
            data,
            stride,
            plane: padded_rows * stride,
        })
    }

    /// Pads rows of `channels` planes of `s` (plane after plane, `w * h` values each), as
    /// [`Padded::new`].
    pub(super) fn copy(
        data: Vec<f32>,
        s: &[f32],
        channels: usize,
        (w, h): (usize, usize),
        r: usize,
        band: (usize, usize),
    ) -> Result<Padded> {
        Padded::new(data, channels, (w, h), r, band, |c, y, row| {
            row.copy_from_slice(&s[(c * h + y) * w..][..w]);
        })
    }

    /// Padded row `py` of channel `c` (image row `y0 + py - r`) from padded column `x0`.
    #[inline(always)]
    pub(super) fn row(&self, c: usize, py: usize, x0: usize) -> &[f32] {
        let start = c * self.plane + py * self.stride;
        &self.data[start + x0..start + self.stride]
    }
}

/// The padded planes of one band.
pub(super) struct Planes {
    pub(super) img: Padded,
    pub(super) var: Padded,
    /// `v`: the summed clamped variances.
    pub(super) v: Padded,
    pub(super) enhanced: Padded,
    pub(super) albedo: Option<Padded>,
    pub(super) normal: Option<Padded>,
    pub(super) up: Option<Padded>,
}

impl Planes {
    /// Pads the planes of `band` (its first row and its number of rows) of `level`, in buffers
    /// taken from `spare` (those of the worker's previous band, in the order of the fields
    /// here; new ones when it runs out).
    pub(super) fn new(
        level: &QpLevel,
        band: (usize, usize),
        spare: &mut Vec<Vec<f32>>,
    ) -> Result<Planes> {
        let dims = level.img.size();
        let (n_px, r) = (dims.0 * dims.1, level.radius);
        let spare = std::cell::RefCell::new(spare);
        let take = || spare.borrow_mut().pop().unwrap_or_default();
        let plain = |img: &Image| Padded::copy(take(), img.as_slice(), 3, dims, r, band);
        let var = level.var.as_slice();
        let up_var = level.up.map(|(_, v)| v.as_slice());
        let w = dims.0;
        Ok(Planes {
            img: plain(level.img)?,
            var: plain(level.var)?,
            v: Padded::new(take(), 1, dims, r, band, |_, y, row| {
                for (x, vq) in row.iter_mut().enumerate() {
                    let q = y * w + x;
                    let mut sum = 0.0;
                    for c in 0..3 {
                        sum += var[c * n_px + q].max(0.0);
                        if let Some(uv) = up_var {
                            sum += uv[c * n_px + q].max(0.0);
                        }
                    }
                    *vq = sum;
                }
            })?,
            enhanced: plain(level.enhanced)?,
            albedo: level.albedo.map(plain).transpose()?,
            normal: level.normal.map(plain).transpose()?,
            up: level.up.map(|(u, _)| plain(u)).transpose()?,
        })
    }

    /// Gives the planes' buffers back to `spare`, for the worker's next band: in reverse, so
    /// that [`Planes::new`] gives each plane the buffer it had (the same length: no fill).
    pub(super) fn recycle(self, spare: &mut Vec<Vec<f32>>) {
        let planes = [
            Some(self.img),
            Some(self.var),
            Some(self.v),
            Some(self.enhanced),
            self.albedo,
            self.normal,
            self.up,
        ];
        spare.extend(planes.into_iter().rev().flatten().map(|p| p.data));
    }

    /// The bias terms whose input is present, in the release's order: those in the objective
    /// (`al`, `k / 3` of them, padded with zero-weight ones if fewer: never needed) have rows;
    /// dropped ones (`level.dropped`) only count in the initial weights.
    pub(super) fn terms<'a>(
        &'a self,
        level: &'a QpLevel,
        al: &[f32; 5],
        k: usize,
    ) -> Vec<Term<'a>> {
        let present = level.present_alphas();
        let term = |src, centre: &'a Image, residual, a: usize| {
            let sq = present[a].sqrt();
            Term {
                src,
                centre: centre.as_slice(),
                residual,
                sq: F32x::splat(sq),
                counts: sq > 0.0,
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
                counts: false,
                ..term(&self.img, level.img, Residual::None, 0)
            });
        }
        terms
    }
}

/// How a bias term adds the coarser level's residual `img(q) - up(q)`.
#[derive(Clone, Copy)]
pub(super) enum Residual {
    /// Not at all (`b0`, `b3`, `b4`): adds `-0`, which leaves every value as it is.
    None,
    /// Feature terms at the coarsest level: `+ 0` (turns a `-0` into `+0`, as the release).
    Zero,
    /// Feature terms at finer levels.
    ImgMinusUp,
}

impl Residual {
    /// Which of `[-0, +0, residual of R, G, B]` channel `c` adds.
    pub(super) fn addend(self, c: usize) -> usize {
        match self {
            Residual::None => 0,
            Residual::Zero => 1,
            Residual::ImgMinusUp => 2 + c,
        }
    }
}

/// One active bias term: `sqrt(alpha) * (src(q) - centre(p) + residual(q))` per channel.
pub(super) struct Term<'a> {
    pub(super) src: &'a Padded,
    /// Unpadded planes, read at the pixel itself.
    pub(super) centre: &'a [f32],
    pub(super) residual: Residual,
    /// `sqrt(alpha)`.
    pub(super) sq: F32x,
    /// Whether the term counts in the initial weights' costs (not one of weight 0).
    pub(super) counts: bool,
    /// Whether the term has rows in the objective (false: dropped, see [`vanishing_terms`](super::vanishing_terms)).
    pub(super) row: bool,
}
