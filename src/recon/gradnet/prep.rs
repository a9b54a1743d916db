//! GradNet's input and output transforms, done natively around the graph (the graph holds only
//! the network): μ-law compression, feature normalisation, padding to a multiple of 8 and the
//! inverse transform. Each function is the Rust twin of one in `onnx/gdrecon_py/pipeline.py`, which the
//! parity tests hold it to.
//!
//! Padding never materialises a padded frame: a tile reads the frame through index maps
//! ([`AxisMap`]) from padded coordinates to frame coordinates, so memory stays bounded by the
//! tile, not by the frame.

use ndarray::ArrayViewMut2;
use rayon::prelude::*;

use crate::frame::Frame;
use crate::recon::ops::reflect;

/// μ of the μ-law, as the release.
pub(crate) const MU: f32 = 16.0;
/// Features are clamped to ±this before normalisation (the release).
pub(crate) const FEATURE_CLAMP: f32 = 1e5;
/// Frames are padded to a multiple of this (three stride-2 encoder levels).
pub(crate) const PAD_MULTIPLE: usize = 8;

/// `C(x) = ln(1 + μ x) / ln(1 + μ)`, for non-negative radiance.
#[inline]
pub(crate) fn compress(x: f32) -> f32 {
    (MU * x).ln_1p() / MU.ln_1p()
}

/// `S(x) = sign(x) C(|x|)`, for signed gradients.
#[inline]
pub(crate) fn compress_signed(x: f32) -> f32 {
    let c = compress(x.abs());
    if x < 0.0 {
        -c
    } else {
        c
    }
}

/// `C⁻¹(y) = ((1 + μ)^y − 1) / μ`, in f64 as the reference (the network's output is not
/// bounded, and `exp` of an f32 loses digits near 0).
#[inline]
pub(crate) fn expand(y: f32) -> f32 {
    ((y as f64 * (MU as f64).ln_1p()).exp_m1() / MU as f64) as f32
}

/// `n` rounded up to a multiple of [`PAD_MULTIPLE`].
pub(crate) fn padded(n: usize) -> usize {
    n.div_ceil(PAD_MULTIPLE) * PAD_MULTIPLE
}

/// Maps padded coordinates along one axis (`0..padded(n)`) to frame coordinates.
///
/// Colour and features are reflected without repeating the edge (numpy's `reflect`,
/// `dcb|abcd|cba`). A forward difference along this axis is mirrored so that it stays the
/// difference of the reflected colour: where the reflection runs backwards the difference
/// changes sign and moves by one (`dx'(p) = -dx(2n - 3 - p)` for `p >= n - 1`), which also
/// replaces the stored zero of the last column. When no padding is needed nothing changes.
/// A 1-pixel axis has no reflection: it is repeated, and its differences are zero.
#[derive(Clone, Copy, Debug)]
pub(crate) struct AxisMap {
    n: usize,
    padded: usize,
}

impl AxisMap {
    pub fn new(n: usize) -> Self {
        AxisMap {
            n,
            padded: padded(n),
        }
    }

    /// Padded length.
    pub fn padded_len(self) -> usize {
        self.padded
    }

    /// Frame index of padded position `p` for colour, features, and gradients across their
    /// axis.
    #[inline]
    pub fn plain(self, p: usize) -> usize {
        reflect(p as isize, self.n)
    }

    /// `(frame index, sign)` of a forward difference along this axis at padded position `p`.
    #[inline]
    pub fn along(self, p: usize) -> (usize, f32) {
        if self.padded == self.n {
            return (p, 1.0);
        }
        let (a, b) = (self.plain(p), self.plain(p + 1));
        match b.cmp(&a) {
            std::cmp::Ordering::Greater => (a, 1.0),
            std::cmp::Ordering::Less => (b, -1.0),
            std::cmp::Ordering::Equal => (0, 0.0),
        }
    }
}

