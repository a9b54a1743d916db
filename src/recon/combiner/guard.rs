//! The combiner's mean guard: an L1 candidate is dropped (its weight set to 0, the others
//! sharing the whole) at pixels where its mean over the [`WINDOW`] x [`WINDOW`] window around
//! the pixel departs from the prior's by more than `tolerance` times the prior's (+ the
//! combiner's radiance floor). Channels are averaged; windows are clamped at the frame's edges
//! (edge pixels repeated).
//!
//! Why: a reconstruction that follows the gradients keeps a region's energy where the
//! gradients carry it. Where they miss it (caustics seen through glass, lit by paths a shift
//! cannot follow) the weak L1 candidate loses or moves it, and the network, which sees the base
//! image agree with that candidate between the region's fireflies, trusted it there (the
//! validation `glass` frames, `docs/benchmarks.md`, twenty-first session). The prior, a
//! denoiser's output, spreads the fireflies' energy instead and keeps it.
//!
//! `combiner.py`'s `dropped` is the reference: the same sums in the same order in f64 (the
//! window's rows, then its columns), so that the two agree on every pixel.

use rayon::prelude::*;

use crate::error::Result;
use crate::image::{try_vec, Image};
use crate::progress::Progress;

/// Side of the window the local means are taken over (`combiner.py`'s `MEAN_WINDOW`).
pub(crate) const WINDOW: usize = 9;

/// Rows of the mask one worker fills at a time (each reads the window's extra rows too).
const BAND: usize = 64;

/// Per pixel of `prior`'s size, bit `k` set where `candidates[k]` is dropped; all clear when
/// `tolerance` is 0. `floor` is the radiance floor added to the prior's local mean. Stops with
/// `Error::Cancelled` at the next band once `progress` is cancelled (a 4K frame takes about
/// 0.25 s on two cores).
pub(crate) fn dropped(
    prior: &Image,
    candidates: [&Image; 2],
    tolerance: f32,
    floor: f32,
    progress: &Progress,
) -> Result<Vec<u8>> {
    let (w, h) = prior.size();
    let mut mask = try_vec(w * h, 0u8)?;
    if tolerance <= 0.0 || w == 0 || h == 0 {
        return Ok(mask);
    }
    let images = [prior, candidates[0], candidates[1]];
    let (tolerance, floor) = (f64::from(tolerance), f64::from(floor));
    let r = WINDOW / 2;
    let area = (WINDOW * WINDOW) as f64;
    mask.par_chunks_mut(BAND * w)
        .enumerate()
        .try_for_each(|(band, out)| -> Result<()> {
            progress.check()?;
            let y0 = band * BAND;
            let rows = out.len() / w;
            // Window sums along each row, for the band's rows and the window's rows around
            // them (clamped), of every image's channel mean.
            let span = rows + 2 * r;
            let mut across = try_vec(3 * span * w, 0.0f64)?;
            let mut mean = vec![0.0f64; w];
            for (i, image) in images.iter().enumerate() {
                let planes = image.as_slice();
                for s in 0..span {
                    let y = (y0 + s).saturating_sub(r).min(h - 1);
                    for (x, m) in mean.iter_mut().enumerate() {
                        let at = |c: usize| f64::from(planes[c * w * h + y * w + x]);
                        *m = (at(0) + at(1) + at(2)) / 3.0;
                    }
                    let row = &mut across[(i * span + s) * w..(i * span + s + 1) * w];
                    for (x, sum) in row.iter_mut().enumerate() {
                        *sum = (0..WINDOW)
                            .map(|j| mean[(x + j).saturating_sub(r).min(w - 1)])
                            .sum();
                    }
                }
            }
            // Then down each column, and the verdict.
            let local = |i: usize, ty: usize, x: usize| -> f64 {
                (0..WINDOW)
                    .map(|j| across[(i * span + ty + j) * w + x])
                    .sum::<f64>()
                    / area
            };
            for ty in 0..rows {
                for x in 0..w {
                    let p = local(0, ty, x);
                    let limit = tolerance * (p + floor);
                    let mut bits = 0u8;
                    for k in 0..2 {
                        if (local(k + 1, ty, x) - p).abs() > limit {
                            bits |= 1 << k;
                        }
                    }
                    out[ty * w + x] = bits;
                }
            }
            Ok(())
        })?;
    Ok(mask)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn constant(w: usize, h: usize, v: f32) -> Image {
        let mut img = Image::try_zeros(3, w, h).unwrap();
        img.as_mut_slice().fill(v);
        img
    }

    /// The window mean by its definition, clamped indices, for one pixel.
    fn direct(img: &Image, x: usize, y: usize) -> f64 {
        let (w, h) = img.size();
        let r = (WINDOW / 2) as isize;
        let mut sum = 0.0;
        for dy in -r..=r {
            for dx in -r..=r {
                let yy = (y as isize + dy).clamp(0, h as isize - 1) as usize;
                let xx = (x as isize + dx).clamp(0, w as isize - 1) as usize;
                let px = |c: usize| f64::from(img.as_slice()[c * w * h + yy * w + xx]);
                sum += (px(0) + px(1) + px(2)) / 3.0;
            }
        }
        sum / (WINDOW * WINDOW) as f64
    }

    #[test]
    fn a_candidate_that_loses_a_regions_energy_is_dropped_there_only() {
        let (w, h) = (40, 150); // more than two bands, a band boundary inside the dark block
        let prior = constant(w, h, 1.0);
        let strong = constant(w, h, 1.0);
        let mut weak = constant(w, h, 1.0);
        for c in 0..3 {
            for y in 60..72 {
                for x in 10..22 {
                    weak.as_mut_slice()[c * w * h + y * w + x] = 0.2;
                }
            }
        }
        let mask = dropped(&prior, [&strong, &weak], 0.4, 0.01, &Progress::none()).unwrap();
        for y in 0..h {
            for x in 0..w {
                let departs = (direct(&weak, x, y) - 1.0).abs() > 0.4 * 1.01;
                assert_eq!(mask[y * w + x], u8::from(departs) << 1, "pixel {x}, {y}");
            }
        }
        assert_eq!(mask[66 * w + 16], 2, "the block's centre");
        assert_eq!(mask[5 * w + 5], 0);
        let off = dropped(&prior, [&strong, &weak], 0.0, 0.01, &Progress::none()).unwrap();
        assert!(off.iter().all(|&b| b == 0), "0 turns the guard off");
    }

    #[test]
    fn windows_are_clamped_at_the_edges() {
        // A frame smaller than the window: every window covers it all, edge pixels repeated.
        let (w, h) = (5, 3);
        let prior = constant(w, h, 1.0);
        let mut strong = constant(w, h, 1.0);
        strong.as_mut_slice()[0] = 10.0; // red, top-left corner: repeated into many windows
        let mask = dropped(&prior, [&strong, &prior], 0.4, 0.01, &Progress::none()).unwrap();
        for y in 0..h {
            for x in 0..w {
                let departs = (direct(&strong, x, y) - 1.0).abs() > 0.4 * 1.01;
                assert_eq!(mask[y * w + x], u8::from(departs), "pixel {x}, {y}");
            }
        }
        assert_eq!(mask[0], 1);
        assert_eq!(mask[w * h - 1], 0);
    }
}
