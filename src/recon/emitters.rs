//! Pixels that the gradients confirm as a bright object's edge (a lamp, a bulb) rather than
//! as a firefly.
//!
//! At a few samples per pixel both look alike in the base image and its variance: a bright
//! pixel beside dark ones, its relative noise near 1. What tells them apart is the gradient
//! across the jump. A gradient-domain renderer estimates `I(q) - I(p)` from paths shifted
//! between the two pixels; an object in view is seen from both sides, so the gradient across
//! its edge is of the jump's size. A firefly is one rare path that the shifts of the neighbours
//! do not find (random replay fails on caustics), so its gradients stay near 0. Counting a
//! bright pixel (one with a jump, below) as real when its reference is at least a third of its
//! base value and as a firefly otherwise, the rule below marks 93-100 % of the real ones on
//! new 4, 16 and 64 spp renders of the `lamps` family and on its guard frame, and 1-7 % of the
//! fireflies of `caustics` (new renders) and validation's `glass` (`docs/benchmarks.md`,
//! thirty-second session).
//!
//! The rule, on the channel sums of the base image `c` and the gradients:
//! - a **jump** from `p` to a 4-neighbour `q`: `c(p) > R (c(q) + 0.3)`, `R` the band's
//!   trimming ratio and 0.3 the three channels' [`TRIM_FLOOR`](super::band);
//! - the jump is **seen** when the gradient's estimate of `c(q) - c(p)` is at least a quarter of
//!   it in magnitude (its sign and size are noisy: a sub-pixel edge's gradient is often twice
//!   the base's jump);
//! - `p` is an **edge pixel** when it has a jump and at least three quarters of its jumps are
//!   seen, or when it has a jump and a 4-neighbour that is an edge pixel by the first test (a
//!   lamp's corner pixel, whose own gradients missed it, beside one whose did).

use rayon::prelude::*;

use crate::error::Result;
use crate::frame::Frame;
use crate::image::try_vec;

/// Fraction of a jump the gradient across it must reach for the jump to count as seen.
const SEEN: f32 = 0.25;

/// Channel-summed radiance added to the darker side of a jump (three times the band's floor).
const FLOOR: f32 = 0.3;

