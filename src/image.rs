//! Planar f32 images, the storage every layer of a frame and every output uses.
//!
//! An [`Image`] is an `ndarray` of shape `(channels, height, width)` in standard (row-major)
//! layout: each channel is one contiguous plane, rows top to bottom, `y` growing downward and
//! `x` to the right. Its API takes sizes and positions as everything in gdrecon does
//! (`docs/CONVENTIONS.md`): width before height, `x` before `y`; only the storage, reached
//! through [`Image::planes`], is indexed `[c, y, x]`. Planar storage keeps the per-channel solvers (DCT, conjugate gradients,
//! filters) on unit-stride rows; interleaved caller buffers are copied in once at validation.

use ndarray::{Array3, ArrayView2, ArrayView3, ArrayViewMut2, Axis};
use rayon::prelude::*;

use crate::error::{Error, Result};

/// A planar image: `channels` planes of `height` x `width` f32 values.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    planes: Array3<f32>,
}

impl Image {
    /// An image of zeros, `width` x `height`.
    pub fn zeros(channels: usize, width: usize, height: usize) -> Self {
        Image {
            planes: Array3::zeros((channels, height, width)),
        }
    }

    /// An image of zeros, `width` x `height`, or [`Error::OutOfMemory`] when the allocation
    /// fails (or its size overflows) instead of aborting the process.
    pub fn try_zeros(channels: usize, width: usize, height: usize) -> Result<Self> {
        let len = channels
            .checked_mul(width)
            .and_then(|n| n.checked_mul(height))
            .ok_or_else(|| too_large(channels, width, height))?;
        // A zeroed allocation, not a fill: large ones get fresh pages from the system, already
        // zero, which the threads that first write them fault in (filled here, serially, a
        // 22-channel 720p bundle's 81 MB of planes cost the CLI's read a fifth of its time).
        let data = try_zeroed_vec(len).map_err(|_| too_large(channels, width, height))?;
        Ok(Image {
            planes: Array3::from_shape_vec((channels, height, width), data)
                .expect("the length is the shape's"),
        })
    }

    /// A copy, or [`Error::OutOfMemory`] when it cannot be allocated (`clone` aborts instead).
    pub fn try_clone(&self) -> Result<Self> {
        let (w, h) = self.size();
        let mut copy = Image::try_zeros(self.channels(), w, h)?;
        copy.as_mut_slice().copy_from_slice(self.as_slice());
        Ok(copy)
    }

    /// Wraps an array of shape `(channels, height, width)`; it is made contiguous if needed.
    pub fn from_planes(planes: Array3<f32>) -> Self {
        let planes = if planes.is_standard_layout() {
            planes
        } else {
            planes.as_standard_layout().into_owned()
        };
        Image { planes }
    }

    /// Builds a `width` x `height` image from a closure `f((channel, x, y))`, called in
    /// storage order (channel by channel, row by row).
    pub fn from_fn(
        channels: usize,
        width: usize,
        height: usize,
        mut f: impl FnMut((usize, usize, usize)) -> f32,
    ) -> Self {
        Image {
            planes: Array3::from_shape_fn((channels, height, width), |(c, y, x)| f((c, x, y))),
        }
    }

    /// [`Image::from_fn`] with the rows filled in parallel (`f` must not depend on the order).
    pub fn par_from_fn(
        channels: usize,
        width: usize,
        height: usize,
        f: impl Fn((usize, usize, usize)) -> f32 + Sync,
    ) -> Self {
        let mut img = Image::zeros(channels, width, height);
        img.par_fill(f);
        img
    }

    /// [`Image::par_from_fn`], or [`Error::OutOfMemory`] when the image cannot be allocated.
    pub(crate) fn try_par_from_fn(
        channels: usize,
        width: usize,
        height: usize,
        f: impl Fn((usize, usize, usize)) -> f32 + Sync,
    ) -> Result<Self> {
        let mut img = Image::try_zeros(channels, width, height)?;
        img.par_fill(f);
        Ok(img)
    }

