//! An algebraic multigrid V-cycle for the weighted screened Poisson systems of IRLS: the
//! preconditioner that follows the weights where the DCT solve cannot.
//!
//! Every level holds an operator of one form, a graph Laplacian on a `w x h` grid plus a
//! diagonal:
//! `(A u)(p) = data(p) u(p) + sum over the grid edges (p, q) of e(p, q) (u(p) - u(q))`,
//! with one weight per horizontal edge (`ex`, zero in the last column) and per vertical edge
//! (`ey`, zero in the last row). The fine level is the IRLS system (`data = alpha^2 w_d`,
//! `ex = w_x`, `ey = w_y`), read where the solve keeps it.
//!
//! Coarsening aggregates 2 x 2 blocks with piecewise-constant interpolation `P`. The Galerkin
//! product `P^T A P` is then again of that form, exactly: a coarse cell's `data` is the sum of
//! its four fine `data`, a coarse edge's weight the sum of the two fine edges that cross
//! between the two blocks (edges inside a block cancel). So weights that jump by orders of
//! magnitude, which a constant-coefficient (DCT) preconditioner cannot see, are carried to
//! every level, and the hierarchy goes down to one cell, which is solved exactly.
//!
//! The cycle: two red-black Gauss-Seidel sweeps before the coarse correction, the same sweeps
//! in reverse colour order after it, so the cycle is a symmetric positive definite operator
//! that conjugate gradients can use. A V-cycle: a W-cycle (two coarse visits) cost more and
//! saved no iterations, as did scaling the coarse correction (the usual remedy for
//! piecewise-constant interpolation: 1.1 was even with 1, 1.3 and above worse).
//!
//! Every pass is parallel over bands of rows and gives the same bits for any thread count:
//! within a colour, cells do not depend on each other, and a band's smoothing reads the rows
//! beyond its edges from copies taken before the pass. The kernels are memory-bound, so the
//! passes are fused: all the sweeps before (after) the coarse correction are one pass over
//! the level, the prolongation is added in the post-smoothing pass, and the three planes of a
//! row are processed together so each row's weights are read once.

use rayon::prelude::*;

use super::ops::{row_sum, Dims, Operator};
use crate::error::Result;
use crate::image::try_vec;

/// Red-black sweeps before (and after) each coarse correction. One sweep needed 1.5x the CG
/// iterations of two (125 against 86 on the 720p synthetic frame) for less than half the
/// saving in cost; three saved few more iterations (73).
const SWEEPS: usize = 2;

/// Half-sweeps fused into one pass (see [`Level::smooth`]), and the rows copied beyond each
/// band's edges.
const HALF_SWEEPS: usize = 2 * SWEEPS;

/// Rows per parallel band. Levels smaller than [`PARALLEL_CELLS`] run on one thread.
const BAND: usize = 32;
const PARALLEL_CELLS: usize = 1 << 15;

/// The fewest items one task of a parallel pass over a level of `cells` cells takes: 1 on
/// large levels; all of them on those under [`PARALLEL_CELLS`], which then run as one task
/// on the calling thread (their passes cost less than handing them out).
fn min_len(cells: usize) -> usize {
    if cells >= PARALLEL_CELLS {
        1
    } else {
        usize::MAX
    }
}

/// Row `k` (of rows or bands) of three planes, as the parallel passes hand them out.
type Rows3<'a> = (usize, ((&'a mut [f32], &'a mut [f32]), &'a mut [f32]));

/// One row of a coarse operator's `data`, `ex` and `ey`, as [`aggregate`] fills them.
type CoarseRow<'a> = ((&'a mut [f32], &'a mut [f32]), &'a mut [f32]);

/// A band of [`Level::smooth`]: its rows of the three planes, its halo, and where its rows'
/// dot products go (when asked for).
type BandWork<'a> = ((Rows3<'a>, &'a mut [f32]), Option<&'a mut [f64]>);

/// A coarse correction `P coarse_x` to add to a level's three planes: each coarse value
/// goes to its 2 x 2 block.
struct Correction<'a> {
    coarse_x: &'a [f32],
    coarse: Dims,
}

impl Correction<'_> {
    /// Adds the correction to row `y` of plane `c`.
    fn add(&self, row: &mut [f32], c: usize, y: usize) {
        let Dims { w, h } = self.coarse;
        let o = c * w * h + (y / 2) * w;
        add_pairs(row, &self.coarse_x[o..o + w]);
    }
}

/// One level's operator and (below the fine level) its vectors.
#[derive(Clone)]
struct Level {
    dims: Dims,
    /// Empty on the fine level, whose operator is the caller's (it is not copied).
    op: Operator,
    /// `1 / diag(A)` (0 where the diagonal is 0).
    inv_diag: Vec<f32>,
    /// Solution and right-hand side, three planes each; empty on the fine level, whose
    /// vectors are the caller's.
    x: Vec<f32>,
    b: Vec<f32>,
    /// Copies of the rows beyond each band's edges (see [`Level::smooth`]).
    halo: Vec<f32>,
    /// A row of zeros: the weights and values above the first row.
    zeros: Vec<f32>,
    /// `true, false, true, ...` (`w + 1` values): the cells of one colour in a row.
    mask: Vec<bool>,
}

/// A planned multigrid preconditioner for one image size (three channels sharing one
/// operator).
pub(crate) struct Multigrid {
    levels: Vec<Level>,
    /// `r . z` of each fine row, row by row, the three planes interleaved (`y * 3 + c`).
    row_dots: Vec<f64>,
}

/// Bytes a [`Multigrid`] for `w x h` frames holds: the halo ([`HALF_SWEEPS`] rows on each
/// side of every band, three planes) and the inverse diagonal on every level, and three
/// operator and six vector planes below the fine one (the coarse levels add a third of the
/// fine level's size).
pub(crate) fn multigrid_bytes(w: usize, h: usize) -> u64 {
    let n = (w * h) as u64;
    // Fine level: 1 plane; coarse levels: (4 + 6) planes over n / 3 cells in all.
    let halo = 6 * HALF_SWEEPS as u64 * w as u64 * (h.div_ceil(BAND) as u64 + 1);
    4 * (n + 10 * n.div_ceil(3)) + 4 * halo
}

