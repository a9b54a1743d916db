//! Exact solver of `(alpha^2 + D^T D) u = f` with Neumann boundaries, by the 2-D DCT-II.
//!
//! The 1-D Neumann Laplacian `D^T D` on `n` samples has the DCT-II basis
//! `cos(pi k (j + 1/2) / n)` as eigenvectors with eigenvalues `2 - 2 cos(pi k / n)`, so the 2-D
//! screened operator is diagonal in the 2-D DCT-II basis: transform, divide by
//! `alpha^2 + lambda_x(k) + lambda_y(l)`, transform back with the DCT-III. `rustdct` leaves its
//! transforms unnormalised (DCT-III after DCT-II multiplies by `n / 2`); the `4 / (w h)` factor
//! is folded into the stored inverse eigenvalues.
//!
//! With `alpha = 0` the operator is singular (constants are in its kernel); the solver then
//! returns the zero-mean solution and callers fix the mean.
//!
//! Layout: rows are transformed in place, each plane is transposed (cache-blocked) so columns
//! become rows, the column transforms, the division and the inverse column transforms run in one
//! pass per row, then the plane is transposed back for the inverse row transforms. All passes
//! are parallel over rows and deterministic.

use std::sync::Arc;

use rayon::prelude::*;
use rustdct::{DctPlanner, TransformType2And3};

use super::ops::Dims;
use crate::error::Result;
use crate::image::try_vec;

/// A planned solver for one image size and `alpha`.
pub(crate) struct DctPoisson {
    dims: Dims,
    rows: Arc<dyn TransformType2And3<f32>>,
    cols: Arc<dyn TransformType2And3<f32>>,
    /// `scale / (alpha^2 + lambda_x + lambda_y)`, stored transposed: index `x * h + y`.
    inv_eigen: Vec<f32>,
    /// Transposed planes, reused between solves.
    transposed: Vec<f32>,
}

const BLOCK: usize = 32;

impl DctPoisson {
    /// Plans the transforms and eigenvalues for `dims` and `alpha`; fails with `OutOfMemory` when the eigenvalue plane cannot be allocated.
    pub fn new(dims: Dims, alpha: f32) -> Result<Self> {
        let Dims { w, h } = dims;
        let mut planner = DctPlanner::new();
        let mut solver = DctPoisson {
            dims,
            rows: planner.plan_dct2(w),
            cols: planner.plan_dct2(h),
            inv_eigen: try_vec(w * h, 0.0f32)?,
            // The three colour planes every caller solves for, allocated with the plan (an
            // execution then allocates nothing large).
            transposed: try_vec(3 * dims.len(), 0.0)?,
        };
        solver.set_alpha(alpha);
        Ok(solver)
    }

    /// Makes this the solver for `alpha` (the same size): the same values as a solver planned
    /// for it, without allocating.
    pub fn set_alpha(&mut self, alpha: f32) {
        let Dims { w, h } = self.dims;
        let eig =
            |k: usize, n: usize| 2.0 - 2.0 * (std::f64::consts::PI * k as f64 / n as f64).cos();
        let ly: Vec<f64> = (0..h).map(|k| eig(k, h)).collect();
        let alpha2 = f64::from(alpha) * f64::from(alpha);
        let scale = 4.0 / (w as f64 * h as f64);
        for (x, column) in self.inv_eigen.chunks_mut(h).enumerate() {
            let lx = eig(x, w);
            for (y, v) in column.iter_mut().enumerate() {
                let denom = alpha2 + lx + ly[y];
                *v = if denom > 0.0 {
                    (scale / denom) as f32
                } else {
                    0.0
                };
            }
        }
    }

    /// Solves in place for every plane of `planes` (a multiple of `w * h` values).
    pub fn solve(&mut self, planes: &mut [f32]) {
        let Dims { w, h } = self.dims;
        let n = w * h;
        assert_eq!(planes.len() % n, 0, "planes must be whole w x h planes");
        self.transposed.resize(planes.len(), 0.0);

        transform_rows(&*self.rows, planes, w, Direction::Forward);
        for (src, dst) in planes.chunks(n).zip(self.transposed.chunks_mut(n)) {
            transpose(src, dst, w, h);
        }
        let cols = &*self.cols;
        let inv = &self.inv_eigen;
        let scratch_len = cols.get_scratch_len();
        self.transposed.par_chunks_mut(h).enumerate().for_each_init(
            || vec![0.0f32; scratch_len],
            |scratch, (r, row)| {
                let x = r % w;
                cols.process_dct2_with_scratch(row, scratch);
                for (v, s) in row.iter_mut().zip(&inv[x * h..(x + 1) * h]) {
                    *v *= s;
                }
                cols.process_dct3_with_scratch(row, scratch);
            },
        );
        for (src, dst) in self.transposed.chunks(n).zip(planes.chunks_mut(n)) {
            transpose(src, dst, h, w);
        }
        transform_rows(&*self.rows, planes, w, Direction::Inverse);
    }
}

#[derive(Clone, Copy)]
enum Direction {
    Forward,
    Inverse,
}

fn transform_rows(t: &dyn TransformType2And3<f32>, data: &mut [f32], len: usize, dir: Direction) {
    let scratch_len = t.get_scratch_len();
    data.par_chunks_mut(len).for_each_init(
        || vec![0.0f32; scratch_len],
        |scratch, row| match dir {
            Direction::Forward => t.process_dct2_with_scratch(row, scratch),
            Direction::Inverse => t.process_dct3_with_scratch(row, scratch),
        },
    );
}

/// `dst` (`w` rows of `h`) = transpose of `src` (`h` rows of `w`), in cache blocks.
fn transpose(src: &[f32], dst: &mut [f32], w: usize, h: usize) {
    dst.par_chunks_mut(BLOCK * h)
        .enumerate()
        .for_each(|(bx, dst_block)| {
            let x0 = bx * BLOCK;
            let bw = dst_block.len() / h;
            for y0 in (0..h).step_by(BLOCK) {
                let y1 = (y0 + BLOCK).min(h);
                for dx in 0..bw {
                    let drow = &mut dst_block[dx * h..(dx + 1) * h];
                    for y in y0..y1 {
                        drow[y] = src[y * w + x0 + dx];
                    }
                }
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transpose_round_trip() {
        let (w, h) = (37, 70);
        let src: Vec<f32> = (0..w * h).map(|i| i as f32).collect();
        let mut t = vec![0.0; w * h];
        let mut back = vec![0.0; w * h];
        transpose(&src, &mut t, w, h);
        assert_eq!(t[5 * h + 3], src[3 * w + 5]);
        transpose(&t, &mut back, h, w);
        assert_eq!(src, back);
    }

    #[test]
    fn screened_identity_when_gradients_vanish() {
        // (alpha^2 + D^T D) u = alpha^2 c has the solution u = c for a constant c.
        let dims = Dims { w: 9, h: 5 };
        let mut s = DctPoisson::new(dims, 0.5).unwrap();
        let mut f = vec![0.25 * 3.0; dims.len()];
        s.solve(&mut f);
        for v in f {
            assert!((v - 3.0).abs() < 1e-5, "{v}");
        }
    }
}
