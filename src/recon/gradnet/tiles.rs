//! Overlapping tiles for frames larger than the configured tile, so that a network's memory
//! is bounded by the tile, not by the frame. Used by GradNet and the combiner, each with its
//! own [`Overlap`].
//!
//! GradNet's receptive field has a radius of 86 pixels (7 from the three stride-2
//! encoders, 64 from the eight 3 x 3 convolutions at 1/8 resolution, 14 from the three
//! transposed convolutions, 1 from the last convolution); measured: a change to one input pixel
//! moves outputs at most 84 pixels away. Each tile therefore reads [`GRADNET`]'s margin of 96
//! pixels beyond the part of the output it owns (its core), on every side that is not a frame
//! border, and the cores tile the frame exactly: the result equals the untiled run up to
//! floating-point reordering, with no blending needed. Tile origins are multiples of the
//! network's padding multiple (8 for GradNet) so the stride-2 grids line up with the untiled
//! run's.
//!
//! All tiles of a frame have the same size (the last one along an axis overlaps its neighbour
//! more), so ONNX Runtime's memory arena, which grows to the largest shape it has seen, stays
//! at one tile's size.

use super::prep::PAD_MULTIPLE;
use crate::error::{Error, Result};

/// How a network's tiles overlap: `margin` pixels read beyond each interior side of a core
/// (at least the receptive field's radius), origins and sizes multiples of `multiple`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Overlap {
    pub margin: usize,
    pub multiple: usize,
}

impl Overlap {
    /// The smallest tile that leaves a core: two margins and one multiple.
    pub(crate) const fn min_tile(self) -> usize {
        2 * self.margin + 2 * self.multiple
    }

    /// The fewest pixels a memory limit lowers a tile to (`max_memory_mb`; a budget set by
    /// hand may go down to [`Overlap::min_tile`]): a square of four margins a side (rounded
    /// up to the multiple), whose core is half its side, so that a tile runs at most 4x the
    /// pixels it writes. Smaller tiles save little memory for much time, as what a tile
    /// holds beyond its pixels is fixed: at the least tile, GradNet's fp32 graph at 1280 x
    /// 720 ran 96x its untiled time and the combiner's network 50x (AMD EPYC Zen 4,
    /// `docs/benchmarks.md`, fifty-ninth session), for 3 to 80 MiB less. OIDN's
    /// `maxMemoryMB` stops at three overlaps a side, for the same reason.
    pub(crate) const fn least_fitted(self) -> usize {
        let side = (4 * self.margin).div_ceil(self.multiple) * self.multiple;
        side * side
    }

    /// The budget a memory limit leaves, `most` pixels, raised to [`Overlap::least_fitted`]:
    /// for a tile, and for a whole frame (a frame within the least fitted tile runs whole,
    /// as tiled it would run as many pixels).
    pub(crate) fn fitted(self, most: usize) -> usize {
        most.max(self.least_fitted())
    }
}

/// GradNet's tiles: its receptive field (84 measured) rounded up to 8.
pub(crate) const GRADNET: Overlap = Overlap {
    margin: 96,
    multiple: PAD_MULTIPLE,
};

/// One tile along one axis: the network reads `origin..origin + size`, and writes back
/// `core_start..core_end` (all in padded coordinates).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Span {
    pub origin: usize,
    pub size: usize,
    pub core_start: usize,
    pub core_end: usize,
}