impl Multigrid {
    /// Allocates every level for `dims` (fails with `OutOfMemory`).
    pub fn new(dims: Dims) -> Result<Self> {
        let mut levels = Vec::new();
        let mut d = dims;
        loop {
            let n = d.len();
            let fine = levels.is_empty();
            let op = if fine {
                Operator::default()
            } else {
                Operator {
                    data: try_vec(n, 0.0)?,
                    ex: try_vec(n, 0.0)?,
                    ey: try_vec(n, 0.0)?,
                }
            };
            levels.push(Level {
                dims: d,
                op,
                inv_diag: try_vec(n, 0.0)?,
                x: if fine {
                    Vec::new()
                } else {
                    try_vec(3 * n, 0.0)?
                },
                b: if fine {
                    Vec::new()
                } else {
                    try_vec(3 * n, 0.0)?
                },
                halo: try_vec(6 * HALF_SWEEPS * d.w * d.h.div_ceil(BAND), 0.0)?,
                zeros: try_vec(d.w, 0.0)?,
                mask: (0..=d.w).map(|i| i % 2 == 0).collect(),
            });
            if n == 1 {
                return Ok(Multigrid {
                    levels,
                    row_dots: try_vec(3 * dims.h, 0.0)?,
                });
            }
            d = Dims {
                w: d.w.div_ceil(2),
                h: d.h.div_ceil(2),
            };
        }
    }

    /// Rebuilds the hierarchy for the fine operator `fine` (`alpha^2 W_d + D_x^T W_x D_x +
    /// D_y^T W_y D_y` of an IRLS step; the weights of edges that do not exist must be 0), which
    /// [`Self::apply`] must then be given: the coarse levels and every level's inverse
    /// diagonal, each level's in the pass that aggregates it.
    pub fn set_operator(&mut self, fine: &Operator) {
        for l in 1..self.levels.len() {
            let (done, rest) = self.levels.split_at_mut(l);
            let level = &mut done[l - 1];
            let op = if l == 1 { fine } else { &level.op };
            aggregate(
                op,
                level.dims,
                &mut level.inv_diag,
                &mut rest[0].op,
                rest[0].dims,
            );
        }
        let single = self.levels.len() == 1;
        let last = self.levels.last_mut().expect("at least one level");
        let op = if single { fine } else { &last.op };
        inverse_diagonal(op, last.dims, &mut last.inv_diag);
    }

    /// `z = B r`, one V-cycle from zero on each of the three planes of `r`, with `fine` the
    /// operator of the last [`Self::set_operator`]; returns `r . z` per plane (as
    /// [`super::ops::plane_sums`] would, bit for bit), summed in the cycle's last pass while
    /// each row of `z` is still in cache.
    pub fn apply(&mut self, fine: &Operator, r: &[f32], z: &mut [f32]) -> [f64; 3] {
        cycle(&mut self.levels, Some(fine), z, r, Some(&mut self.row_dots));
        // Rows in order within each plane, as `plane_sums` adds them.
        std::array::from_fn(|c| self.row_dots.iter().skip(c).step_by(3).sum())
    }
}

/// One V-cycle on `levels[0]` from `x = 0` (`fine`: its operator, when it is the caller's);
/// with `dots`, also each row's `b . x` (see [`Level::smooth`]).
fn cycle(
    levels: &mut [Level],
    fine: Option<&Operator>,
    x: &mut [f32],
    b: &[f32],
    dots: Option<&mut [f64]>,
) {
    let (level, coarser) = levels.split_first_mut().expect("at least one level");
    let Some(coarse) = coarser.first_mut() else {
        // One cell: A is the scalar data(0).
        for (x, &b) in x.iter_mut().zip(b) {
            *x = b * level.inv_diag[0];
        }
        if let Some(dots) = dots {
            for (d, (&x, &b)) in dots.iter_mut().zip(x.iter().zip(b)) {
                *d = f64::from(x) * f64::from(b);
            }
        }
        return;
    };
    // Out of the level for the cycle, so the level's passes can borrow it.
    let own = std::mem::take(&mut level.op);
    let op = fine.unwrap_or(&own);
    level.smooth(op, x, b, 0, true, None, None);
    let cd = coarse.dims;
    let (mut cx, mut cb) = (std::mem::take(&mut coarse.x), std::mem::take(&mut coarse.b));
    level.restrict_residual(op, x, b, cd, &mut cb);
    cycle(coarser, None, &mut cx, &cb, None);
    let correction = Correction {
        coarse_x: &cx,
        coarse: cd,
    };
    level.smooth(op, x, b, 1, false, Some(correction), dots);
    (coarser[0].x, coarser[0].b) = (cx, cb);
    level.op = own;
}

/// `1 / diag(A)` of row `y` of `op` (of width `w`), 0 where the diagonal is 0: the cell's
/// `data` and the weights of its (up to four) edges.
fn inverse_diagonal_row(op: &Operator, w: usize, y: usize, out: &mut [f32]) {
    let o = y * w;
    let (data, ex, ey) = (&op.data[o..o + w], &op.ex[o..o + w], &op.ey[o..o + w]);
    let up = (y >= 1).then(|| &op.ey[o - w..o]);
    for (i, v) in out[..w].iter_mut().enumerate() {
        let mut d = data[i] + ex[i] + ey[i];
        if i >= 1 {
            d += ex[i - 1];
        }
        if let Some(up) = up {
            d += up[i];
        }
        *v = if d > 0.0 { 1.0 / d } else { 0.0 };
    }
}

