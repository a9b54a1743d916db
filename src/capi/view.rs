//! Caller-owned image views: validation, overlap checks, reading into a frame, writing out.

use ndarray::{ArrayView3, ShapeBuilder};

use super::gdr_error::*;
use super::{err, CResult};
use crate::image::Image;

/// A strided view of caller memory: `channels` f32 values per pixel, byte strides between
/// channels, pixels and rows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct View {
    ptr: usize,
    pub(crate) width: usize,
    pub(crate) height: usize,
    pub(crate) channels: usize,
    channel_stride: usize,
    pixel_stride: usize,
    row_stride: usize,
}

/// How the caller described a view; 0 strides mean packed.
pub(crate) enum Layout {
    /// `[y][x][c]` with byte strides per pixel and per row.
    Interleaved { pixel: usize, row: usize },
    /// `[c][y][x]` with byte strides per row and per plane.
    Planar { row: usize, plane: usize },
}

const F32: usize = std::mem::size_of::<f32>();

impl View {
    /// Validates a view of `name` that must have `expected_channels` channels.
    pub(crate) fn new(
        name: &str,
        ptr: *const f32,
        width: usize,
        height: usize,
        channels: usize,
        expected_channels: usize,
        layout: Layout,
    ) -> CResult<View> {
        let bad = |msg: String| err(GDR_ERROR_INVALID_IMAGE, format!("image '{name}': {msg}"));
        if ptr.is_null() {
            return err(
                GDR_ERROR_NULL_POINTER,
                format!("image '{name}': pointer is NULL (use gdr_filter_unset_image to remove a layer)"),
            );
        }
        if width == 0 || height == 0 {
            return bad(format!(
                "size is {width} x {height}, expected at least 1 x 1"
            ));
        }
        if channels != expected_channels {
            let hint = if channels == 4 && expected_channels == 3 {
                " (for RGBA buffers pass 3 channels and a pixel stride of 16 bytes)"
            } else {
                ""
            };
            return bad(format!(
                "{channels} channels, expected {expected_channels}{hint}"
            ));
        }
        if ptr as usize % F32 != 0 {
            return bad(format!("pointer {ptr:p} is not aligned to 4 bytes"));
        }
        let (channel_stride, pixel_stride, row_stride) = match layout {
            Layout::Interleaved { pixel, row } => {
                let pixel = if pixel == 0 {
                    channels.saturating_mul(F32)
                } else {
                    pixel
                };
                let row = if row == 0 {
                    width.saturating_mul(pixel)
                } else {
                    row
                };
                (F32, pixel, row)
            }
            Layout::Planar { row, plane } => {
                let row = if row == 0 {
                    width.saturating_mul(F32)
                } else {
                    row
                };
                let plane = if plane == 0 {
                    height.saturating_mul(row)
                } else {
                    plane
                };
                (plane, F32, row)
            }
        };
        for (what, s) in [
            ("channel", channel_stride),
            ("pixel", pixel_stride),
            ("row", row_stride),
        ] {
            if s % F32 != 0 {
                return bad(format!(
                    "{what} stride is {s} bytes, expected a multiple of 4"
                ));
            }
        }
        let view = View {
            ptr: ptr as usize,
            width,
            height,
            channels,
            channel_stride,
            pixel_stride,
            row_stride,
        };
        let end = view
            .last_offset()
            .and_then(|o| o.checked_add(F32))
            .filter(|&e| e <= isize::MAX as usize && view.ptr.checked_add(e).is_some());
        if end.is_none() {
            return bad("strides and size span more memory than can be addressed".into());
        }
        // Non-overlap: sorted by stride, each stride must clear the extent of the smaller one.
        let mut dims = [
            (channel_stride, channels, "channel"),
            (pixel_stride, width, "pixel"),
            (row_stride, height, "row"),
        ];
        dims.sort_by_key(|d| d.0);
        let mut needed = F32;
        let mut prev = "element (4 bytes)";
        for (stride, extent, what) in dims {
            if extent > 1 {
                if stride < needed {
                    return bad(format!(
                        "{what} stride is {stride} bytes, smaller than the {needed} bytes of one {prev}: elements would overlap"
                    ));
                }
                needed = stride * extent;
                prev = what;
            }
        }
        Ok(view)
    }

