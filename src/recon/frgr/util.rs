//! Small helpers shared by FRGR's stages: borders, luminance, planes.

use rayon::prelude::*;

use crate::error::Result;
use crate::image::{try_zeroed_vec, Image};
pub(crate) use crate::recon::ops::reflect;

/// Rec. 709 luminance weights.
pub(crate) const LUMA: [f32; 3] = [0.2126, 0.7152, 0.0722];

/// Fills a padded row's border from its interior, reflect-101: `row[pad..pad + w]` holds an
/// image row, and every other `row[j]` becomes that row's column `reflect(j - pad, w)` (the
/// row may extend past `pad` on the right, as the QP's lane groups need).
pub(crate) fn reflect_borders(row: &mut [f32], pad: usize, w: usize) {
    for j in (0..pad).chain(pad + w..row.len()) {
        row[j] = row[pad + reflect(j as isize - pad as isize, w)];
    }
}

/// An image whose rows are padded left and right by `pad` columns (reflect-101), so that the
/// column `reflect(x + dx)` of a window offset `dx` is `x + dx` of a padded row: a slice.
pub(crate) struct PaddedRows {
    data: Vec<f32>,
    /// The image's channels, width and height (unpadded).
    pub(crate) channels: usize,
    pub(crate) w: usize,
    pub(crate) h: usize,
    pad: usize,
}

impl PaddedRows {
    pub(crate) fn new(img: &Image, pad: usize) -> Result<Self> {
        let (w, h) = img.size();
        let stride = w + 2 * pad;
        let s = img.as_slice();
        let mut data = try_zeroed_vec(img.channels() * h * stride)?;
        data.par_chunks_mut(stride)
            .enumerate()
            .for_each(|(row, out)| {
                out[pad..pad + w].copy_from_slice(&s[row * w..(row + 1) * w]);
                reflect_borders(out, pad, w);
            });
        Ok(PaddedRows {
            data,
            channels: img.channels(),
            w,
            h,
            pad,
        })
    }

    /// [`PaddedRows::row`] of channels 0, 1 and 2.
    #[inline]
    pub(crate) fn rows3(&self, y: usize, x0: usize, dx: isize, len: usize) -> [&[f32]; 3] {
        [
            self.row(0, y, x0, dx, len),
            self.row(1, y, x0, dx, len),
            self.row(2, y, x0, dx, len),
        ]
    }

    /// Channel `c`, row `y`, columns `reflect(x0 + dx) ..` (`len` of them, `|dx| <= pad`).
    #[inline]
    pub(crate) fn row(&self, c: usize, y: usize, x0: usize, dx: isize, len: usize) -> &[f32] {
        let start = (c * self.h + y) * (self.w + 2 * self.pad)
            + (x0 + self.pad)
                .checked_add_signed(dx)
                .expect("offset within the padding");
        &self.data[start..start + len]
    }
}

/// Runs `f` on a pool of `threads` workers (tests: results must not depend on the count).
#[cfg(test)]
pub(crate) fn with_threads<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("a thread pool")
        .install(f)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reflect_101() {
        let got: Vec<usize> = (-4..8).map(|i| reflect(i, 4)).collect();
        assert_eq!(got, [2, 3, 2, 1, 0, 1, 2, 3, 2, 1, 0, 1]);
        assert_eq!(reflect(-3, 1), 0);
        assert_eq!(reflect(5, 2), 1);
    }
}