/// [`inverse_diagonal_row`] on every row of a level.
fn inverse_diagonal(op: &Operator, dims: Dims, out: &mut [f32]) {
    out.par_chunks_mut(dims.w)
        .enumerate()
        .with_min_len(min_len(dims.len()))
        .for_each(|(y, row)| inverse_diagonal_row(op, dims.w, y, row));
}

/// The Galerkin operator `coarse` of `fine` under 2 x 2 aggregation (see the module comment),
/// and in the same pass over `fine` its inverse diagonal `fine_inv`.
fn aggregate(fine: &Operator, fd: Dims, fine_inv: &mut [f32], coarse: &mut Operator, cd: Dims) {
    let Dims { w: fw, h: fh } = fd;
    let cw = cd.w;
    let each = |(cy, (((data, ex), ey), inv)): (usize, (CoarseRow<'_>, &mut [f32]))| {
        let y0 = 2 * cy;
        for (k, row) in inv.chunks_mut(fw).enumerate() {
            inverse_diagonal_row(fine, fw, y0 + k, row);
        }
        // Row `y` of a fine plane (the last one for a row past it: read, never used).
        fn rows(v: &[f32], y: usize, fw: usize, fh: usize) -> &[f32] {
            let o = y.min(fh - 1) * fw;
            &v[o..o + fw]
        }
        let rows = |v, y| rows(v, y, fw, fh);
        let (d0, d1) = (rows(&fine.data, y0), rows(&fine.data, y0 + 1));
        let (h0, h1) = (rows(&fine.ex, y0), rows(&fine.ex, y0 + 1));
        let v1 = rows(&fine.ey, y0 + 1);
        let pairs = fw / 2;
        if y0 + 1 < fh {
            // Both fine rows, both fine columns: the cell sums in the order of the general
            // case below (rows, then columns), so the bits are the same.
            for cx in 0..pairs {
                let x0 = 2 * cx;
                data[cx] = ((d0[x0] + d0[x0 + 1]) + d1[x0]) + d1[x0 + 1];
                ex[cx] = h0[x0 + 1] + h1[x0 + 1];
                ey[cx] = v1[x0] + v1[x0 + 1];
            }
        }
        let from = if y0 + 1 < fh { pairs } else { 0 };
        let ys = if y0 + 1 < fh { y0..y0 + 2 } else { y0..y0 + 1 };
        for cx in from..cw {
            let x0 = 2 * cx;
            let xs = if x0 + 1 < fw { x0..x0 + 2 } else { x0..x0 + 1 };
            let (mut d, mut h, mut v) = (0.0, 0.0, 0.0);
            for y in ys.clone() {
                for x in xs.clone() {
                    d += fine.data[y * fw + x];
                }
                // The fine edge (x0 + 1, x0 + 2) crosses to the next block.
                if x0 + 1 < fw {
                    h += fine.ex[y * fw + x0 + 1];
                }
            }
            if y0 + 1 < fh {
                for x in xs.clone() {
                    v += fine.ey[(y0 + 1) * fw + x];
                }
            }
            (data[cx], ex[cx], ey[cx]) = (d, h, v);
        }
    };
    coarse
        .data
        .par_chunks_mut(cw)
        .zip(coarse.ex.par_chunks_mut(cw))
        .zip(coarse.ey.par_chunks_mut(cw))
        .zip(fine_inv.par_chunks_mut(2 * fw))
        .enumerate()
        .with_min_len(min_len(fd.len()))
        .for_each(each);
}

impl Level {
    /// Copies the [`HALF_SWEEPS`] rows above and below every band of `x` (all three planes)
    /// into the halo, with the coarse correction added if there is one: above rows first,
    /// below rows from offset `HALF_SWEEPS` rows, per plane.
    fn fill_halo(&self, halo: &mut [f32], x: &[f32], correction: Option<&Correction<'_>>) {
        let Dims { w, h } = self.dims;
        let (n, g) = (w * h, HALF_SWEEPS);
        let each = |(k, halo): (usize, &mut [f32])| {
            let (top, bottom) = (k * BAND, ((k + 1) * BAND).min(h));
            let (lo, hi) = (top.saturating_sub(g), (bottom + g).min(h));
            for (c, halo) in halo.chunks_mut(2 * g * w).enumerate() {
                let rows = (lo..top).zip(0..).chain((bottom..hi).zip(g..));
                for (y, at) in rows {
                    let row = &mut halo[at * w..(at + 1) * w];
                    row.copy_from_slice(&x[c * n + y * w..c * n + (y + 1) * w]);
                    if let Some(correction) = correction {
                        correction.add(row, c, y);
                    }
                }
            }
        };
        let halo = &mut halo[..6 * g * w * h.div_ceil(BAND)];
        halo.par_chunks_mut(6 * g * w)
            .enumerate()
            .with_min_len(min_len(n))
            .for_each(each);
    }

    /// [`SWEEPS`] red-black Gauss-Seidel sweeps on all three planes of `x`, each the cells of
    /// colour `first` (`(x + y) % 2 == first`), then the others. With `from_zero`, `x` is
    /// taken as 0 and the first half-sweep reads no neighbours; with a `correction`, `x` is
    /// first increased by it (the prolongation, done here to save a pass over memory).
    ///
    /// All half-sweeps run in one pass over each band, as a wavefront: half-sweep `j` one row
    /// behind half-sweep `j - 1`, so each row is read from memory once. A band works on
    /// private copies of the [`HALF_SWEEPS`] rows beyond each of its edges, taken before the
    /// pass, and updates them too: half-sweep `j` leaves out the `j + 1` outermost rows
    /// (their neighbours are not there), which still leaves the band's own rows exact after
    /// the last one. The result is that of the plain sweeps, bit for bit, for any number of
    /// threads.
    #[allow(clippy::too_many_arguments)]
    fn smooth(
        &mut self,
        op: &Operator,
        x: &mut [f32],
        b: &[f32],
        first: usize,
        from_zero: bool,
        correction: Option<Correction<'_>>,
        dots: Option<&mut [f64]>,
    ) {
        let Dims { w, h } = self.dims;
        let (n, g) = (w * h, HALF_SWEEPS);
        let mut halo = std::mem::take(&mut self.halo);
        if !from_zero {
            self.fill_halo(&mut halo, x, correction.as_ref());
        }
        let this = &*self;
        let band = |(((k, ((p0, p1), p2)), halo), mut dots): BandWork<'_>| {
            let top = k * BAND;
            let bottom = top + p0.len() / w;
            let (lo, hi) = (top.saturating_sub(g), (bottom + g).min(h));
            let (above, below, total) = (top - lo, hi - bottom, hi - lo);
            // Each plane's rows lo..hi: the halo copies above, the band, the copies below.
            let mut planes: Vec<Vec<&mut [f32]>> = [p0, p1, p2]
                .into_iter()
                .zip(halo.chunks_mut(2 * g * w))
                .map(|(band, halo)| {
                    let (up, down) = halo.split_at_mut(g * w);
                    up[..above * w]
                        .chunks_mut(w)
                        .chain(band.chunks_mut(w))
                        .chain(down[..below * w].chunks_mut(w))
                        .collect()
                })
                .collect();
            let mut corrected = above;
            for step in 0..total + g - 1 {
                // The band's rows receive the correction one row ahead of the first
                // half-sweep, which reads the row below.
                if let Some(correction) = &correction {
                    while corrected < (step + 2).min(above + (bottom - top)) {
                        for (c, rows) in planes.iter_mut().enumerate() {
                            correction.add(rows[corrected], c, lo + corrected);
                        }
                        corrected += 1;
                    }
                }
                for j in 0..g.min(step + 1) {
                    let r = step - j;
                    if r >= total {
                        continue;
                    }
                    let colour = (first + j) % 2;
                    if j == 0 && from_zero {
                        for (c, rows) in planes.iter_mut().enumerate() {
                            this.start_row(rows[r], lo + r, colour, &b[c * n..(c + 1) * n]);
                        }
                    } else if (lo == 0 || r > j) && (hi == h || r + j + 1 < total) {
                        this.relax_rows(op, &mut planes, r, lo + r, b, colour);
                    }
                    // After the last half-sweep a band row is final: its b . x.
                    if let Some(dots) = dots.as_deref_mut() {
                        if j == g - 1 && (above..above + (bottom - top)).contains(&r) {
                            let o = (lo + r) * w;
                            for (c, rows) in planes.iter().enumerate() {
                                let b = &b[c * n + o..c * n + o + w];
                                dots[(lo + r - top) * 3 + c] =
                                    row_sum(b, rows[r], |b, x| f64::from(b) * f64::from(x));
                            }
                        }
                    }
                }
            }
        };
        let (x0, rest) = x.split_at_mut(n);
        let (x1, x2) = rest.split_at_mut(n);
        let (rows, per_band) = (BAND * w, 6 * g * w);
        let halo_bands = &mut halo[..per_band * h.div_ceil(BAND)];
        let band_dots: Vec<Option<&mut [f64]>> = match dots {
            Some(dots) => dots[..3 * h].chunks_mut(3 * BAND).map(Some).collect(),
            None => (0..h.div_ceil(BAND)).map(|_| None).collect(),
        };
        x0.par_chunks_mut(rows)
            .zip(x1.par_chunks_mut(rows))
            .zip(x2.par_chunks_mut(rows))
            .enumerate()
            .zip(halo_bands.par_chunks_mut(per_band))
            .zip(band_dots)
            .with_min_len(min_len(n))
            .for_each(band);
        self.halo = halo;
    }

    /// The first half-sweep from `x = 0` on row `y`: the cells of `colour` get `b / diag`,
    /// the others 0.
    fn start_row(&self, row: &mut [f32], y: usize, colour: usize, b: &[f32]) {
        let w = self.dims.w;
        let o = y * w;
        let first = (colour + y) % 2;
        start_kernel(
            row,
            &b[o..o + w],
            &self.inv_diag[o..o + w],
            &self.mask[first..first + w],
        );
    }

    /// Gauss-Seidel on the cells of `colour` in row `r` of each of the three planes' rows (row
    /// `r` at height `y`; `b` holds the three planes); the rows next to it must be there
    /// unless `y` is the first or last. The three planes go through one kernel, so the row's
    /// weights are read once for all of them.
    fn relax_rows(
        &self,
        op: &Operator,
        planes: &mut [Vec<&mut [f32]>],
        r: usize,
        y: usize,
        b: &[f32],
        colour: usize,
    ) {
        let Dims { w, h } = self.dims;
        let (n, o) = (w * h, y * w);
        let zeros = &self.zeros[..w];
        let [p0, p1, p2] = planes else {
            unreachable!("three planes")
        };
        let (x0, up0, down0) = neighbours(p0, r, y, h, zeros);
        let (x1, up1, down1) = neighbours(p1, r, y, h, zeros);
        let (x2, up2, down2) = neighbours(p2, r, y, h, zeros);
        let br = |c: usize| &b[c * n + o..c * n + o + w];
        // The last row's `ey` is 0; above the first row, `zeros` stands in.
        let ey_up = if y >= 1 { &op.ey[o - w..o] } else { zeros };
        let first = (colour + y) % 2;
        relax_kernel(
            [x0, x1, x2],
            [
                [br(0), up0, down0],
                [br(1), up1, down1],
                [br(2), up2, down2],
            ],
            [
                ey_up,
                &op.ey[o..o + w],
                &op.ex[o..o + w],
                &self.inv_diag[o..o + w],
            ],
            &self.mask[first..first + w],
        );
    }

    /// `coarse_b = P^T (b - A x)` on all three planes.
    fn restrict_residual(
        &self,
        op: &Operator,
        x: &[f32],
        b: &[f32],
        coarse: Dims,
        coarse_b: &mut [f32],
    ) {
        let Dims { w, h } = self.dims;
        let (n, cn, cw) = (w * h, coarse.len(), coarse.w);
        let (b0, rest) = coarse_b.split_at_mut(cn);
        let (b1, b2) = rest.split_at_mut(cn);
        // The three channels of a fine row one after the other: its weights are read from
        // memory once.
        let each = |row_buf: &mut Vec<f32>, (cy, ((o0, o1), o2)): Rows3<'_>| {
            row_buf.resize(w, 0.0);
            let mut outs = [o0, o1, o2];
            for out in outs.iter_mut() {
                out.fill(0.0);
            }
            for y in 2 * cy..(2 * cy + 2).min(h) {
                for (c, out) in outs.iter_mut().enumerate() {
                    let (x, b) = (&x[c * n..(c + 1) * n], &b[c * n..(c + 1) * n]);
                    self.residual_row(op, x, b, y, row_buf);
                    add_pair_sums(out, row_buf);
                }
            }
        };
        b0.par_chunks_mut(cw)
            .zip(b1.par_chunks_mut(cw))
            .zip(b2.par_chunks_mut(cw))
            .enumerate()
            .with_min_len(min_len(n))
            .for_each_init(Vec::new, each);
    }

    /// `out = (b - A x)` on row `y` of one plane, branch-free inside the row (the weights of
    /// missing edges are 0, and the rows outside are skipped).
    fn residual_row(&self, op: &Operator, x: &[f32], b: &[f32], y: usize, out: &mut [f32]) {
        let Dims { w, h } = self.dims;
        let o = y * w;
        let zeros = &self.zeros[..];
        let (ey_up, up) = if y >= 1 {
            (&op.ey[o - w..o], &x[o - w..o])
        } else {
            (zeros, zeros)
        };
        let down = if y + 1 < h {
            &x[o + w..o + 2 * w]
        } else {
            zeros
        };
        residual_kernel(
            &mut out[..w],
            [
                &x[o..o + w],
                &b[o..o + w],
                &op.data[o..o + w],
                &op.ex[o..o + w],
                ey_up,
                up,
                &op.ey[o..o + w],
                down,
            ],
        );
    }
}