    /// Byte offset of the last element from the pointer.
    fn last_offset(&self) -> Option<usize> {
        let a = (self.height - 1).checked_mul(self.row_stride)?;
        let b = (self.width - 1).checked_mul(self.pixel_stride)?;
        let c = (self.channels - 1).checked_mul(self.channel_stride)?;
        a.checked_add(b)?.checked_add(c)
    }

    /// The view's elements as a nested lattice (see [`Lattice`]).
    fn lattice(&self) -> Lattice {
        Lattice::new(
            self.ptr / F32,
            [
                (self.channel_stride / F32, self.channels),
                (self.pixel_stride / F32, self.width),
                (self.row_stride / F32, self.height),
            ],
        )
    }

    /// True when both views put every (x, y, c) at the same address: the same view, in place.
    /// Strides of dimensions of extent 1 are never used, so they may differ.
    fn same_elements(&self, other: &View) -> bool {
        let used = |extent: usize, stride: usize| if extent > 1 { stride } else { 0 };
        (self.ptr, self.width, self.height, self.channels)
            == (other.ptr, other.width, other.height, other.channels)
            && used(self.channels, self.channel_stride)
                == used(other.channels, other.channel_stride)
            && used(self.width, self.pixel_stride) == used(other.width, other.pixel_stride)
            && used(self.height, self.row_stride) == used(other.height, other.row_stride)
    }

    /// True when the two views share at least one element but are not the same view.
    ///
    /// Exact, in O(1) memory: interval arithmetic on the nested strides and a Chinese-remainder
    /// test on arithmetic progressions (see [`Lattice::meets`]); passes interleaved in one
    /// render buffer, whose byte ranges intersect, cost a few operations per row at most.
    pub(crate) fn partially_overlaps(&self, other: &View) -> bool {
        !self.same_elements(other) && self.lattice().meets(&other.lattice(), &mut Crt::default())
    }

    /// The caller's memory as an ndarray view of shape `(height, width, channels)`.
    ///
    /// # Safety
    /// The memory must be readable for the whole view during `'a` (the caller's promise).
    pub(crate) unsafe fn array<'a>(&self) -> ArrayView3<'a, f32> {
        let shape = (self.height, self.width, self.channels).strides((
            self.row_stride / F32,
            self.pixel_stride / F32,
            self.channel_stride / F32,
        ));
        // SAFETY: non-null, aligned, in-bounds and addressable were checked in `new`.
        ArrayView3::from_shape_ptr(shape, self.ptr as *const f32)
    }

    /// Writes a planar 3-channel image of the view's size through the view.
    ///
    /// # Safety
    /// The memory must be writable for the whole view and not borrowed elsewhere.
    pub(crate) unsafe fn write(&self, image: &Image) {
        let (w, h) = (self.width, self.height);
        let data = image.as_slice();
        let plane = w * h;
        let base = self.ptr as *mut u8;
        for y in 0..h {
            for x in 0..w {
                let px = base.add(y * self.row_stride + x * self.pixel_stride);
                for c in 0..self.channels {
                    // SAFETY: within the span checked in `new`, aligned, non-overlapping.
                    px.add(c * self.channel_stride)
                        .cast::<f32>()
                        .write(data[c * plane + y * w + x]);
                }
            }
        }
    }
}