    /// [`Image::try_par_from_fn`] a row at a time: `f(channel, y, row)` fills the row (zeros on
    /// entry), rows in parallel; for kernels that read whole rows of their inputs as slices.
    pub(crate) fn try_par_from_rows(
        channels: usize,
        width: usize,
        height: usize,
        f: impl Fn(usize, usize, &mut [f32]) + Sync,
    ) -> Result<Self> {
        let mut img = Image::try_zeros(channels, width, height)?;
        img.par_rows(f);
        Ok(img)
    }

    /// Sets every value to `f((channel, x, y))`, rows in parallel.
    fn par_fill(&mut self, f: impl Fn((usize, usize, usize)) -> f32 + Sync) {
        self.par_rows(|c, y, row| {
            for (x, v) in row.iter_mut().enumerate() {
                *v = f((c, x, y));
            }
        });
    }

    /// Calls `f(channel, y, row)` on every row, rows in parallel.
    fn par_rows(&mut self, f: impl Fn(usize, usize, &mut [f32]) + Sync) {
        let (width, height) = self.size();
        if width > 0 {
            self.as_mut_slice()
                .par_chunks_mut(width)
                .enumerate()
                .for_each(|(r, row)| f(r / height, r % height, row));
        }
    }

    /// Copies an interleaved-or-strided view of shape `(height, width, channels)` (the natural
    /// shape of a renderer's RGB buffer) into planar storage.
    pub fn from_hwc(view: ArrayView3<'_, f32>) -> Self {
        let planes = view
            .permuted_axes([2, 0, 1])
            .as_standard_layout()
            .into_owned();
        Image { planes }
    }

    /// Builds a `width` x `height` image from a row-major interleaved buffer `[y][x][c]`.
    pub fn from_interleaved(
        data: &[f32],
        channels: usize,
        width: usize,
        height: usize,
    ) -> Result<Self> {
        let view = ArrayView3::from_shape((height, width, channels), data).map_err(|_| {
            Error::arg(format!(
                "interleaved buffer holds {} floats, expected {height} x {width} x {channels} = {}",
                data.len(),
                height * width * channels
            ))
        })?;
        Ok(Self::from_hwc(view))
    }

    /// Number of channels (planes).
    pub fn channels(&self) -> usize {
        self.planes.shape()[0]
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.planes.shape()[1]
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.planes.shape()[2]
    }

    /// `(width, height)`.
    pub fn size(&self) -> (usize, usize) {
        (self.width(), self.height())
    }

    /// The whole array, shape `(channels, height, width)`.
    pub fn planes(&self) -> &Array3<f32> {
        &self.planes
    }

    /// The whole array, mutable.
    pub fn planes_mut(&mut self) -> &mut Array3<f32> {
        &mut self.planes
    }

    /// Consumes the image, returning its array.
    pub fn into_planes(self) -> Array3<f32> {
        self.planes
    }