/// Row `r` of one plane's rows (at height `y` of `h`) and the rows above and below it, or
/// `zeros` where the frame has none.
fn neighbours<'a>(
    rows: &'a mut [&mut [f32]],
    r: usize,
    y: usize,
    h: usize,
    zeros: &'a [f32],
) -> (&'a mut [f32], &'a [f32], &'a [f32]) {
    let (before, rest) = rows.split_at_mut(r);
    let (cur, after) = rest.split_first_mut().expect("row r exists");
    let up: &[f32] = if y >= 1 { &*before[r - 1] } else { zeros };
    let down: &[f32] = if y + 1 < h { &*after[0] } else { zeros };
    (&mut **cur, up, down)
}

/// `row[i] += coarse[i / 2]`: one row of the prolongation (a last odd cell included).
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn add_pairs(row: &mut [f32], coarse: &[f32]) {
    let half = row.len() / 2;
    let mut pairs = row.chunks_exact_mut(2);
    for (pair, &v) in (&mut pairs).zip(coarse) {
        pair[0] += v;
        pair[1] += v;
    }
    if let ([last], Some(&v)) = (pairs.into_remainder(), coarse.get(half)) {
        *last += v;
    }
}

/// `out[i] += row[2 i] + row[2 i + 1]` (a last odd cell alone): one fine row's share of the
/// restriction `P^T`. A loop over `chunks(2)` with an iterator sum did not vectorise and cost
/// as much as a smoothing pass; the bits are the same (`out` starts at +0, which absorbs the
/// sign of a zero pair).
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn add_pair_sums(out: &mut [f32], row: &[f32]) {
    let half = row.len() / 2;
    let (out_pairs, row_pairs) = (&mut out[..half], &row[..2 * half]);
    for (k, o) in out_pairs.iter_mut().enumerate() {
        *o += row_pairs[2 * k] + row_pairs[2 * k + 1];
    }
    if row.len() % 2 == 1 {
        out[half] += row[2 * half];
    }
}