/// The elements of a view in 4-byte units: `base + sum(i_k * stride_k)` for `0 <= i_k < count_k`,
/// dimensions sorted by stride, extents of 1 dropped, contiguous neighbours merged. `View::new`
/// guarantees nesting: each stride is at least the span of the dimensions below it, so the
/// blocks of the outermost dimension are disjoint intervals in increasing order.
#[derive(Clone, Copy, Debug)]
struct Lattice {
    base: u128,
    /// `(stride, count)`, ascending strides, counts of at least 2; `len` of them are used.
    dims: [(u128, u128); 3],
    len: usize,
}

impl Lattice {
    fn new(base: usize, dims: [(usize, usize); 3]) -> Lattice {
        let mut sorted: Vec<(u128, u128)> = dims
            .iter()
            .filter(|d| d.1 > 1)
            .map(|&(s, n)| (s as u128, n as u128))
            .collect();
        sorted.sort_unstable();
        let mut out = Lattice {
            base: base as u128,
            dims: [(0, 0); 3],
            len: 0,
        };
        for (stride, count) in sorted {
            match out.len.checked_sub(1).map(|i| &mut out.dims[i]) {
                // Contiguous continuation of the dimension below: one longer dimension.
                Some(last) if last.0 * last.1 == stride => last.1 *= count,
                _ => {
                    out.dims[out.len] = (stride, count);
                    out.len += 1;
                }
            }
        }
        out
    }

    /// Span (last offset + 1) of the lowest `levels` dimensions.
    fn extent(&self, levels: usize) -> u128 {
        1 + self.dims[..levels]
            .iter()
            .map(|&(s, n)| s * (n - 1))
            .sum::<u128>()
    }

    /// First and last element.
    fn bounds(&self) -> (u128, u128) {
        (self.base, self.base + self.extent(self.len) - 1)
    }

    /// Block `k` of the outermost dimension: the lattice of the dimensions below it.
    fn outer_block(&self, k: u128) -> Lattice {
        let (stride, _) = self.dims[self.len - 1];
        Lattice {
            base: self.base + k * stride,
            len: self.len - 1,
            ..*self
        }
    }

    /// Slice `j` of the innermost dimension: the lattice of the dimensions above it.
    fn inner_slice(&self, j: u128) -> Lattice {
        let mut dims = [(0, 0); 3];
        dims[..self.len - 1].copy_from_slice(&self.dims[1..self.len]);
        Lattice {
            base: self.base + j * self.dims[0].0,
            dims,
            len: self.len - 1,
        }
    }

    /// The outermost blocks that intersect `[lo, hi]`, as an inclusive index range (empty
    /// when `first > last`).
    fn outer_blocks_within(&self, lo: u128, hi: u128) -> (u128, u128) {
        let (stride, count) = self.dims[self.len - 1];
        let below = self.extent(self.len - 1);
        // Block k covers [base + k*stride, base + k*stride + below - 1].
        let first = (lo + 1).saturating_sub(self.base + below).div_ceil(stride);
        let last = match hi.checked_sub(self.base) {
            Some(d) => (d / stride).min(count - 1),
            None => return (1, 0),
        };
        (first, last)
    }

    /// True when the two lattices share an element. Splits one of them (its outermost blocks
    /// that meet the other's range, or its innermost slices, whichever are fewer) until both
    /// are arithmetic progressions, which [`Crt`] compares in O(1). Memory: the recursion,
    /// at most 4 deep.
    fn meets(&self, other: &Lattice, crt: &mut Crt) -> bool {
        let (a0, a1) = self.bounds();
        let (b0, b1) = other.bounds();
        if a1 < b0 || b1 < a0 {
            return false;
        }
        if self.len <= 1 && other.len <= 1 {
            return crt.progressions_meet(self.progression(), other.progression());
        }
        // Candidate splits: (cost, which lattice, outer?).
        let mut best: Option<(u128, bool, bool)> = None;
        for (is_self, x, (lo, hi)) in [(true, self, (b0, b1)), (false, other, (a0, a1))] {
            // Progressions are compared whole: only lattices of 2 or more dimensions split.
            if x.len < 2 {
                continue;
            }
            let (first, last) = x.outer_blocks_within(lo, hi);
            let outer = (last + 1).saturating_sub(first);
            for (cost, outer_split) in [(outer, true), (x.dims[0].1, false)] {
                if best.is_none_or(|b| cost < b.0) {
                    best = Some((cost, is_self, outer_split));
                }
            }
        }
        let Some((_, split_self, outer)) = best else {
            return crt.progressions_meet(self.progression(), other.progression());
        };
        let (x, y) = if split_self {
            (self, other)
        } else {
            (other, self)
        };
        let (y0, y1) = y.bounds();
        if outer {
            let (first, last) = x.outer_blocks_within(y0, y1);
            let mut k = first;
            while k <= last {
                if x.outer_block(k).meets(y, crt) {
                    return true;
                }
                k += 1;
            }
            false
        } else {
            (0..x.dims[0].1).any(|j| x.inner_slice(j).meets(y, crt))
        }
    }

