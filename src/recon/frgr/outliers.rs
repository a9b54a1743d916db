//! Gradient outlier removal (the release's first step).
//!
//! Per pixel, the luminance of the 24 neighbours in a 5 x 5 window (centre excluded,
//! reflect-101 borders) gives a mean and a sample standard deviation; when the centre's
//! luminance lies 3 or more standard deviations from that mean (or the deviation is 0), the
//! gradient pixel is replaced by the per-channel median of the 25 window values. Applied to
//! `dx` and `dy` separately; the boundary column / row that carries no information stays 0.

use rayon::prelude::*;

use super::util::{reflect, PaddedRows, LUMA};
use crate::error::Result;
use crate::image::Image;

/// Adds the luminances of one window offset's row to the sums: `sum += l`, `sum2 += l * l` in
/// f64. Called once per offset in the window's order, so that each pixel's sums add the same
/// values in the same order as a per-pixel loop would.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn add_row(sum: &mut [f64], sum2: &mut [f64], lum: &[f32]) {
    let n = sum.len();
    let (sum2, lum) = (&mut sum2[..n], &lum[..n]);
    for i in 0..n {
        let l = f64::from(lum[i]);
        sum[i] += l;
        sum2[i] += l * l;
    }
}

/// Replaces outliers of one gradient image in place; returns how many pixels were replaced,
/// or [`Error::OutOfMemory`](crate::Error::OutOfMemory) (the image is then unchanged).
///
/// The window statistics are summed row by row (vectorised over the row, borders from a
/// reflect-101 padded copy); only the pixels that fail the test look at their window again
/// for the median: the same bits as the per-pixel definition (tested), in about half its time.
pub(crate) fn remove_outliers(g: &mut Image) -> Result<u64> {
    let (w, h) = g.size();
    let n = w * h;
    if n == 0 {
        return Ok(0);
    }
    let src = g.try_clone()?;
    let src = src.as_slice();
    let lum = Image::try_par_from_fn(1, w, h, |(_, x, y)| {
        let i = y * w + x;
        LUMA[0] * src[i] + LUMA[1] * src[n + i] + LUMA[2] * src[2 * n + i]
    })?;
    let padded = PaddedRows::new(&lum, 2)?;
    // Rows in parallel, each writing its medians into the three planes' rows.
    let (r, rest) = g.as_mut_slice().split_at_mut(n);
    let (gr, b) = rest.split_at_mut(n);
    let replaced = r
        .par_chunks_mut(w)
        .zip(gr.par_chunks_mut(w))
        .zip(b.par_chunks_mut(w))
        .enumerate()
        .map(|(y, ((r, gr), b))| {
            let (mut sum, mut sum2) = (vec![0.0f64; w], vec![0.0f64; w]);
            for dy in -2..=2 {
                let qy = reflect(y as isize + dy, h);
                for dx in -2..=2 {
                    if dx != 0 || dy != 0 {
                        add_row(&mut sum, &mut sum2, padded.row(0, qy, 0, dx, w));
                    }
                }
            }
            let lum = lum.as_slice();
            let mut replaced = 0;
            for x in 0..w {
                let mean = sum[x] / 24.0;
                let var = ((sum2[x] - 24.0 * mean * mean) / 23.0).max(0.0);
                let sd = var.sqrt();
                let centre = f64::from(lum[y * w + x]);
                if sd > 0.0 && (centre - mean).abs() < 3.0 * sd {
                    continue;
                }
                let idx = |dx: isize, dy: isize| {
                    reflect(y as isize + dy, h) * w + reflect(x as isize + dx, w)
                };
                let median: [f32; 3] = std::array::from_fn(|c| {
                    let mut v = [0.0f32; 25];
                    let mut k = 0;
                    for dy in -2..=2 {
                        for dx in -2..=2 {
                            v[k] = src[c * n + idx(dx, dy)];
                            k += 1;
                        }
                    }
                    let (_, m, _) = v.select_nth_unstable_by(12, f32::total_cmp);
                    *m
                });
                let own = [r[x], gr[x], b[x]];
                if median != own {
                    [r[x], gr[x], b[x]] = median;
                    replaced += 1;
                }
            }
            replaced
        })
        .sum();
    Ok(replaced)
}