/// `x = b / diag` where `keep` (the cells of one colour), else 0: a half-sweep from zero.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn start_kernel(x: &mut [f32], b: &[f32], inv: &[f32], keep: &[bool]) {
    let w = x.len();
    let (b, inv, keep) = (&b[..w], &inv[..w], &keep[..w]);
    for i in 0..w {
        x[i] = if keep[i] { b[i] * inv[i] } else { 0.0 };
    }
}

/// `out = b - A x` on one row (see [`Level::residual_row`]); missing neighbours have weight 0.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn residual_kernel(out: &mut [f32], rows: [&[f32]; 8]) {
    let w = out.len();
    let [x, b, data, ex, ey_up, up, ey_down, down] = rows.map(|r| &r[..w]);
    for i in 0..w {
        let c = x[i];
        out[i] = b[i] - data[i] * c - ey_up[i] * (c - up[i]) - ey_down[i] * (c - down[i]);
    }
    if w >= 2 {
        // Horizontal edge (i, i + 1) with flux ex[i] (x[i] - x[i + 1]).
        out[0] -= ex[0] * (x[0] - x[1]);
        out[w - 1] -= ex[w - 2] * (x[w - 1] - x[w - 2]);
        for ((v, x3), e2) in out[1..w - 1]
            .iter_mut()
            .zip(x.windows(3))
            .zip(ex.windows(2))
        {
            *v -= e2[0] * (x3[1] - x3[0]) + e2[1] * (x3[1] - x3[2]);
        }
    }
}