    /// A lattice of at most one dimension as `(first, stride, count)`.
    fn progression(&self) -> (u128, u128, u128) {
        match self.len {
            0 => (self.base, 1, 1),
            _ => (self.base, self.dims[0].0, self.dims[0].1),
        }
    }
}

/// Intersection of two arithmetic progressions by the Chinese remainder theorem, caching the
/// modular inverse of the last pair of strides (a layout repeats the same pair row after row).
#[derive(Default)]
struct Crt {
    /// `(s, t, gcd, inverse of s/g modulo t/g)`.
    last: Option<(u128, u128, u128, u128)>,
}

impl Crt {
    /// True when `{a + i*s : i < n}` and `{b + j*t : j < m}` share a value.
    fn progressions_meet(
        &mut self,
        (a, s, n): (u128, u128, u128),
        (b, t, m): (u128, u128, u128),
    ) -> bool {
        let lo = a.max(b);
        let hi = (a + s * (n - 1)).min(b + t * (m - 1));
        if lo > hi {
            return false;
        }
        let on = |x: u128, first: u128, stride: u128, count: u128| {
            x >= first && (x - first) % stride == 0 && (x - first) / stride < count
        };
        if n == 1 {
            return on(a, b, t, m);
        }
        if m == 1 {
            return on(b, a, s, n);
        }
        if s == t {
            return a.abs_diff(b) % s == 0;
        }
        let (g, inv) = match self.last {
            Some((ls, lt, g, inv)) if (ls, lt) == (s, t) => (g, inv),
            _ => {
                let g = gcd(s, t);
                let inv = mod_inverse((s / g) % (t / g), t / g);
                self.last = Some((s, t, g, inv));
                (g, inv)
            }
        };
        let diff = if b >= a { b - a } else { t - (a - b) % t };
        if diff % g != 0 {
            return false;
        }
        // a + s*k = b (mod t)  <=>  k = (diff/g) * inv (mod t/g); the common values are
        // x0 + L*i with L = lcm(s, t).
        let tg = t / g;
        let k = mul_mod((diff / g) % tg, inv, tg);
        let x0 = a + s * k;
        let period = s * tg;
        // The smallest x0 + period*i >= lo (x0 >= a, and a <= lo).
        let x = if x0 >= lo {
            x0
        } else {
            x0 + (lo - x0).div_ceil(period) * period
        };
        x <= hi
    }
}

fn gcd(mut a: u128, mut b: u128) -> u128 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

/// `a * b mod m` for `a, b < m` without overflow (m < 2^64 here, so the product fits).
fn mul_mod(a: u128, b: u128, m: u128) -> u128 {
    (a * b) % m
}

