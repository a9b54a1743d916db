//! Finite-difference operators on planes, and reductions with a fixed order.
//!
//! A plane is a row-major `&[f32]` of `h` rows of `w` values. `D_x` and `D_y` are the forward
//! differences of the frame conventions with natural (Neumann) boundaries: only the `w - 1`
//! horizontal and `h - 1` vertical differences exist, so the last column of `dx` and the last
//! row of `dy` are never read.
//!
//! Every function is parallel over rows and writes each output value from reads only, and
//! every reduction sums per-row partials serially, so results are bit-identical for any
//! thread count.

use rayon::prelude::*;

/// Reflect-101 border rule (`dcb|abcd|cba`), the release's choice almost everywhere: index
/// `i` (possibly outside `0..n`) mapped into `0..n`. Indices inside, or one reflection away,
/// take no division (the filter's window loops call this per tap).
#[inline]
pub(crate) fn reflect(i: isize, n: usize) -> usize {
    let m = n as isize;
    if (0..m).contains(&i) {
        i as usize
    } else if i < 0 && -i < m {
        -i as usize
    } else if i >= m && i <= 2 * m - 2 {
        (2 * m - 2 - i) as usize
    } else {
        reflect_periodic(i, n)
    }
}

/// [`reflect`] by its period, for any distance from the image.
fn reflect_periodic(i: isize, n: usize) -> usize {
    if n == 1 {
        return 0;
    }
    let n = n as isize;
    let period = 2 * (n - 1);
    let mut i = i.rem_euclid(period);
    if i >= n {
        i = period - i;
    }
    i as usize
}

/// Plane dimensions.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Dims {
    pub w: usize,
    pub h: usize,
}

impl Dims {
    pub fn len(self) -> usize {
        self.w * self.h
    }
}

/// `out = D_x^T gx + D_y^T gy` (the negative divergence of the gradient field).
pub(crate) fn grad_adjoint(gx: &[f32], gy: &[f32], d: Dims, out: &mut [f32]) {
    let Dims { w, h } = d;
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let gxr = &gx[y * w..(y + 1) * w];
        for x in 0..w {
            let mut v = 0.0;
            if x >= 1 {
                v += gxr[x - 1];
            }
            if x + 1 < w {
                v -= gxr[x];
            }
            if y >= 1 {
                v += gy[(y - 1) * w + x];
            }
            if y + 1 < h {
                v -= gy[y * w + x];
            }
            row[x] = v;
        }
    });
}

/// An operator `(A u)(p) = data(p) u(p) + sum over the grid edges (p, q) of e(p, q) (u(p) -
/// u(q))` in row-major planes: `data` on the diagonal, one weight per horizontal edge (`ex`, 0
/// in the last column) and per vertical edge (`ey`, 0 in the last row). The IRLS system owns
/// one, the multigrid one per coarse level.
#[derive(Clone, Default)]
pub(crate) struct Operator {
    pub data: Vec<f32>,
    pub ex: Vec<f32>,
    pub ey: Vec<f32>,
}

impl Operator {
    /// The whole operator as the weights [`apply_weighted`] reads.
    pub fn weights(&self) -> RowWeights<'_> {
        RowWeights {
            data: &self.data,
            x: &self.ex,
            y: &self.ey,
        }
    }
}

/// The weighted operator of an IRLS step: `data` its diagonal (`alpha^2` times the weights of
/// the data rows `alpha (I - I_b)`), `x` and `y` the weights of the gradient rows (last column
/// of `x`, last row of `y` unused).
pub(crate) struct RowWeights<'a> {
    pub data: &'a [f32],
    pub x: &'a [f32],
    pub y: &'a [f32],
}

/// `out = data * u + D_x^T (wx * D_x u) + D_y^T (wy * D_y u)` on each of the three
/// planes of `u`, each row then handed to `finish(plane, y, row, u_row)`, which may rewrite
/// it (a residual) and returns the row's share of a per-plane sum (f64, rows added in order,
/// a fixed order): conjugate gradients needs `u . out` or `r . r` next, and gets it without
/// another pass over memory.
///
/// Written edge by edge with the boundary rows and columns outside the inner loops, so the
/// loops are branch-free and vectorise. The three planes' rows are done together, so a row's
/// weights are read from memory once. `partials` is scratch reused between calls.
pub(crate) fn apply_weighted(
    u: &[f32],
    wt: &RowWeights,
    d: Dims,
    out: &mut [f32],
    partials: &mut Vec<[f64; 3]>,
    finish: impl Fn(usize, usize, &mut [f32], &[f32]) -> f64 + Sync,
) -> [f64; 3] {
    let Dims { w, h } = d;
    let n = w * h;
    let (o0, rest) = out.split_at_mut(n);
    let (o1, o2) = rest.split_at_mut(n);
    o0.par_chunks_mut(w)
        .zip(o1.par_chunks_mut(w))
        .zip(o2.par_chunks_mut(w))
        .enumerate()
        .map(|(y, ((r0, r1), r2))| {
            let o = y * w;
            let row_weights = RowWeights {
                data: &wt.data[o..o + w],
                x: &wt.x[o..o + w],
                y: &wt.y[o..o + w],
            };
            let mut dots = [0.0; 3];
            for (plane, row) in [r0, r1, r2].into_iter().enumerate() {
                let u = &u[plane * n..(plane + 1) * n];
                let ur = &u[o..o + w];
                let up = (y >= 1).then(|| (&u[o - w..o], &wt.y[o - w..o]));
                let down = (y + 1 < h).then(|| &u[o + w..o + 2 * w]);
                weighted_row(row, &row_weights, ur, up, down);
                dots[plane] = finish(plane, y, row, ur);
            }
            dots
        })
        .collect_into_vec(partials);
    // Rows in order within each plane.
    std::array::from_fn(|c| partials.iter().map(|p| p[c]).sum())
}

