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
/// `whole` pixels or `max == 0`, whatever its shape (1280 x 720 under the default 2^20: the
/// cheapest and most exact run); square tiles of side `max` otherwise.
pub(crate) fn layout(
    width: usize,
    height: usize,
    whole: usize,
    max: usize,
    overlap: Overlap,
) -> Result<Vec<Tile>> {
    let max = if max == 0 || width.saturating_mul(height) <= whole {
        usize::MAX
    } else {
        max
    };
    let (ys, xs) = (split(height, max, overlap)?, split(width, max, overlap)?);
    Ok(ys
        .iter()
        .flat_map(|&y| xs.iter().map(move |&x| Tile { y, x }))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

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
    fn small_frames_are_one_tile_and_small_tiles_are_refused() {
        let whole = 1 << 20;
        assert_eq!(layout(720, 1280, 0, 0, GRADNET).unwrap().len(), 1);
        assert_eq!(layout(1280, 720, 0, 1280, GRADNET).unwrap().len(), 1);
        // Within the pixel budget: one tile even though 1280 > 640.
        assert_eq!(layout(1280, 720, whole, 640, GRADNET).unwrap().len(), 1);
        assert_eq!(layout(8192, 8, whole, 640, GRADNET).unwrap().len(), 1);
        // Over it: tiles, even for a frame smaller than a tile's area.
        assert_eq!(
            layout(1280, 720, 1280 * 720 - 1, 1024, GRADNET)
                .unwrap()
                .len(),
            2
        );
        // 4K: square tiles of 640, and of 1024.
        let k4 = layout(3840, 2160, whole, 640, GRADNET).unwrap();
        assert!(k4.iter().all(|t| t.x.size == 640 && t.y.size == 640));
        assert_eq!(k4.len(), 9 * 5);
        assert_eq!(
            layout(3840, 2160, whole, 1024, GRADNET).unwrap().len(),
            5 * 3
        );
        let err = layout(1024, 1024, 0, 100, GRADNET).unwrap_err().to_string();
        assert!(err.contains("too small"), "{err}");
    }
}