/// One flag per pixel (row-major): the edge pixels of `frame` at trimming ratio `ratio`.
/// Fails only with [`Error::OutOfMemory`](crate::Error::OutOfMemory).
pub(crate) fn edge_pixels(frame: &Frame, ratio: f32) -> Result<Vec<bool>> {
    let (w, h) = frame.size();
    let n = w * h;
    // Channel sums, read where needed (each is read at most five times; no planes of them).
    let sum = |img: &[f32], i: usize| img[i] + img[n + i] + img[2 * n + i];
    let (colour, dx, dy) = (
        frame.color().as_slice(),
        frame.dx().as_slice(),
        frame.dy().as_slice(),
    );
    // Per pixel: whether it has a jump, and whether it passes the first test.
    let mut jump = try_vec(n, false)?;
    let mut seen = try_vec(n, false)?;
    jump.par_chunks_mut(w.max(1))
        .zip(seen.par_chunks_mut(w.max(1)))
        .enumerate()
        .for_each(|(y, (jump, seen))| {
            for x in 0..w {
                let p = y * w + x;
                // (neighbour, the gradient's estimate of c(q) - c(p))
                let neighbours = [
                    (x + 1 < w).then(|| (p + 1, sum(dx, p))),
                    (x > 0).then(|| (p - 1, -sum(dx, p - 1))),
                    (y + 1 < h).then(|| (p + w, sum(dy, p))),
                    (y > 0).then(|| (p - w, -sum(dy, p - w))),
                ];
                let cp = sum(colour, p);
                let (mut jumps, mut confirmed) = (0u32, 0u32);
                for (q, g) in neighbours.into_iter().flatten() {
                    let cq = sum(colour, q);
                    if cp > ratio * (cq.max(0.0) + FLOOR) {
                        jumps += 1;
                        confirmed += u32::from(g.abs() >= SEEN * (cq - cp).abs());
                    }
                }
                jump[x] = jumps > 0;
                seen[x] = jumps > 0 && 4 * confirmed >= 3 * jumps;
            }
        });
    // The jump flags become the edge flags in place (a pixel reads only its own jump flag).
    let mut edge = jump;
    edge.par_chunks_mut(w.max(1))
        .enumerate()
        .for_each(|(y, edge)| {
            for (x, e) in edge.iter_mut().enumerate() {
                let p = y * w + x;
                *e = seen[p]
                    || (*e
                        && ((x + 1 < w && seen[p + 1])
                            || (x > 0 && seen[p - 1])
                            || (y + 1 < h && seen[p + w])
                            || (y > 0 && seen[p - w])));
            }
        });
    Ok(edge)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::{FrameBuilder, Layer};
    use crate::image::Image;
    use crate::validate::Policy;

    /// A frame whose base is `colour` (grey) and whose gradients are `dx`, `dy` (grey).
    fn frame(w: usize, h: usize, colour: &[f32], dx: &[f32], dy: &[f32]) -> Frame {
        let grey = |v: &[f32]| Image::from_fn(3, w, h, |(_, x, y)| v[y * w + x] / 3.0);
        FrameBuilder::new()
            .image(Layer::Color, grey(colour))
            .image(Layer::Dx, grey(dx))
            .image(Layer::Dy, grey(dy))
            .build(Policy::Strict)
            .unwrap()
    }

    #[test]
    fn a_seen_edge_is_marked_and_a_firefly_is_not() {
        // 5 x 3, dark (0.03) everywhere but (1, 1) and (3, 1), both 60.
        let (w, h) = (5, 3);
        let mut colour = vec![0.03f32; w * h];
        colour[w + 1] = 60.0;
        colour[w + 3] = 60.0;
        let (mut dx, mut dy) = (vec![0.0f32; w * h], vec![0.0f32; w * h]);
        // (1, 1): a lamp; its four gradients see it (one at a third of the jump, noisy).
        dx[w] = 60.0; // (0, 1) -> (1, 1)
        dx[w + 1] = -20.0; // (1, 1) -> (2, 1)
        dy[1] = 59.0; // (1, 0) -> (1, 1)
        dy[w + 1] = -61.0; // (1, 1) -> (1, 2)
                           // (3, 1): a firefly; only one gradient of four saw it.
        dy[w + 3] = -60.0;
        let edge = edge_pixels(&frame(w, h, &colour, &dx, &dy), 8.0).unwrap();
        let marked: Vec<usize> = (0..w * h).filter(|&p| edge[p]).collect();
        assert_eq!(marked, [w + 1]);
    }

    #[test]
    fn a_lamps_corner_joins_its_seen_neighbour() {
        // 4 x 3: a 2-pixel lamp at (1, 1) and (2, 1); only (1, 1)'s jumps are seen.
        let (w, h) = (4, 3);
        let mut colour = vec![0.0f32; w * h];
        colour[w + 1] = 90.0;
        colour[w + 2] = 90.0;
        let (mut dx, mut dy) = (vec![0.0f32; w * h], vec![0.0f32; w * h]);
        dx[w] = 90.0;
        dy[1] = 90.0;
        dy[w + 1] = -90.0;
        let edge = edge_pixels(&frame(w, h, &colour, &dx, &dy), 8.0).unwrap();
        assert!(edge[w + 1] && edge[w + 2]);
        assert_eq!(edge.iter().filter(|&&e| e).count(), 2);
        // Without the horizontal gradients (1, 1) has two of three jumps seen: not enough,
        // and then its neighbour has no marked pixel to join.
        let none = edge_pixels(&frame(w, h, &colour, &vec![0.0; w * h], &dy), 8.0).unwrap();
        assert!(none.iter().all(|&e| !e));
    }

    #[test]
    fn only_jumps_beyond_the_ratio_count() {
        // A 2x step (not a jump at ratio 8) is never marked, whatever its gradients.
        let (w, h) = (2, 1);
        let edge = edge_pixels(&frame(w, h, &[1.0, 2.0], &[1.0, 0.0], &[0.0, 0.0]), 8.0).unwrap();
        assert_eq!(edge, [false, false]);
    }
}