/// Zeroes the column (`dx`) or row (`dy`) that carries no information.
pub(crate) fn zero_boundary(g: &mut Image, horizontal: bool) {
    let (w, h) = g.size();
    for c in 0..3 {
        let mut p = g.plane_mut(c);
        if horizontal {
            p.column_mut(w - 1).fill(0.0);
        } else {
            p.row_mut(h - 1).fill(0.0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_spike_is_replaced_by_the_median_and_smooth_data_is_kept() {
        let (w, h) = (9, 7);
        let mut g = Image::from_fn(3, w, h, |(c, x, y)| 0.01 * (x + 2 * y + c) as f32);
        let clean = g.clone();
        g.planes_mut()[[0, 3, 4]] = 50.0;
        g.planes_mut()[[1, 3, 4]] = 50.0;
        g.planes_mut()[[2, 3, 4]] = 50.0;
        let n = remove_outliers(&mut g).unwrap();
        assert_eq!(n, 1);
        for c in 0..3 {
            // The median of a linear ramp's 5x5 window is the centre's value.
            assert!((g.at(c, 4, 3) - clean.at(c, 4, 3)).abs() < 1e-6);
        }
        assert_eq!(g, clean);
    }

    /// The per-pixel definition (the previous implementation): the flags and medians.
    fn naive(g: &Image) -> Image {
        let (w, h) = g.size();
        let mut out = g.clone();
        let lum = |x: usize, y: usize| (0..3).map(|c| LUMA[c] * g.at(c, x, y)).sum::<f32>();
        for y in 0..h {
            for x in 0..w {
                let at = |dx: isize, dy: isize| {
                    (reflect(x as isize + dx, w), reflect(y as isize + dy, h))
                };
                let (mut sum, mut sum2) = (0.0f64, 0.0f64);
                for dy in -2..=2 {
                    for dx in -2..=2 {
                        if dx != 0 || dy != 0 {
                            let (qx, qy) = at(dx, dy);
                            let l = f64::from(lum(qx, qy));
                            sum += l;
                            sum2 += l * l;
                        }
                    }
                }
                let mean = sum / 24.0;
                let sd = ((sum2 - 24.0 * mean * mean) / 23.0).max(0.0).sqrt();
                if sd > 0.0 && (f64::from(lum(x, y)) - mean).abs() < 3.0 * sd {
                    continue;
                }
                for c in 0..3 {
                    let mut v: Vec<f32> = (-2..=2)
                        .flat_map(|dy| (-2..=2).map(move |dx| (dx, dy)))
                        .map(|(dx, dy)| {
                            let (qx, qy) = at(dx, dy);
                            g.at(c, qx, qy)
                        })
                        .collect();
                    v.sort_by(f32::total_cmp);
                    out.planes_mut()[[c, y, x]] = v[12];
                }
            }
        }
        out
    }

    #[test]
    fn rows_of_sums_equal_the_per_pixel_definition() {
        // Heavy-tailed noise (some spikes, some flat black patches), odd sizes and sizes below
        // the window.
        for (w, h) in [(31, 23), (3, 2), (1, 7)] {
            let mut s = 12345u64;
            let g = Image::from_fn(3, w, h, |(_, x, y)| {
                s = s.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
                let u = (s >> 40) as f32 / (1u64 << 24) as f32;
                if x < 4 && y < 4 {
                    0.0
                } else if u > 0.97 {
                    40.0 * u
                } else {
                    u - 0.5
                }
            });
            let mut got = g.clone();
            remove_outliers(&mut got).unwrap();
            assert_eq!(got, naive(&g), "{w} x {h}");
        }
    }

    #[test]
    fn constant_data_is_untouched() {
        let mut g = Image::from_fn(3, 6, 6, |_| 0.5);
        assert_eq!(remove_outliers(&mut g).unwrap(), 0);
    }
}