/// Gauss-Seidel on one row of each of the three planes: every cell's new value from its
/// current neighbours, kept where `keep` (the cells of one colour; the others are their
/// neighbours, which this half-sweep does not change, so a cell's value is the same whether
/// its neighbour was updated first). `rows` are each plane's right-hand side and the rows
/// above and below; `weights` the shared `ey` above, `ey` below, `ex` and `1 / diag`.
/// The row goes in blocks of [`LANES`] cells: a block's weights are loaded once for the
/// three planes, and each plane's block is computed in registers from three overlapping
/// loads, then stored one block late: the next block's loads reach one cell into this one,
/// and a load that overlaps a store still in flight waits for it (store forwarding fails on
/// partial overlaps). Storing late changes no value: a kept cell's neighbours are all of the
/// other colour, which this half-sweep leaves as they are. Rust never fuses multiply-adds, so
/// every target gives the same bits.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn relax_kernel(cur: [&mut [f32]; 3], rows: [[&[f32]; 3]; 3], weights: [&[f32]; 4], keep: &[bool]) {
    let w = keep.len();
    let weights = weights.map(|r| &r[..w]);
    if w <= LANES + 1 {
        // Narrow rows (coarse levels): cell by cell.
        for (cur, rows) in cur.into_iter().zip(rows) {
            relax_narrow(cur, rows, weights, keep);
        }
        return;
    }
    let [ey_up, ey_down, ex, inv] = weights;
    let [x0, x1, x2] = cur;
    let mut planes = [(x0, rows[0]), (x1, rows[1]), (x2, rows[2])];
    let ends = planes
        .each_ref()
        .map(|(cur, rows)| row_ends(cur, *rows, weights));
    let mut s = 1;
    // The previous block's output of each plane, and where it goes.
    let mut pending = [[0.0f32; LANES]; 3];
    let mut pending_at = None;
    while s + LANES < w {
        let block = |v: &[f32], from: usize| -> [f32; LANES] {
            v[from..from + LANES].try_into().expect("in range")
        };
        let (eu, ed, el, er, iv) = (
            block(ey_up, s),
            block(ey_down, s),
            block(ex, s - 1),
            block(ex, s),
            block(inv, s),
        );
        let kk: &[bool; LANES] = keep[s..s + LANES].try_into().expect("in range");
        for ((cur, [b, up, down]), pending) in planes.iter_mut().zip(pending.iter_mut()) {
            let (left, mid, right) = (block(cur, s - 1), block(cur, s), block(cur, s + 1));
            let (bb, uu, dd) = (block(b, s), block(up, s), block(down, s));
            let mut out = [0.0f32; LANES];
            for k in 0..LANES {
                let t = bb[k] + eu[k] * uu[k] + ed[k] * dd[k];
                let t = t + (el[k] * left[k] + er[k] * right[k]);
                out[k] = if kk[k] { t * iv[k] } else { mid[k] };
            }
            if let Some(at) = pending_at {
                cur[at..at + LANES].copy_from_slice(pending);
            }
            *pending = out;
        }
        pending_at = Some(s);
        s += LANES;
    }
    if let Some(at) = pending_at {
        for ((cur, _), pending) in planes.iter_mut().zip(&pending) {
            cur[at..at + LANES].copy_from_slice(pending);
        }
    }
    for ((cur, rows), ends) in planes.iter_mut().zip(ends) {
        relax_from(cur, *rows, weights, keep, s, ends);
    }
}

/// [`relax_kernel`] on one plane, cell by cell (for rows of up to [`LANES`] + 1 cells).
fn relax_narrow(cur: &mut [f32], rows: [&[f32]; 3], weights: [&[f32]; 4], keep: &[bool]) {
    if keep.len() < 2 {
        let ([b, up, down], [ey_up, ey_down, _, inv]) = (rows, weights);
        if keep.first() == Some(&true) {
            cur[0] = (b[0] + ey_up[0] * up[0] + ey_down[0] * down[0]) * inv[0];
        }
        return;
    }
    let ends = row_ends(cur, rows, weights);
    relax_from(cur, rows, weights, keep, 1, ends);
}

/// The new values of a row's first and last cells (at least two), from the values before the
/// half-sweep (see [`relax_kernel`] for `rows` and `weights`).
fn row_ends(cur: &[f32], rows: [&[f32]; 3], weights: [&[f32]; 4]) -> (f32, f32) {
    let ([b, up, down], [ey_up, ey_down, ex, inv]) = (rows, weights);
    let w = cur.len();
    let vertical = |i: usize| b[i] + ey_up[i] * up[i] + ey_down[i] * down[i];
    (
        (vertical(0) + ex[0] * cur[1]) * inv[0],
        (vertical(w - 1) + ex[w - 2] * cur[w - 2]) * inv[w - 1],
    )
}

/// Relaxes the cells `from..w - 1` of a row one by one, then stores its `ends` (from
/// [`row_ends`]) where `keep`.
fn relax_from(
    cur: &mut [f32],
    rows: [&[f32]; 3],
    weights: [&[f32]; 4],
    keep: &[bool],
    from: usize,
    (first, last): (f32, f32),
) {
    let ([b, up, down], [ey_up, ey_down, ex, inv]) = (rows, weights);
    let w = keep.len();
    for i in from..w - 1 {
        let t = b[i] + ey_up[i] * up[i] + ey_down[i] * down[i];
        let t = t + (ex[i - 1] * cur[i - 1] + ex[i] * cur[i + 1]);
        if keep[i] {
            cur[i] = t * inv[i];
        }
    }
    if keep[0] {
        cur[0] = first;
    }
    if keep[w - 1] {
        cur[w - 1] = last;
    }
}

/// Cells per block of [`relax_kernel`]: one AVX-512 register of `f32`.
const LANES: usize = 16;

#[cfg(test)]
mod tests {
    use super::*;

    /// `A u` for one plane of a level's operator, written independently of the cycle's passes.
    fn apply(level: &Operator, dims: Dims, u: &[f32]) -> Vec<f32> {
        let Dims { w, h } = dims;
        let mut out = vec![0.0; w * h];
        for y in 0..h {
            for i in 0..w {
                let p = y * w + i;
                out[p] += level.data[p] * u[p];
                if i + 1 < w {
                    let f = level.ex[p] * (u[p] - u[p + 1]);
                    out[p] += f;
                    out[p + 1] -= f;
                }
                if y + 1 < h {
                    let f = level.ey[p] * (u[p] - u[p + w]);
                    out[p] += f;
                    out[p + w] -= f;
                }
            }
        }
        out
    }

