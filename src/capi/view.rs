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

    /// Byte range `[start, end)` the view touches.
    fn span(&self) -> (usize, usize) {
        let last = self.last_offset().unwrap_or(0);
        (self.ptr, self.ptr + last + F32)
    }

    /// Byte addresses of every element.
    fn addresses(&self) -> impl Iterator<Item = usize> + '_ {
        (0..self.height).flat_map(move |y| {
            (0..self.width).flat_map(move |x| {
                (0..self.channels).map(move |c| {
                    self.ptr + y * self.row_stride + x * self.pixel_stride + c * self.channel_stride
                })
            })
        })
    }

    /// True when the two views share at least one element but are not the same view.
    pub(crate) fn partially_overlaps(&self, other: &View) -> bool {
        if self == other {
            return false;
        }
        let (a0, a1) = self.span();
        let (b0, b1) = other.span();
        if a1 <= b0 || b1 <= a0 {
            return false;
        }
        // The byte ranges intersect (e.g. passes interleaved in one render buffer): compare
        // element sets exactly with a bitmap over the common span.
        let lo = a0.min(b0);
        let words = (a1.max(b1) - lo) / F32 / 64 + 1;
        let mut marks = vec![0u64; words];
        for a in self.addresses() {
            let i = (a - lo) / F32;
            marks[i / 64] |= 1 << (i % 64);
        }
        other.addresses().any(|a| {
            let i = (a - lo) / F32;
            marks[i / 64] & (1 << (i % 64)) != 0
        })
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
