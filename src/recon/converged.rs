//! Pixels a frame has already converged: the expensive methods return their base colour there
//! instead of computing it.
//!
//! A pixel is converged when, in every channel, the variance of its mean is at most
//! `(RELATIVE_NOISE * I)²` (its noise is below 0.1 % of its value) and each of the four
//! gradients touching it agrees with the base image's finite difference to that same relative
//! precision. The base is then already the answer to the precision of the estimate; a filter
//! or network could only move it away. Frames without a variance layer have no converged
//! pixels (nothing says they are). At the validation set's 4-64 spp no pixel qualifies (it
//! takes roughly a million samples), so results there are unchanged.

use rayon::prelude::*;

use crate::error::Result;
use crate::frame::Frame;
use crate::image::try_vec;

/// Relative noise level (standard deviation over value) under which a pixel is converged.
pub const RELATIVE_NOISE: f32 = 1e-3;

/// One flag per pixel (row-major), or `None` when the frame has no variance layer or no
/// pixel is converged; fails only with [`Error::OutOfMemory`](crate::Error::OutOfMemory).
pub(crate) fn converged_mask(frame: &Frame) -> Result<Option<Vec<bool>>> {
    let Some(var) = frame.variance() else {
        return Ok(None);
    };
    let (w, h) = frame.size();
    let n = w * h;
    let (colour, dx, dy) = (
        frame.color().as_slice(),
        frame.dx().as_slice(),
        frame.dy().as_slice(),
    );
    let var = var.as_slice();
    let close = |g: f32, a: f32, b: f32| {
        (g - (b - a)).abs() <= RELATIVE_NOISE * (a.abs() + b.abs()) + f32::MIN_POSITIVE
    };
    if n == 0 {
        return Ok(None);
    }
    let mut mask = try_vec(n, false)?;
    // Row by row over slices (so that the tests vectorise), each condition and edge as the
    // definition above states it; the edge between two rows is tested in both.
    let scratch = || vec![false; w - 1];
    mask.par_chunks_mut(w)
        .enumerate()
        .for_each_init(scratch, |edge, (y, row)| {
            row.fill(true);
            for c in 0..3 {
                let o = c * n + y * w;
                let (i, v) = (&colour[o..][..w], &var[o..][..w]);
                for ((m, &i), &v) in row.iter_mut().zip(i).zip(v) {
                    *m &= v <= (RELATIVE_NOISE * i) * (RELATIVE_NOISE * i);
                }
                // Across each edge to the right, for the pixels on both sides.
                let (g, right) = (&dx[o..][..edge.len()], &i[1..]);
                for (((e, &g), &a), &b) in edge.iter_mut().zip(g).zip(i).zip(right) {
                    *e = close(g, a, b);
                }
                for (m, &e) in row.iter_mut().zip(edge.iter()) {
                    *m &= e;
                }
                for (m, &e) in row.iter_mut().skip(1).zip(edge.iter()) {
                    *m &= e;
                }
                if y + 1 < h {
                    let (g, below) = (&dy[o..][..w], &colour[o + w..][..w]);
                    for (((m, &g), &a), &b) in row.iter_mut().zip(g).zip(i).zip(below) {
                        *m &= close(g, a, b);
                    }
                }
                if y > 0 {
                    let (g, above) = (&dy[o - w..][..w], &colour[o - w..][..w]);
                    for (((m, &g), &a), &b) in row.iter_mut().zip(g).zip(above).zip(i) {
                        *m &= close(g, a, b);
                    }
                }
            }
        });
    Ok(mask.iter().any(|&c| c).then_some(mask))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::{FrameBuilder, Layer};
    use crate::image::Image;
    use crate::validate::Policy;

    fn frame(var: f32, grad_error: f32) -> Frame {
        let colour = Image::from_fn(3, 5, 4, |(c, x, y)| 0.5 + 0.1 * (x + y + c) as f32);
        let (mut dx, dy) = colour.forward_differences();
        dx.as_mut_slice()[7] += grad_error;
        FrameBuilder::new()
            .image(Layer::Color, colour)
            .image(Layer::Dx, dx)
            .image(Layer::Dy, dy)
            .image(Layer::Variance, Image::from_fn(3, 5, 4, |_| var))
            .build(Policy::Replace)
            .unwrap()
    }

    #[test]
    fn noise_and_gradient_disagreement_decide() {
        assert!(converged_mask(&frame(0.0, 0.0))
            .unwrap()
            .unwrap()
            .iter()
            .all(|&c| c));
        // Noise above 0.1 % of the value anywhere: not converged there.
        assert!(converged_mask(&frame(1e-4, 0.0)).unwrap().is_none());
        // One inconsistent gradient (pixel 7 -> 8): both its ends are not converged.
        let m = converged_mask(&frame(0.0, 0.05)).unwrap().unwrap();
        assert!(!m[7] && !m[8] && m[0] && m[19]);
    }

    /// The definition pixel by pixel (the form before the row kernels).
    fn literal(frame: &Frame) -> Vec<bool> {
        let (w, h) = frame.size();
        let n = w * h;
        let colour = frame.color().as_slice();
        let (dx, dy) = (frame.dx().as_slice(), frame.dy().as_slice());
        let var = frame.variance().unwrap().as_slice();
        let close = |g: f32, a: f32, b: f32| {
            (g - (b - a)).abs() <= RELATIVE_NOISE * (a.abs() + b.abs()) + f32::MIN_POSITIVE
        };
        (0..n)
            .map(|p| {
                let (x, y) = (p % w, p / w);
                (0..3).all(|c| {
                    let o = c * n;
                    let i = colour[o + p];
                    let quiet = var[o + p] <= (RELATIVE_NOISE * i) * (RELATIVE_NOISE * i);
                    let right = x + 1 >= w || close(dx[o + p], i, colour[o + p + 1]);
                    let left = x == 0 || close(dx[o + p - 1], colour[o + p - 1], i);
                    let down = y + 1 >= h || close(dy[o + p], i, colour[o + p + w]);
                    let up = y == 0 || close(dy[o + p - w], colour[o + p - w], i);
                    quiet && right && left && down && up
                })
            })
            .collect()
    }

    #[test]
    fn rows_give_the_per_pixel_definition() {
        // Noise, horizontal and vertical gradient errors scattered by three different
        // strides, in one channel each, over sizes with one row or column and odd ones.
        for (w, h) in [(1, 1), (1, 6), (7, 1), (2, 2), (13, 7), (40, 9)] {
            let colour =
                Image::from_fn(3, w, h, |(c, x, y)| 0.2 + 0.05 * (3 * x + 2 * y + c) as f32);
            let (mut dx, mut dy) = colour.forward_differences();
            let n = w * h;
            for p in (0..n).step_by(5) {
                dx.as_mut_slice()[n + p] += 0.01;
            }
            for p in (0..n).step_by(7) {
                dy.as_mut_slice()[2 * n + p] -= 0.01;
            }
            let var = Image::from_fn(3, w, h, |(c, x, y)| {
                if c == 0 && (x + 3 * y) % 11 == 0 {
                    1e-3
                } else {
                    0.0
                }
            });
            let f = FrameBuilder::new()
                .image(Layer::Color, colour)
                .image(Layer::Dx, dx)
                .image(Layer::Dy, dy)
                .image(Layer::Variance, var)
                .build(Policy::Replace)
                .unwrap();
            let want = literal(&f);
            let got = converged_mask(&f)
                .unwrap()
                .unwrap_or_else(|| vec![false; n]);
            assert_eq!(got, want, "{w} x {h}");
            assert!(
                want.iter().any(|&c| c) || n <= 2,
                "{w} x {h}: some converged"
            );
        }
    }

    #[test]
    fn no_variance_layer_means_nothing_is_converged() {
        let colour = Image::from_fn(3, 2, 2, |_| 1.0);
        let (dx, dy) = colour.forward_differences();
        let f = FrameBuilder::new()
            .image(Layer::Color, colour)
            .image(Layer::Dx, dx)
            .image(Layer::Dy, dy)
            .build(Policy::Replace)
            .unwrap();
        assert!(converged_mask(&f).unwrap().is_none());
    }
}