/// One row of [`apply_weighted`]: `row = (A u)` at the row `ur`, `wt` holding that row's
/// weights, `up` the row above with the vertical weights between the two (`None` on the first
/// row), `down` the row below (`None` on the last, whose `wt.y` are 0).
#[inline]
pub(crate) fn weighted_row(
    row: &mut [f32],
    wt: &RowWeights,
    ur: &[f32],
    up: Option<(&[f32], &[f32])>,
    down: Option<&[f32]>,
) {
    let w = row.len();
    let (wd, wx, wy) = (wt.data, wt.x, wt.y);
    for ((v, &c), &k) in row.iter_mut().zip(ur).zip(wd) {
        *v = k * c;
    }
    // Horizontal edges (x, x+1), x < w - 1, each with flux wx[x] (u[x+1] - u[x]).
    if w >= 2 {
        row[0] -= wx[0] * (ur[1] - ur[0]);
        row[w - 1] += wx[w - 2] * (ur[w - 1] - ur[w - 2]);
        for ((v, u3), k2) in row[1..w - 1]
            .iter_mut()
            .zip(ur.windows(3))
            .zip(wx.windows(2))
        {
            *v += k2[0] * (u3[1] - u3[0]) - k2[1] * (u3[2] - u3[1]);
        }
    }
    if let Some((up, wy_up)) = up {
        for (((v, &c), &a), &k) in row.iter_mut().zip(ur).zip(up).zip(wy_up) {
            *v += k * (c - a);
        }
    }
    if let Some(dn) = down {
        for (((v, &c), &b), &k) in row.iter_mut().zip(ur).zip(dn).zip(wy) {
            *v -= k * (b - c);
        }
    }
}

/// Interleaved partial sums of [`row_sum`].
pub(crate) const SUM_LANES: usize = 16;

/// `sum of f(a_i, b_i)` over a row, in [`SUM_LANES`] interleaved partial sums then added in
/// order. A single running sum is a chain of dependent additions (4 cycles each) that the
/// compiler may not reorder, and it was what bounded the CG loop's passes over memory;
/// interleaved, the sums vectorise. The order is fixed, so any thread count gives the same
/// bits.
#[inline(always)]
pub(crate) fn row_sum<T>(a: &[f32], b: &[f32], f: impl Fn(f32, f32) -> T) -> T
where
    T: Copy + Default + std::ops::AddAssign + std::iter::Sum,
{
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [T::default(); SUM_LANES];
    let (ca, cb) = (a.chunks_exact(SUM_LANES), b.chunks_exact(SUM_LANES));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (ca, cb) in ca.zip(cb) {
        for k in 0..SUM_LANES {
            acc[k] += f(ca[k], cb[k]);
        }
    }
    for (k, (&a, &b)) in ra.iter().zip(rb).enumerate() {
        acc[k] += f(a, b);
    }
    acc.into_iter().sum()
}

/// Sums of `f(a_i, b_i)` per plane of `plane_len` values, in f64, in a fixed order (each
/// row's by [`row_sum`]). `partials` is scratch reused between calls.
pub(crate) fn plane_sums(
    a: &[f32],
    b: &[f32],
    row: usize,
    plane_len: usize,
    partials: &mut Vec<f64>,
    f: impl Fn(f32, f32) -> f64 + Sync,
) -> Vec<f64> {
    a.par_chunks(row)
        .zip(b.par_chunks(row))
        .map(|(ra, rb)| row_sum(ra, rb, &f))
        .collect_into_vec(partials);
    let rows_per_plane = plane_len / row;
    partials
        .chunks(rows_per_plane)
        .map(|c| c.iter().sum())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reflect_fast_paths_equal_the_periodic_rule() {
        for n in 1..30 {
            for i in -70..100 {
                assert_eq!(reflect(i, n), reflect_periodic(i, n), "{i} {n}");
            }
        }
    }
}