    /// Iterations of preconditioned CG from 0 to a relative residual of 1e-5 (at most 2000).
    fn pcg(
        op: &Operator,
        dims: Dims,
        b: &[f32],
        mut precondition: impl FnMut(&[f32], &mut [f32]),
    ) -> usize {
        let n = b.len();
        let dot = |a: &[f32], b: &[f32]| {
            a.iter()
                .zip(b)
                .map(|(&a, &b)| f64::from(a) * f64::from(b))
                .sum::<f64>()
        };
        let r0 = dot(b, b).sqrt();
        let (mut x, mut r, mut z) = (vec![0.0f32; n], b.to_vec(), vec![0.0f32; n]);
        precondition(&r, &mut z);
        let mut p = z.clone();
        let mut rz = dot(&r, &z);
        for it in 1..=2000 {
            let q = apply(op, dims, &p);
            let a = (rz / dot(&p, &q)) as f32;
            for i in 0..n {
                x[i] += a * p[i];
                r[i] -= a * q[i];
            }
            if dot(&r, &r).sqrt() <= 1e-5 * r0 {
                return it;
            }
            precondition(&r, &mut z);
            let rz_new = dot(&r, &z);
            for i in 0..n {
                p[i] = z[i] + (rz_new / rz) as f32 * p[i];
            }
            rz = rz_new;
        }
        2000
    }

    fn weights(n: usize, seed: u32) -> Vec<f32> {
        // Weights over five orders of magnitude, like late IRLS steps.
        (0..n)
            .map(|i| {
                let t = ((i as u32).wrapping_mul(2654435761) ^ seed) % 1000;
                10f32.powf(t as f32 / 200.0 - 2.5)
            })
            .collect()
    }

    /// A planned multigrid for a fine operator of random weights, and that operator.
    fn operator(w: usize, h: usize) -> (Multigrid, Operator) {
        let n = w * h;
        let mut op = Operator {
            data: weights(n, 1).into_iter().map(|v| 0.04 * v).collect(),
            ex: weights(n, 2),
            ey: weights(n, 3),
        };
        op.ex.chunks_mut(w).for_each(|r| r[w - 1] = 0.0);
        op.ey[(h - 1) * w..].fill(0.0);
        let mut mg = Multigrid::new(Dims { w, h }).unwrap();
        mg.set_operator(&op);
        (mg, op)
    }

    /// One half-sweep of red-black Gauss-Seidel on one plane, cell by cell, with the
    /// kernel's order of operations (from `x = 0` with `start`).
    fn half_sweep(
        level: &Level,
        op: &Operator,
        x: &mut [f32],
        b: &[f32],
        colour: usize,
        start: bool,
    ) {
        let Dims { w, h } = level.dims;
        for y in 0..h {
            for i in 0..w {
                let p = y * w + i;
                if (i + y) % 2 != colour {
                    if start {
                        x[p] = 0.0;
                    }
                    continue;
                }
                if start {
                    x[p] = b[p] * level.inv_diag[p];
                    continue;
                }
                let (ey_up, up) = if y >= 1 {
                    (op.ey[p - w], x[p - w])
                } else {
                    (0.0, 0.0)
                };
                let down = if y + 1 < h { x[p + w] } else { 0.0 };
                let mut t = b[p] + ey_up * up + op.ey[p] * down;
                if w >= 2 {
                    t += if i == 0 {
                        op.ex[p] * x[p + 1]
                    } else if i == w - 1 {
                        op.ex[p - 1] * x[p - 1]
                    } else {
                        op.ex[p - 1] * x[p - 1] + op.ex[p] * x[p + 1]
                    };
                }
                x[p] = t * level.inv_diag[p];
            }
        }
    }

    /// The fused smoothing pass (wavefront, halo copies, prolongation folded in, parallel
    /// bands on the large frame) gives the plain sweeps' bits, on frames whose last band is
    /// short, and ignores `x` from zero (NaN there stays out).
    #[test]
    fn smoothing_is_plain_red_black_gauss_seidel() {
        for (w, h) in [(37, 75), (64, 70), (5, 33), (40, 1), (1, 40), (200, 170)] {
            let n = w * h;
            let (mut mg, op) = operator(w, h);
            let cd = Dims {
                w: w.div_ceil(2),
                h: h.div_ceil(2),
            };
            let b: Vec<f32> = (0..3 * n).map(|i| (i as f32 * 0.61).sin()).collect();
            let coarse_x: Vec<f32> = (0..3 * cd.len()).map(|i| (i as f32 * 0.3).cos()).collect();
            let level = &mut mg.levels[0];
            let colours = |first: usize| (0..HALF_SWEEPS).map(move |j| (first + j) % 2);

            let mut x = vec![f32::NAN; 3 * n];
            level.smooth(&op, &mut x, &b, 0, true, None, None);
            let mut plain = vec![f32::NAN; 3 * n];
            for c in 0..3 {
                let (x, b) = (&mut plain[c * n..(c + 1) * n], &b[c * n..(c + 1) * n]);
                for (j, colour) in colours(0).enumerate() {
                    half_sweep(level, &op, x, b, colour, j == 0);
                }
            }
            let bits = |v: &[f32]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&x), bits(&plain), "{w}x{h} from zero");