/// Splits a padded axis of length `n` (a multiple of `overlap.multiple`) into spans at most
/// `max` long.
pub(crate) fn split(n: usize, max: usize, overlap: Overlap) -> Result<Vec<Span>> {
    let Overlap { margin, multiple } = overlap;
    debug_assert_eq!(n % multiple, 0);
    if n <= max {
        return Ok(vec![Span {
            origin: 0,
            size: n,
            core_start: 0,
            core_end: n,
        }]);
    }
    if max < overlap.min_tile() {
        return Err(Error::arg(format!(
            "tile size {max} is too small: tiles need at least {} pixels \
             ({margin} of overlap on each side, for the network's receptive field)",
            overlap.min_tile()
        )));
    }
    let size = max / multiple * multiple;
    // Greedy from the start: each tile owns all but its right margin; the last one is moved
    // back to end at the border. Every tile costs the same, so the fewest tiles is the
    // cheapest layout, whatever the cores' sizes.
    let mut spans = Vec::new();
    let mut start: usize = 0;
    loop {
        let origin = start.saturating_sub(margin);
        if origin + size >= n {
            spans.push(Span {
                origin: n - size,
                size,
                core_start: start,
                core_end: n,
            });
            return Ok(spans);
        }
        let core_end = origin + size - margin;
        spans.push(Span {
            origin,
            size,
            core_start: start,
            core_end,
        });
        start = core_end;
    }
}

/// A tile: spans along y and x.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Tile {
    pub y: Span,
    pub x: Span,
}

/// Tiles covering a padded `width x height` frame: one tile when the frame has at most
/// `whole` pixels or `budget == 0`, whatever its shape (1280 x 720 and 1920 x 1080 under the
/// default 2^21: the cheapest and most exact run); otherwise the fewest-pixels layout of
/// equal tiles of at most `budget` pixels each.
///
/// Every tile costs the network time in proportion to its pixels, margins included, so the
/// layout is chosen by the pixels it runs (tiles times tile area), not by a fixed shape:
/// square tiles of a fixed side waste their margins on frames they do not divide (at
/// 3840 x 2160, 45 tiles of 640 x 640 ran 2.2x the frame's pixels; 15 tiles of 928 x 848,
/// under twice their pixels each, run 1.42x). Each candidate tile height (a multiple of the overlap's
/// `multiple`, or the whole height) takes the widest tile the budget allows, then both sides
/// shrink to the least that keeps their tile counts; the candidate running the fewest pixels
/// wins (then the fewest tiles).
pub(crate) fn layout(
    width: usize,
    height: usize,
    whole: usize,
    budget: usize,
    overlap: Overlap,
) -> Result<Vec<Tile>> {
    let (h, w) = if budget == 0 || width.saturating_mul(height) <= whole {
        (height, width)
    } else {
        shape(width, height, budget, overlap)?
    };
    let (ys, xs) = (split(height, h, overlap)?, split(width, w, overlap)?);
    Ok(ys
        .iter()
        .flat_map(|&y| xs.iter().map(move |&x| Tile { y, x }))
        .collect())
}

/// The tile `(height, width)` of [`layout`] for a frame that does not run whole.
fn shape(width: usize, height: usize, budget: usize, overlap: Overlap) -> Result<(usize, usize)> {
    let min = overlap.min_tile();
    // The least tile: `min` along an axis that is cut, the whole of one shorter than that.
    let (least_h, least_w) = (min.min(height), min.min(width));
    if budget < least_h * least_w {
        return Err(Error::arg(format!(
            "tile_pixels {budget} is too small: a tile of this frame needs at least \
             {least_w} x {least_h} = {} pixels ({} of overlap on each side, for the network's \
             receptive field)",
            least_h * least_w,
            overlap.margin
        )));
    }
    let step = overlap.multiple;
    // Tile heights to try: the whole height, and every multiple of `step` that leaves a core.
    let heights = std::iter::once(height).chain((min..height).step_by(step));
    let mut best: Option<(usize, usize, usize, usize)> = None; // (pixels, tiles, h, w)
    for h in heights {
        let widest = (budget / h / step * step).min(width);
        if widest < width && widest < min {
            continue; // too tall for the budget to leave a tile across the frame's width
        }
        let (ny, nx) = (count(height, h, overlap), count(width, widest, overlap));
        let (h, w) = (fit(height, ny, overlap), fit(width, nx, overlap));
        let (pixels, tiles) = (nx * ny * h * w, nx * ny);
        if best.is_none_or(|(p, t, _, _)| (pixels, tiles) < (p, t)) {
            best = Some((pixels, tiles, h, w));
        }
    }
    let (_, _, h, w) = best.expect("the budget holds the least tile, which is a candidate");
    Ok((h, w))
}