    /// One channel as a `(height, width)` view.
    pub fn plane(&self, c: usize) -> ArrayView2<'_, f32> {
        self.planes.index_axis(Axis(0), c)
    }

    /// One channel, mutable.
    pub fn plane_mut(&mut self, c: usize) -> ArrayViewMut2<'_, f32> {
        self.planes.index_axis_mut(Axis(0), c)
    }

    /// All samples, channel after channel (planar order).
    pub fn as_slice(&self) -> &[f32] {
        self.planes
            .as_slice()
            .expect("Image storage is always standard layout")
    }

    /// All samples, mutable.
    pub fn as_mut_slice(&mut self) -> &mut [f32] {
        self.planes
            .as_slice_mut()
            .expect("Image storage is always standard layout")
    }

    /// The value at channel `c`, pixel `(x, y)`.
    pub fn at(&self, c: usize, x: usize, y: usize) -> f32 {
        self.planes[[c, y, x]]
    }

    /// Copies the image into an interleaved `[y][x][c]` vector.
    pub fn to_interleaved(&self) -> Vec<f32> {
        self.planes
            .view()
            .permuted_axes([1, 2, 0])
            .iter()
            .copied()
            .collect()
    }

    /// The forward differences `(dx, dy)` of the frame convention:
    /// `dx(x, y) = I(x+1, y) - I(x, y)`, `dy(x, y) = I(x, y+1) - I(x, y)`, 0 in the last column
    /// of `dx` and the last row of `dy`. Exact gradients, e.g. for tests and synthetic frames.
    pub fn forward_differences(&self) -> (Image, Image) {
        let (w, h, ch) = (self.width(), self.height(), self.channels());
        let dx = Image::from_fn(ch, w, h, |(c, x, y)| {
            if x + 1 < w {
                self.at(c, x + 1, y) - self.at(c, x, y)
            } else {
                0.0
            }
        });
        let dy = Image::from_fn(ch, w, h, |(c, x, y)| {
            if y + 1 < h {
                self.at(c, x, y + 1) - self.at(c, x, y)
            } else {
                0.0
            }
        });
        (dx, dy)
    }

    /// True when every sample is finite.
    pub fn all_finite(&self) -> bool {
        self.as_slice().iter().all(|v| v.is_finite())
    }

    /// Largest absolute difference to `other`, sample by sample (tests' comparisons).
    #[cfg(test)]
    pub(crate) fn max_abs_diff(&self, other: &Image) -> f32 {
        self.as_slice()
            .iter()
            .zip(other.as_slice())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max)
    }
}

/// The error for an image that cannot be allocated.
fn too_large(channels: usize, width: usize, height: usize) -> Error {
    Error::OutOfMemory(format!(
        "cannot allocate a {width} x {height} x {channels} image ({} MiB)",
        (channels as u128 * width as u128 * height as u128 * 4) >> 20
    ))
}

/// `len` copies of `value`, or [`Error::OutOfMemory`] when the allocation fails instead of
/// aborting the process.
pub(crate) fn try_vec<T: Clone>(len: usize, value: T) -> Result<Vec<T>> {
    let mut v = Vec::new();
    try_resize(&mut v, len, value)?;
    Ok(v)
}

/// Makes `v` `len` values long, as [`Vec::resize`] (the values it holds stay, new ones are
/// `value`), or fails with [`Error::OutOfMemory`]: for buffers reused from one part of a job to
/// the next, which the caller overwrites.
pub(crate) fn try_resize<T: Clone>(v: &mut Vec<T>, len: usize, value: T) -> Result<()> {
    if len > v.len() {
        v.try_reserve_exact(len - v.len()).map_err(|_| {
            Error::OutOfMemory(format!(
                "cannot allocate {} MiB",
                (len as u128 * std::mem::size_of::<T>() as u128) >> 20
            ))
        })?;
    }
    v.resize(len, value);
    Ok(())
}

/// `len` zeros from a zeroed allocation (large ones are fresh pages from the system, already
/// zero: no fill), or [`Error::OutOfMemory`]; for buffers of an image's size.
pub(crate) fn try_zeroed_vec<T: bytemuck::Zeroable>(len: usize) -> Result<Vec<T>> {
    bytemuck::allocation::try_zeroed_vec(len).map_err(|()| {
        Error::OutOfMemory(format!(
            "cannot allocate {} MiB",
            (len as u128 * std::mem::size_of::<T>() as u128) >> 20
        ))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zeroed_planes_are_zero_and_an_impossible_size_is_an_error() {
        // Large enough for the allocator to map fresh pages, small enough for any machine.
        let v = Image::try_zeros(3, 1 << 10, 1 << 10).unwrap();
        assert!(v.as_slice().len() == 3 << 20 && v.as_slice().iter().all(|&x| x.to_bits() == 0));
        assert!(Image::try_zeros(3, 0, 5).unwrap().as_slice().is_empty());
        assert!(matches!(
            Image::try_zeros(1, usize::MAX / 8, 1),
            Err(Error::OutOfMemory(_))
        ));
        assert!(matches!(
            Image::try_zeros(3, 1 << 30, 1 << 30),
            Err(Error::OutOfMemory(_))
        ));
    }
}