            let correction = Correction {
                coarse_x: &coarse_x,
                coarse: cd,
            };
            level.smooth(&op, &mut x, &b, 1, false, Some(correction), None);
            for c in 0..3 {
                let (x, b) = (&mut plain[c * n..(c + 1) * n], &b[c * n..(c + 1) * n]);
                for (p, x) in x.iter_mut().enumerate() {
                    *x += coarse_x[c * cd.len() + (p / w / 2) * cd.w + (p % w) / 2];
                }
                for colour in colours(1) {
                    half_sweep(level, &op, x, b, colour, false);
                }
            }
            assert_eq!(bits(&x), bits(&plain), "{w}x{h} with a correction");
        }
    }

    /// The coarse operator is the Galerkin product `P^T A P`: for random coarse `v`,
    /// `A_c v == P^T A (P v)`, with `A` applied independently; every level's inverse diagonal
    /// is its operator's.
    #[test]
    fn coarse_levels_are_galerkin_products() {
        for (w, h) in [(7, 5), (8, 6), (1, 9), (13, 1)] {
            let (mg, op) = operator(w, h);
            for l in 0..mg.levels.len() - 1 {
                let (fine, coarse) = (&mg.levels[l], &mg.levels[l + 1]);
                let fine_op = if l == 0 { &op } else { &fine.op };
                let v: Vec<f32> = (0..coarse.dims.len())
                    .map(|i| (i as f32 * 0.7).sin())
                    .collect();
                let pv: Vec<f32> = (0..fine.dims.len())
                    .map(|p| {
                        let (y, x) = (p / fine.dims.w, p % fine.dims.w);
                        v[(y / 2) * coarse.dims.w + x / 2]
                    })
                    .collect();
                let apv = apply(fine_op, fine.dims, &pv);
                let mut ptapv = vec![0.0f32; coarse.dims.len()];
                for (p, a) in apv.iter().enumerate() {
                    let (y, x) = (p / fine.dims.w, p % fine.dims.w);
                    ptapv[(y / 2) * coarse.dims.w + x / 2] += a;
                }
                // The fine level's inverse diagonal, made in the same pass: 1 / (data + the
                // weights of the cell's edges).
                let Dims { w: fw, h: fh } = fine.dims;
                for p in 0..fw * fh {
                    let (x, y) = (p % fw, p / fw);
                    let mut d = fine_op.data[p] + fine_op.ex[p] + fine_op.ey[p];
                    if x >= 1 {
                        d += fine_op.ex[p - 1];
                    }
                    if y >= 1 {
                        d += fine_op.ey[p - fw];
                    }
                    assert!(
                        (fine.inv_diag[p] - 1.0 / d).abs() <= 1e-6 / d,
                        "{w}x{h} level {l} cell {p}"
                    );
                }
                let av = apply(&coarse.op, coarse.dims, &v);
                for (a, b) in av.iter().zip(&ptapv) {
                    assert!(
                        (a - b).abs() <= 1e-4 * (1.0 + b.abs()),
                        "{w}x{h} level {l}: {a} {b}"
                    );
                }
            }
        }
    }

    /// The cycle is symmetric (`u . B v == v . B u`) and positive (`v . B v > 0`), as
    /// conjugate gradients needs, and makes CG converge fast on weights that jump by five
    /// orders of magnitude from cell to cell.
    #[test]
    fn the_cycle_returns_plane_sums_of_r_dot_z() {
        // Several bands, rows not a multiple of the kernel's blocks: the dot products summed
        // in the last pass are those of `plane_sums` on the result, bit for bit.
        let (w, h) = (203, 150);
        let n = w * h;
        let (mut mg, op) = operator(w, h);
        let r: Vec<f32> = (0..3 * n).map(|i| (i as f32 * 0.013).sin()).collect();
        let mut z = vec![0.0; 3 * n];
        let dots = mg.apply(&op, &r, &mut z);
        let sums = crate::recon::ops::plane_sums(&r, &z, w, n, &mut Vec::new(), |a, b| {
            f64::from(a) * f64::from(b)
        });
        assert_eq!(dots.to_vec(), sums);
        assert!(dots.iter().all(|&d| d > 0.0));
    }

    #[test]
    fn the_cycle_is_spd_and_converges() {
        let (w, h) = (37, 23);
        let n = w * h;
        let (mut mg, op) = operator(w, h);
        let u: Vec<f32> = (0..3 * n)
            .map(|i| ((i * 7 % 11) as f32 - 5.0) / 3.0)
            .collect();
        let v: Vec<f32> = (0..3 * n).map(|i| (i as f32 * 0.37).cos()).collect();
        let (mut bu, mut bv) = (vec![0.0; 3 * n], vec![0.0; 3 * n]);
        mg.apply(&op, &u, &mut bu);
        mg.apply(&op, &v, &mut bv);
        let dot = |a: &[f32], b: &[f32]| {
            a.iter()
                .zip(b)
                .map(|(&a, &b)| f64::from(a * b))
                .sum::<f64>()
        };
        let (ubv, vbu) = (dot(&u, &bv), dot(&v, &bu));
        assert!(
            (ubv - vbu).abs() <= 1e-4 * ubv.abs().max(vbu.abs()),
            "{ubv} {vbu}"
        );
        assert!(dot(&v, &bv) > 0.0 && dot(&u, &bu) > 0.0);
        // Conjugate gradients on plane 0 to a relative residual of 1e-5: preconditioned by the
        // cycle, in a handful of iterations, several times fewer than with Jacobi's.
        let b: Vec<f32> = v[..n].to_vec();
        let (dims, inv_diag) = (mg.levels[0].dims, mg.levels[0].inv_diag.clone());
        let cycle_its = pcg(&op, dims, &b, |r, z| {
            let (mut r3, mut z3) = (vec![0.0; 3 * n], vec![0.0; 3 * n]);
            r3[..n].copy_from_slice(r);
            mg.apply(&op, &r3, &mut z3);
            z.copy_from_slice(&z3[..n]);
        });
        let jacobi_its = pcg(&op, dims, &b, |r, z| {
            for ((z, &r), &d) in z.iter_mut().zip(r).zip(&inv_diag) {
                *z = r * d;
            }
        });
        assert!(
            cycle_its <= 25 && 3 * cycle_its <= jacobi_its,
            "{cycle_its} vs {jacobi_its}"
        );
    }
}
