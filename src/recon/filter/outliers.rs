//! Gradient outlier removal (the release's first step).
//!
//! Per pixel, the luminance of the 24 neighbours in a 5 x 5 window (centre excluded,
//! reflect-101 borders) gives a mean and a sample standard deviation; when the centre's
//! luminance lies 3 or more standard deviations from that mean (or the deviation is 0), the
//! gradient pixel is replaced by the per-channel median of the 25 window values. Applied to
//! `dx` and `dy` separately; the boundary column / row that carries no information stays 0.

use rayon::prelude::*;

use super::util::{reflect, LUMA};
use crate::image::Image;

/// Replaces outliers of one gradient image in place; returns how many pixels were replaced.
pub(crate) fn remove_outliers(g: &mut Image) -> u64 {
    let (w, h) = g.size();
    let n = w * h;
    let src = g.as_slice().to_vec();
    let lum: Vec<f32> = (0..n)
        .map(|i| LUMA[0] * src[i] + LUMA[1] * src[n + i] + LUMA[2] * src[2 * n + i])
        .collect();
    let replaced: Vec<(usize, [f32; 3])> = (0..h)
        .into_par_iter()
        .flat_map_iter(|y| {
            let (src, lum) = (&src, &lum);
            (0..w).filter_map(move |x| {
                let idx = |dx: isize, dy: isize| {
                    reflect(y as isize + dy, h) * w + reflect(x as isize + dx, w)
                };
                let (mut sum, mut sum2) = (0.0f64, 0.0f64);
                for dy in -2..=2 {
                    for dx in -2..=2 {
                        if dx == 0 && dy == 0 {
                            continue;
                        }
                        let l = f64::from(lum[idx(dx, dy)]);
                        sum += l;
                        sum2 += l * l;
                    }
                }
                let mean = sum / 24.0;
                let var = ((sum2 - 24.0 * mean * mean) / 23.0).max(0.0);
                let sd = var.sqrt();
                let centre = f64::from(lum[y * w + x]);
                if sd > 0.0 && (centre - mean).abs() < 3.0 * sd {
                    return None;
                }
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
                (median
                    .iter()
                    .zip(0..3)
                    .any(|(&m, c)| m != src[c * n + y * w + x]))
                .then_some((y * w + x, median))
            })
        })
        .collect();
    let out = g.as_mut_slice();
    for &(i, m) in &replaced {
        for c in 0..3 {
            out[c * n + i] = m[c];
        }
    }
    replaced.len() as u64
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
        let mut g = Image::from_fn(3, h, w, |(c, y, x)| 0.01 * (x + 2 * y + c) as f32);
        let clean = g.clone();
        g.planes_mut()[[0, 3, 4]] = 50.0;
        g.planes_mut()[[1, 3, 4]] = 50.0;
        g.planes_mut()[[2, 3, 4]] = 50.0;
        let n = remove_outliers(&mut g);
        assert_eq!(n, 1);
        for c in 0..3 {
            // The median of a linear ramp's 5x5 window is the centre's value.
            assert!((g.at(c, 4, 3) - clean.at(c, 4, 3)).abs() < 1e-6);
        }
        assert_eq!(g, clean);
    }

    #[test]
    fn constant_data_is_untouched() {
        let mut g = Image::from_fn(3, 6, 6, |_| 0.5);
        assert_eq!(remove_outliers(&mut g), 0);
    }
}