/// Per-frame feature normalisation: albedo clamped to [0, 1], normal `n * 0.5 + 0.5`, depth
/// min-max normalised over the frame (0 when constant). Everything clamped to ±1e5 first.
///
/// Albedo is clamped to [0, 1] at inference (a deviation from the release, documented in
/// `onnx/gdrecon_py/pipeline.py`): conductors' AOV albedo reaches hundreds, far outside what the network
/// learnt.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct FeatureNorm {
    depth_min: f32,
    depth_range: f32,
}

impl FeatureNorm {
    /// The normalisation of `frame`'s features; `None` when albedo, normal or depth is missing.
    pub fn of(frame: &Frame) -> Option<FeatureNorm> {
        let (_, _, depth) = (frame.albedo()?, frame.normal()?, frame.depth()?);
        let (lo, hi) = depth
            .plane(0)
            .as_slice()
            .expect("planes are contiguous")
            .par_iter()
            .map(|&d| clamp_feature(d))
            .fold(
                || (f32::INFINITY, f32::NEG_INFINITY),
                |(lo, hi), d| (lo.min(d), hi.max(d)),
            )
            .reduce(
                || (f32::INFINITY, f32::NEG_INFINITY),
                |a, b| (a.0.min(b.0), a.1.max(b.1)),
            );
        Some(FeatureNorm {
            depth_min: lo,
            depth_range: if hi > lo {
                (hi as f64 - lo as f64) as f32
            } else {
                0.0
            },
        })
    }

    #[inline]
    fn albedo(self, a: f32) -> f32 {
        clamp_feature(a).clamp(0.0, 1.0)
    }

    #[inline]
    fn normal(self, n: f32) -> f32 {
        clamp_feature(n) * 0.5 + 0.5
    }

    #[inline]
    fn depth(self, d: f32) -> f32 {
        if self.depth_range > 0.0 {
            (clamp_feature(d) - self.depth_min) / self.depth_range
        } else {
            0.0
        }
    }
}

#[inline]
fn clamp_feature(v: f32) -> f32 {
    v.clamp(-FEATURE_CLAMP, FEATURE_CLAMP)
}

/// A window of the padded frame: rows `y0..y0 + h`, columns `x0..x0 + w` (padded coordinates).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Window {
    pub y0: usize,
    pub x0: usize,
    pub h: usize,
    pub w: usize,
}

/// Index maps of both axes.
#[derive(Clone, Copy, Debug)]
pub(crate) struct FrameMap {
    pub x: AxisMap,
    pub y: AxisMap,
}

impl FrameMap {
    pub fn new(width: usize, height: usize) -> Self {
        FrameMap {
            x: AxisMap::new(width),
            y: AxisMap::new(height),
        }
    }
}

/// Writes the seven normalised feature planes of window `win` into `planes` (7 planes of
/// `win.h x win.w`, row-major, one after the other).
pub(crate) fn fill_features(
    frame: &Frame,
    norm: FeatureNorm,
    map: FrameMap,
    win: Window,
    planes: &mut [f32],
) {
    let (albedo, normal, depth) = (
        frame
            .albedo()
            .expect("FeatureNorm::of checked the features"),
        frame
            .normal()
            .expect("FeatureNorm::of checked the features"),
        frame.depth().expect("FeatureNorm::of checked the features"),
    );
    let plane_len = win.h * win.w;
    planes
        .par_chunks_mut(win.w)
        .enumerate()
        .for_each(|(row_index, row)| {
            let (k, i) = (row_index / win.h, row_index % win.h);
            debug_assert!(k < 7 && row_index < 7 * plane_len);
            let sy = map.y.plain(win.y0 + i);
            let (image, c) = match k {
                0..=2 => (albedo, k),
                3..=5 => (normal, k - 3),
                _ => (depth, 0),
            };
            let src = image.plane(c);
            let src = src.row(sy);
            for (j, v) in row.iter_mut().enumerate() {
                let s = src[map.x.plain(win.x0 + j)];
                *v = match k {
                    0..=2 => norm.albedo(s),
                    3..=5 => norm.normal(s),
                    _ => norm.depth(s),
                };
            }
        });
}