/// The inverse of `a` modulo `m` (`a` and `m` coprime; 0 when `m == 1`).
fn mod_inverse(a: u128, m: u128) -> u128 {
    if m == 1 {
        return 0;
    }
    let (mut old_r, mut r) = (a as i128, m as i128);
    let (mut old_s, mut s) = (1i128, 0i128);
    while r != 0 {
        let q = old_r / r;
        (old_r, r) = (r, old_r - q * r);
        (old_s, s) = (s, old_s - q * s);
    }
    old_s.rem_euclid(m as i128) as u128
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashSet;
    use std::time::Instant;

    /// Byte addresses of every element (the brute-force reference).
    fn addresses(v: &View) -> HashSet<usize> {
        let mut set = HashSet::new();
        for y in 0..v.height {
            for x in 0..v.width {
                for c in 0..v.channels {
                    set.insert(
                        v.ptr + y * v.row_stride + x * v.pixel_stride + c * v.channel_stride,
                    );
                }
            }
        }
        set
    }

    /// The old check: equal descriptions are in place, else any shared element overlaps.
    fn brute_force(a: &View, b: &View) -> bool {
        !a.same_elements(b) && !addresses(a).is_disjoint(&addresses(b))
    }

    fn view(ptr: usize, w: usize, h: usize, c: usize, layout: Layout) -> CResult<View> {
        View::new("test", ptr as *const f32, w, h, c, c, layout)
    }

    /// A small deterministic generator (xorshift).
    struct Rng(u64);
    impl Rng {
        fn below(&mut self, n: usize) -> usize {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 % n as u64) as usize
        }
    }

    fn random_view(rng: &mut Rng) -> Option<View> {
        let base = 0x10000 + 4 * rng.below(64);
        let (w, h) = (1 + rng.below(6), 1 + rng.below(6));
        let c = if rng.below(3) == 0 { 1 } else { 3 };
        // Strides: packed (0), or small multiples of 4 that interleave or pad.
        let planar = rng.below(2) == 0;
        let mut stride = || match rng.below(4) {
            0 => 0,
            _ => 4 * (1 + rng.below(40)),
        };
        let layout = if !planar {
            Layout::Interleaved {
                pixel: stride(),
                row: stride(),
            }
        } else {
            Layout::Planar {
                row: stride(),
                plane: stride(),
            }
        };
        view(base, w, h, c, layout).ok()
    }

    #[test]
    fn overlap_equals_the_brute_force_on_random_layouts() {
        let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
        let (mut pairs, mut overlapping) = (0, 0);
        while pairs < 200_000 {
            let (Some(a), Some(b)) = (random_view(&mut rng), random_view(&mut rng)) else {
                continue;
            };
            // Same size, as commit requires, half of the time.
            let b = if rng.below(2) == 0 {
                match view(
                    b.ptr,
                    a.width,
                    a.height,
                    a.channels,
                    Layout::Interleaved {
                        pixel: b.pixel_stride.max(a.channels * 4),
                        row: 0,
                    },
                ) {
                    Ok(v) => v,
                    Err(_) => continue,
                }
            } else {
                b
            };
            let expected = brute_force(&a, &b);
            assert_eq!(a.partially_overlaps(&b), expected, "{a:?} vs {b:?}");
            assert_eq!(b.partially_overlaps(&a), expected, "{b:?} vs {a:?}");
            pairs += 1;
            overlapping += usize::from(expected);
        }
        // Both answers are well represented.
        assert!(
            overlapping > pairs / 10 && overlapping < pairs * 9 / 10,
            "{overlapping} of {pairs}"
        );
    }

    #[test]
    fn interleaved_passes_in_one_buffer() {
        // Four RGB passes per pixel (48-byte pixels), rows padded: disjoint however offset.
        let (w, h, row) = (7, 5, 48 * 7 + 16);
        let pass = |k: usize| {
            view(
                0x1000 + 12 * k,
                w,
                h,
                3,
                Layout::Interleaved { pixel: 48, row },
            )
            .unwrap()
        };
        for i in 0..4 {
            for j in 0..4 {
                assert!(!pass(i).partially_overlaps(&pass(j)));
                assert!(!brute_force(&pass(i), &pass(j)));
            }
        }
        // Shifted by one float: shares elements.
        let shifted = view(0x1004, w, h, 3, Layout::Interleaved { pixel: 48, row }).unwrap();
        assert!(shifted.partially_overlaps(&pass(0)) && brute_force(&shifted, &pass(0)));
        // The same view with an unused row stride (height 1) is in place, not an overlap.
        let a = view(0x1000, w, 1, 3, Layout::Interleaved { pixel: 48, row: 0 }).unwrap();
        let b = view(
            0x1000,
            w,
            1,
            3,
            Layout::Interleaved {
                pixel: 48,
                row: 4096,
            },
        )
        .unwrap();
        assert!(!a.partially_overlaps(&b));
    }

    #[test]
    fn huge_views_are_checked_without_allocating() {
        let t = Instant::now();
        // Two tiny views 512 GiB apart (the old bitmap spanned the gap).
        let a = view(0x1000, 2, 2, 3, Layout::Interleaved { pixel: 0, row: 0 }).unwrap();
        let far = view(
            0x1000 + (512 << 30),
            2,
            2,
            3,
            Layout::Interleaved { pixel: 0, row: 0 },
        )
        .unwrap();
        assert!(!a.partially_overlaps(&far));
        // Views spanning addresses near the top of the address space.
        let top = (usize::MAX / 2) & !3;
        let a = view(
            top,
            4,
            4,
            3,
            Layout::Planar {
                row: 1 << 40,
                plane: 1 << 50,
            },
        )
        .unwrap();
        let b = view(
            top + 4,
            4,
            4,
            3,
            Layout::Planar {
                row: 1 << 40,
                plane: 1 << 50,
            },
        )
        .unwrap();
        assert!(a.partially_overlaps(&b));
        let b = view(
            top + 16,
            4,
            4,
            3,
            Layout::Planar {
                row: 1 << 40,
                plane: 1 << 50,
            },
        )
        .unwrap();
        assert!(!a.partially_overlaps(&b));
        // 100000 x 100000 RGB passes interleaved in one buffer (24-byte pixels, padded rows),
        // and a 4K frame's passes in one buffer (48-byte pixels, packed rows).
        for (w, h, pixel, row) in [
            (100_000, 100_000, 24, 24 * 100_000 + 64),
            (3840, 2160, 48, 0),
        ] {
            let color = view(0x1000, w, h, 3, Layout::Interleaved { pixel, row }).unwrap();
            let output = view(0x1000 + 12, w, h, 3, Layout::Interleaved { pixel, row }).unwrap();
            assert!(!color.partially_overlaps(&output));
            let off = view(0x1000 + 8, w, h, 3, Layout::Interleaved { pixel, row }).unwrap();
            assert!(color.partially_overlaps(&off));
        }
        // Column-major against row-major, padded, in one region: a few thousand steps.
        let cols = view(0x1000, 1000, 1000, 1, Layout::Planar { row: 4, plane: 0 });
        assert!(cols.is_err()); // a row stride of 4 with 1000 pixels overlaps itself
        let cols = view(
            0x1000,
            1000,
            1000,
            1,
            Layout::Interleaved {
                pixel: 4 * 1001,
                row: 4,
            },
        )
        .unwrap();
        let rows = view(
            0x1000 + 4 * 1000 * 1001,
            1000,
            1000,
            1,
            Layout::Interleaved {
                pixel: 4,
                row: 4 * 1001,
            },
        )
        .unwrap();
        let rows_inside = view(
            0x1000 + 4 * 999,
            1000,
            1000,
            1,
            Layout::Interleaved {
                pixel: 4,
                row: 4 * 1001,
            },
        )
        .unwrap();
        assert!(!cols.partially_overlaps(&rows));
        assert_eq!(
            cols.partially_overlaps(&rows_inside),
            brute_force(&cols, &rows_inside)
        );
        let elapsed = t.elapsed();
        assert!(elapsed.as_secs_f64() < 1.0, "{elapsed:?}");
    }
}
