//! The Gaussian bias correction of the authors' release: the network's output is rescaled per
//! pixel so that its local mean (a wide Gaussian, radius 45, σ 15) matches the input's:
//! `gain = (blur(R+G+B of input) + 1e-9) / (blur(R+G+B of output) + 1e-9)`, multiplied into
//! all three channels. Borders are zero-padded (the kernel is not renormalised), as in the
//! release, so the gain near the border is a ratio of two equally truncated sums.
//!
//! The blur is separable and written as 91 row-wide multiply-adds per pass (shifted rows for
//! the horizontal pass, whole rows for the vertical one) so that it vectorises; rows run in
//! parallel. Cost: 2 images x 2 passes x 91 taps per pixel.

use rayon::prelude::*;

use crate::error::Result;
use crate::image::{try_vec, Image};

/// Kernel radius of the release.
pub(crate) const RADIUS: usize = 45;
/// Kernel σ of the release.
pub(crate) const SIGMA: f64 = 15.0;
const EPS: f32 = 1e-9;

/// The normalised 1-D Gaussian, `2 * RADIUS + 1` taps.
pub(crate) fn kernel() -> Vec<f32> {
    let r = RADIUS as isize;
    let raw: Vec<f64> = (-r..=r)
        .map(|x| (-((x * x) as f64) / (2.0 * SIGMA * SIGMA)).exp())
        .collect();
    let sum: f64 = raw.iter().sum();
    raw.iter().map(|&v| (v / sum) as f32).collect()
}

/// Separable zero-padded blur of a `w x h` plane with `taps` (odd length).
/// Fails only when its row-pass plane cannot be allocated.
pub(crate) fn blur(src: &[f32], w: usize, h: usize, taps: &[f32], out: &mut [f32]) -> Result<()> {
    let r = taps.len() / 2;
    let mut rows = try_vec(w * h, 0.0f32)?;
    // Horizontal: out[x] = sum_t taps[t] * src[x + t - r], zero outside.
    rows.par_chunks_mut(w).zip(src.par_chunks(w)).for_each_init(
        || vec![0.0f32; w + 2 * r],
        |padded, (dst, row)| {
            padded[r..r + w].copy_from_slice(row);
            dst.fill(0.0);
            for (t, &k) in taps.iter().enumerate() {
                for (d, &s) in dst.iter_mut().zip(&padded[t..t + w]) {
                    *d += k * s;
                }
            }
        },
    );
    // Vertical: out row y = sum_t taps[t] * rows[y + t - r], rows outside skipped.
    out.par_chunks_mut(w).enumerate().for_each(|(y, dst)| {
        dst.fill(0.0);
        let lo = y.saturating_sub(r);
        let hi = (y + r).min(h - 1);
        for sy in lo..=hi {
            let k = taps[sy + r - y];
            for (d, &s) in dst.iter_mut().zip(&rows[sy * w..(sy + 1) * w]) {
                *d += k * s;
            }
        }
    });
    Ok(())
}

/// Applies the bias correction to `out` (3 channels) against the input colour `color`.
/// Pixels marked in `skip` (row-major, one per pixel) enter neither blur: the gain then
/// compares the two images' energy only where the network can reproduce the input.
///
/// Four frame-sized planes at most (a channel sum, the two blurs, the blur's row pass): at
/// 3840 x 2160 that is 133 MB, where computing every intermediate into its own plane took 233.
/// Fails (with `out` unchanged) only when a plane cannot be allocated.
pub(crate) fn correct(out: &mut Image, color: &Image, skip: Option<&[bool]>) -> Result<()> {
    let (w, h) = out.size();
    let n = w * h;
    let taps = kernel();
    let channel_sum = |img: &Image, sum: &mut [f32]| {
        let s = img.as_slice();
        sum.par_iter_mut().enumerate().for_each(|(i, v)| {
            *v = if skip.is_some_and(|m| m[i]) {
                0.0
            } else {
                s[i] + s[n + i] + s[2 * n + i]
            }
        });
    };
    let mut sum = try_vec(n, 0.0f32)?;
    channel_sum(color, &mut sum);
    let mut blur_in = try_vec(n, 0.0f32)?;
    blur(&sum, w, h, &taps, &mut blur_in)?;
    channel_sum(out, &mut sum);
    let mut blur_out = try_vec(n, 0.0f32)?;
    blur(&sum, w, h, &taps, &mut blur_out)?;
    drop(sum);
    out.as_mut_slice().par_chunks_mut(n).for_each(|plane| {
        for ((v, &bi), &bo) in plane.iter_mut().zip(&blur_in).zip(&blur_out) {
            *v *= (bi + EPS) / (bo + EPS);
        }
    });
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Direct 2-D evaluation in f64: sum over every in-bounds pixel of k(dy) k(dx) src.
    fn naive(src: &[f32], w: usize, h: usize, taps: &[f32]) -> Vec<f64> {
        let r = (taps.len() / 2) as isize;
        let mut out = vec![0.0; w * h];
        for y in 0..h as isize {
            for x in 0..w as isize {
                let mut s = 0.0f64;
                for dy in -r..=r {
                    for dx in -r..=r {
                        let (sy, sx) = (y + dy, x + dx);
                        if sy >= 0 && sy < h as isize && sx >= 0 && sx < w as isize {
                            s += taps[(dy + r) as usize] as f64
                                * taps[(dx + r) as usize] as f64
                                * src[(sy * w as isize + sx) as usize] as f64;
                        }
                    }
                }
                out[(y * w as isize + x) as usize] = s;
            }
        }
        out
    }

    #[test]
    fn kernel_is_normalised_and_symmetric() {
        let k = kernel();
        assert_eq!(k.len(), 91);
        assert!((k.iter().map(|&v| v as f64).sum::<f64>() - 1.0).abs() < 1e-6);
        assert_eq!(k[0], k[90]);
        assert!(k[45] > k[44]);
    }

    #[test]
    fn blur_matches_direct_evaluation_with_zero_borders() {
        // Sizes smaller than, around and larger than the kernel.
        for &(w, h) in &[(1, 1), (5, 3), (50, 7), (97, 96)] {
            let src: Vec<f32> = (0..w * h)
                .map(|i| ((i * 37 % 101) as f32 / 50.0) - 0.3)
                .collect();
            let mut out = vec![0.0; w * h];
            blur(&src, w, h, &kernel(), &mut out).unwrap();
            let want = naive(&src, w, h, &kernel());
            for (g, e) in out.iter().zip(&want) {
                assert!((*g as f64 - e).abs() < 1e-5, "{w}x{h}: {g} vs {e}");
            }
        }
    }

    #[test]
    fn identical_input_and_output_give_unit_gain() {
        let img = Image::from_fn(3, 30, 20, |(c, x, y)| (c + y * x) as f32 * 0.01 + 0.1);
        let mut out = img.clone();
        correct(&mut out, &img, None).unwrap();
        for (a, b) in out.as_slice().iter().zip(img.as_slice()) {
            assert!((a - b).abs() <= 1e-6 * b.abs());
        }
        // Twice the input everywhere: gain 1/2 everywhere.
        let mut doubled = Image::from_fn(3, 30, 20, |(c, x, y)| 2.0 * img.at(c, x, y));
        correct(&mut doubled, &img, None).unwrap();
        for (a, b) in doubled.as_slice().iter().zip(img.as_slice()) {
            assert!((a - b).abs() <= 1e-5 * b.abs());
        }
    }
}