/// Writes colour channel `c` of window `win`, compressed, into `data` (`win.h x win.w`) and its
/// compressed, mirrored gradients into `dx` and `dy`.
pub(crate) fn fill_channel(
    frame: &Frame,
    c: usize,
    map: FrameMap,
    win: Window,
    data: ArrayViewMut2<'_, f32>,
    dx: ArrayViewMut2<'_, f32>,
    dy: ArrayViewMut2<'_, f32>,
) {
    let (color, gx, gy) = (
        frame.color().plane(c),
        frame.dx().plane(c),
        frame.dy().plane(c),
    );
    data.into_slice()
        .expect("tile planes are contiguous")
        .par_chunks_mut(win.w)
        .zip(dx.into_slice().expect("contiguous").par_chunks_mut(win.w))
        .zip(dy.into_slice().expect("contiguous").par_chunks_mut(win.w))
        .enumerate()
        .for_each(|(i, ((d_row, dx_row), dy_row))| {
            let py = win.y0 + i;
            let sy = map.y.plain(py);
            let (gy_row, gy_sign) = map.y.along(py);
            let (color_row, gx_row, gy_row) = (color.row(sy), gx.row(sy), gy.row(gy_row));
            for j in 0..win.w {
                let px = win.x0 + j;
                let sx = map.x.plain(px);
                let (gx_col, gx_sign) = map.x.along(px);
                d_row[j] = compress(color_row[sx]);
                dx_row[j] = compress_signed(gx_sign * gx_row[gx_col]);
                dy_row[j] = compress_signed(gy_sign * gy_row[sx]);
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mu_law_round_trip_and_values() {
        // C(1) = 1 and C(0) = 0 by construction; C(0.5) = ln 9 / ln 17.
        assert_eq!(compress(0.0), 0.0);
        assert!((compress(1.0) - 1.0).abs() < 1e-7);
        assert!((compress(0.5) - (9f32.ln() / 17f32.ln())).abs() < 1e-7);
        assert_eq!(compress_signed(-0.5), -compress(0.5));
        for &x in &[0.0f32, 1e-6, 0.01, 0.3, 1.0, 7.5, 1e4] {
            let back = expand(compress(x));
            assert!((back - x).abs() <= 1e-5 * x.max(1e-2), "{x} -> {back}");
        }
    }

    #[test]
    fn axis_map_reflects_and_mirrors_gradients() {
        // n = 5 padded to 8: colour indices 0 1 2 3 4 3 2 1.
        let m = AxisMap::new(5);
        let plain: Vec<usize> = (0..8).map(|p| m.plain(p)).collect();
        assert_eq!(plain, [0, 1, 2, 3, 4, 3, 2, 1]);
        // Differences of that colour: d0 d1 d2 d3 -d3 -d2 -d1 -d0.
        let along: Vec<(usize, f32)> = (0..8).map(|p| m.along(p)).collect();
        assert_eq!(
            along,
            [
                (0, 1.0),
                (1, 1.0),
                (2, 1.0),
                (3, 1.0),
                (3, -1.0),
                (2, -1.0),
                (1, -1.0),
                (0, -1.0)
            ]
        );
        // Already a multiple of 8: the stored last difference is kept as is.
        assert_eq!(AxisMap::new(8).along(7), (7, 1.0));
        // One pixel: repeated, no difference.
        assert_eq!(AxisMap::new(1).along(3), (0, 0.0));
    }

    #[test]
    fn mirrored_gradients_are_differences_of_the_padded_colour() {
        let colour = [0.3f32, 1.7, -0.2, 4.0, 2.5, 0.9, 3.3, 1.1, 0.4, 2.2, 5.0];
        for n in 2..colour.len() {
            let c = &colour[..n];
            let d: Vec<f32> = (0..n)
                .map(|i| if i + 1 < n { c[i + 1] - c[i] } else { 0.0 })
                .collect();
            let m = AxisMap::new(n);
            for p in 0..m.padded_len() - 1 {
                let (i, s) = m.along(p);
                let want = c[m.plain(p + 1)] - c[m.plain(p)];
                if m.padded_len() > n || p + 1 < n {
                    assert!((s * d[i] - want).abs() < 1e-6, "n {n} p {p}");
                }
            }
        }
    }
}