/// How many spans [`split`] cuts an axis of length `n` into with spans of `size`.
fn count(n: usize, size: usize, overlap: Overlap) -> usize {
    if size >= n {
        return 1;
    }
    // k spans cover `k size - 2 margin (k - 1)` pixels (their margins inside the axis).
    let core = size - 2 * overlap.margin;
    (n - 2 * overlap.margin).div_ceil(core)
}

/// The least span size (a multiple of the overlap's `multiple`, or `n`) that cuts an axis of
/// length `n` into at most `spans` spans.
fn fit(n: usize, spans: usize, overlap: Overlap) -> usize {
    if spans <= 1 {
        return n;
    }
    let Overlap { margin, multiple } = overlap;
    // From `spans size - 2 margin (spans - 1) >= n`.
    let size = (n + 2 * margin * (spans - 1)).div_ceil(spans);
    size.div_ceil(multiple) * multiple
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The least tile a memory limit lowers a budget to: four margins a side, so a tile at
    /// that size writes a core of at least a quarter of the pixels it runs.
    #[test]
    fn the_least_fitted_tile_is_four_margins_a_side() {
        assert_eq!(GRADNET.least_fitted(), 384 * 384);
        let combiner = Overlap {
            margin: 24,
            multiple: 4,
        };
        assert_eq!(combiner.least_fitted(), 96 * 96);
        let odd = Overlap {
            margin: 10,
            multiple: 8,
        };
        assert_eq!(odd.least_fitted(), 40 * 40);
        for overlap in [GRADNET, combiner, odd] {
            let side = overlap.least_fitted().isqrt();
            let core = side - 2 * overlap.margin;
            assert!(4 * core * core >= side * side, "{overlap:?}");
            assert!(overlap.least_fitted() > overlap.min_tile().pow(2));
        }
    }

    #[test]
    fn cores_partition_the_axis_with_full_margins() {
        for overlap in [
            GRADNET,
            Overlap {
                margin: 24,
                multiple: 4,
            },
        ] {
            let Overlap { margin, multiple } = overlap;
            for n in (multiple..5000).step_by(multiple) {
                for &max in &[overlap.min_tile(), 256, 512, 1000, 1024, 4096] {
                    let spans = split(n, max, overlap).unwrap();
                    let mut next = 0;
                    for (k, s) in spans.iter().enumerate() {
                        assert_eq!(s.core_start, next, "n {n} max {max}");
                        assert!(s.core_end > s.core_start);
                        assert!(s.origin + s.size <= n && s.size <= max);
                        assert_eq!(s.origin % multiple, 0);
                        assert_eq!(s.size, spans[0].size, "all tiles share one size");
                        let fewest = if n <= max {
                            1
                        } else {
                            (n - 2 * margin).div_ceil(max / multiple * multiple - 2 * margin)
                        };
                        assert!(
                            spans.len() <= fewest.max(1),
                            "n {n} max {max}: {} tiles",
                            spans.len()
                        );
                        assert!(k == 0 || s.core_start >= s.origin + margin);
                        assert!(k + 1 == spans.len() || s.core_end + margin <= s.origin + s.size);
                        next = s.core_end;
                    }
                    assert_eq!(next, n);
                }
            }
        }
    }

    #[test]
    fn small_frames_are_one_tile_and_small_budgets_are_refused() {
        let whole = 1 << 21;
        let budget = 1 << 20;
        assert_eq!(layout(720, 1280, 0, 0, GRADNET).unwrap().len(), 1);
        assert_eq!(layout(1280, 720, 0, 1280 * 720, GRADNET).unwrap().len(), 1);
        // Within the pixel budget: one tile, whatever the tile budget.
        assert_eq!(layout(1920, 1080, whole, budget, GRADNET).unwrap().len(), 1);
        assert_eq!(layout(8192, 8, whole, 640 * 640, GRADNET).unwrap().len(), 1);
        // Over it: tiles of at most the tile budget; one when the frame is within it.
        assert_eq!(layout(1280, 720, 0, 1 << 20, GRADNET).unwrap().len(), 1);
        let halves = layout(1280, 720, 0, 1280 * 720 * 3 / 5, GRADNET).unwrap();
        assert_eq!(halves.len(), 2);
        assert!(halves.iter().all(|t| t.x.size == 736 && t.y.size == 720));
        // 4K under 2^20 pixels a tile: 4 x 3 tiles of 1104 x 848, 1.35x the frame's pixels
        // (45 square tiles of 640 ran 2.2x).
        let k4 = layout(3840, 2160, whole, budget, GRADNET).unwrap();
        assert_eq!(k4.len(), 12);
        assert!(k4.iter().all(|t| t.x.size == 1104 && t.y.size == 848));
        let err = layout(1024, 1024, 0, 207 * 207, GRADNET)
            .unwrap_err()
            .to_string();
        assert!(err.contains("tile_pixels 42849 is too small"), "{err}");
        assert!(layout(1024, 1024, 0, 208 * 208, GRADNET).is_ok());
        // An axis shorter than the least tile is never cut: the least tile is that short.
        assert_eq!(layout(320, 184, 0, 232 * 184, GRADNET).unwrap().len(), 4);
        assert!(layout(320, 184, 0, 208 * 184 - 1, GRADNET).is_err());
    }

    /// Pixels a layout with tiles of `h x w` runs, by [`split`] itself.
    fn pixels(width: usize, height: usize, h: usize, w: usize, overlap: Overlap) -> usize {
        let ny = split(height, h, overlap).unwrap().len();
        let nx = split(width, w, overlap).unwrap().len();
        nx * ny * h * w
    }

    #[test]
    fn layouts_tile_the_frame_in_the_fewest_pixels() {
        let small = Overlap {
            margin: 12,
            multiple: 4,
        };
        for overlap in [GRADNET, small] {
            let (min, step) = (overlap.min_tile(), overlap.multiple);
            let sizes = [
                step,
                min - step,
                min,
                min + 5 * step,
                min + 45 * step,
                min + 200 * step,
            ];
            for &width in &sizes {
                for &height in &sizes {
                    let least = min.min(width) * min.min(height);
                    for budget in [
                        least,
                        min * (min + 3 * step),
                        3 * min * min,
                        width * height / 2,
                    ] {
                        if budget < least {
                            continue;
                        }
                        let tiles = layout(width, height, 0, budget, overlap).unwrap();
                        let (h, w) = (tiles[0].y.size, tiles[0].x.size);
                        // Equal tiles within the budget whose cores cover every pixel once.
                        assert!(h * w <= budget, "{width} x {height} budget {budget}");
                        let mut covered = vec![0u8; width * height];
                        for t in &tiles {
                            assert_eq!((t.y.size, t.x.size), (h, w));
                            for y in t.y.core_start..t.y.core_end {
                                for x in t.x.core_start..t.x.core_end {
                                    covered[y * width + x] += 1;
                                }
                            }
                        }
                        assert!(covered.iter().all(|&c| c == 1));
                        // No equal-tile layout within the budget runs fewer pixels.
                        let sides = |n: usize| {
                            std::iter::once(n)
                                .chain((min..n).step_by(step))
                                .collect::<Vec<_>>()
                        };
                        let fewest = sides(height)
                            .into_iter()
                            .flat_map(|h| sides(width).into_iter().map(move |w| (h, w)))
                            .filter(|&(h, w)| h * w <= budget)
                            .map(|(h, w)| pixels(width, height, h, w, overlap))
                            .min()
                            .unwrap();
                        assert_eq!(
                            tiles.len() * h * w,
                            fewest,
                            "{width} x {height} budget {budget}: {h} x {w}"
                        );
                    }
                }
            }
        }
    }
}
