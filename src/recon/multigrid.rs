//! An algebraic multigrid V-cycle for the weighted screened Poisson systems of IRLS: the
//! preconditioner that follows the weights where the DCT solve cannot.
//!
//! Every level holds an operator of one form, a graph Laplacian on a `w x h` grid plus a
//! diagonal:
//! `(A u)(p) = data(p) u(p) + sum over the grid edges (p, q) of e(p, q) (u(p) - u(q))`,
//! with one weight per horizontal edge (`ex`, zero in the last column) and per vertical edge
//! (`ey`, zero in the last row). The fine level is the IRLS system (`data = alpha^2 w_d`,
//! `ex = w_x`, `ey = w_y`).
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
//! within a colour, cells do not depend on each other, and the rows next to a band are read
//! from a copy taken before the half-sweep (they are of the other colour, so unchanged by it).

use rayon::prelude::*;

use super::ops::Dims;
use crate::error::Result;
use crate::image::try_vec;

/// Red-black sweeps before (and after) each coarse correction. One sweep needed 1.5x the CG
/// iterations of two (125 against 86 on the 720p synthetic frame) for less than half the
/// saving in cost; three saved few more iterations (73).
const SWEEPS: usize = 2;

/// Rows per parallel band. Levels smaller than [`PARALLEL_CELLS`] run on one thread.
const BAND: usize = 32;
const PARALLEL_CELLS: usize = 1 << 15;

/// Row `k` (of rows or bands) of three planes, as the parallel passes hand them out.
type Rows3<'a> = (usize, ((&'a mut [f32], &'a mut [f32]), &'a mut [f32]));

/// One level's operator and (below the fine level) its vectors.
#[derive(Clone)]
struct Level {
    dims: Dims,
    data: Vec<f32>,
    ex: Vec<f32>,
    ey: Vec<f32>,
    /// `1 / diag(A)` (0 where the diagonal is 0).
    inv_diag: Vec<f32>,
    /// Solution and right-hand side, three planes each; empty on the fine level, whose
    /// vectors are the caller's.
    x: Vec<f32>,
    b: Vec<f32>,
    /// Copies of the rows next to each band (see the module comment).
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
}

/// Bytes a [`Multigrid`] for `w x h` frames holds: four operator planes and the halo on every
/// level, and six vector planes below the fine one (the coarse levels add a third of the
/// fine level's size).
pub(crate) fn multigrid_bytes(w: usize, h: usize) -> u64 {
    let n = (w * h) as u64;
    // Fine level: 4 planes; coarse levels: (4 + 6) planes over n / 3 cells in all.
    4 * (4 * n + 10 * n.div_ceil(3)) + 4 * 6 * w as u64 * (h.div_ceil(BAND) as u64 + 1)
}

impl Multigrid {
    /// Allocates every level for `dims` (fails with `OutOfMemory`).
    pub fn new(dims: Dims) -> Result<Self> {
        let mut levels = Vec::new();
        let mut d = dims;
        loop {
            let n = d.len();
            let fine = levels.is_empty();
            levels.push(Level {
                dims: d,
                data: try_vec(n, 0.0)?,
                ex: try_vec(n, 0.0)?,
                ey: try_vec(n, 0.0)?,
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
                halo: try_vec(6 * d.w * d.h.div_ceil(BAND), 0.0)?,
                zeros: try_vec(d.w, 0.0)?,
                mask: (0..=d.w).map(|i| i % 2 == 0).collect(),
            });
            if n == 1 {
                return Ok(Multigrid { levels });
            }
            d = Dims {
                w: d.w.div_ceil(2),
                h: d.h.div_ceil(2),
            };
        }
    }

    /// Sets the fine operator to `alpha2 wd + D_x^T W_x D_x + D_y^T W_y D_y` (the weights of
    /// edges that do not exist must be 0) and rebuilds the coarse levels.
    pub fn set_operator(&mut self, alpha2: f32, wd: &[f32], wx: &[f32], wy: &[f32]) {
        let fine = &mut self.levels[0];
        let w = fine.dims.w;
        fine.data
            .par_chunks_mut(w)
            .zip(wd.par_chunks(w))
            .for_each(|(d, s)| d.iter_mut().zip(s).for_each(|(d, &s)| *d = alpha2 * s));
        fine.ex.copy_from_slice(wx);
        fine.ey.copy_from_slice(wy);
        fine.update_inv_diag();
        for l in 1..self.levels.len() {
            let (done, rest) = self.levels.split_at_mut(l);
            rest[0].aggregate(&done[l - 1]);
            rest[0].update_inv_diag();
        }
    }

    /// `z = B r`, one V-cycle from zero on each of the three planes of `r`.
    pub fn apply(&mut self, r: &[f32], z: &mut [f32]) {
        cycle(&mut self.levels, z, r);
    }
}

/// One V-cycle on `levels[0]` from `x = 0`.
fn cycle(levels: &mut [Level], x: &mut [f32], b: &[f32]) {
    let (level, coarser) = levels.split_first_mut().expect("at least one level");
    let Some(coarse) = coarser.first_mut() else {
        // One cell: A is the scalar data(0).
        for (x, &b) in x.iter_mut().zip(b) {
            *x = b * level.inv_diag[0];
        }
        return;
    };
    level.sweep(x, b, 0, true);
    for _ in 1..SWEEPS {
        level.sweep(x, b, 0, false);
    }
    let cd = coarse.dims;
    let (mut cx, mut cb) = (std::mem::take(&mut coarse.x), std::mem::take(&mut coarse.b));
    level.restrict_residual(x, b, cd, &mut cb);
    cycle(coarser, &mut cx, &cb);
    level.prolong_add(x, &cx, cd);
    (coarser[0].x, coarser[0].b) = (cx, cb);
    for _ in 0..SWEEPS {
        level.sweep(x, b, 1, false);
    }
}

impl Level {
    fn update_inv_diag(&mut self) {
        let Dims { w, .. } = self.dims;
        let (data, ex, ey) = (&self.data, &self.ex, &self.ey);
        let each = |(y, row): (usize, &mut [f32])| {
            let o = y * w;
            for (i, v) in row.iter_mut().enumerate() {
                let mut d = data[o + i] + ex[o + i] + ey[o + i];
                if i >= 1 {
                    d += ex[o + i - 1];
                }
                if y >= 1 {
                    d += ey[o + i - w];
                }
                *v = if d > 0.0 { 1.0 / d } else { 0.0 };
            }
        };
        if self.dims.len() >= PARALLEL_CELLS {
            self.inv_diag.par_chunks_mut(w).enumerate().for_each(each);
        } else {
            self.inv_diag.chunks_mut(w).enumerate().for_each(each);
        }
    }

    /// The Galerkin operator of `fine` under 2 x 2 aggregation (see the module comment).
    fn aggregate(&mut self, fine: &Level) {
        let Dims { w: fw, h: fh } = fine.dims;
        let cw = self.dims.w;
        let each = |(cy, ((data, ex), ey)): Rows3<'_>| {
            let y0 = 2 * cy;
            let ys = if y0 + 1 < fh { y0..y0 + 2 } else { y0..y0 + 1 };
            for cx in 0..cw {
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
        if fine.dims.len() >= PARALLEL_CELLS {
            self.data
                .par_chunks_mut(cw)
                .zip(self.ex.par_chunks_mut(cw))
                .zip(self.ey.par_chunks_mut(cw))
                .enumerate()
                .for_each(each);
        } else {
            self.data
                .chunks_mut(cw)
                .zip(self.ex.chunks_mut(cw))
                .zip(self.ey.chunks_mut(cw))
                .enumerate()
                .for_each(each);
        }
    }

    /// Copies the rows above and below every band of `x` into the halo.
    fn fill_halo(&self, halo: &mut [f32], x: &[f32]) {
        let Dims { w, h } = self.dims;
        let n = w * h;
        for (k, halo) in halo.chunks_mut(6 * w).take(h.div_ceil(BAND)).enumerate() {
            let (top, bottom) = (k * BAND, ((k + 1) * BAND).min(h));
            for c in 0..3 {
                if top >= 1 {
                    let o = c * n + (top - 1) * w;
                    halo[2 * c * w..(2 * c + 1) * w].copy_from_slice(&x[o..o + w]);
                }
                if bottom < h {
                    let o = c * n + bottom * w;
                    halo[(2 * c + 1) * w..(2 * c + 2) * w].copy_from_slice(&x[o..o + w]);
                }
            }
        }
    }

    /// One red-black Gauss-Seidel sweep on all three planes of `x`: the cells of colour
    /// `first` (`(x + y) % 2 == first`), then the others. With `from_zero`, `x` is taken as
    /// 0 and the first half-sweep reads no neighbours.
    ///
    /// The two half-sweeps run in one pass over each band, the second one row behind the
    /// first, so the band is read once; only the band's first and last rows, which need the
    /// neighbouring bands' first half, wait for a second, short pass. The result is the
    /// plain sweep's, bit for bit.
    fn sweep(&mut self, x: &mut [f32], b: &[f32], first: usize, from_zero: bool) {
        let Dims { w, h } = self.dims;
        let n = w * h;
        let second = 1 - first;
        let mut halo = std::mem::take(&mut self.halo);
        if !from_zero {
            self.fill_halo(&mut halo, x);
        }
        let this = &*self;
        let start_row = |band: &mut [f32], r: usize, top: usize, b: &[f32]| {
            let o = (top + r) * w;
            let (row, b, inv) = (
                &mut band[r * w..(r + 1) * w],
                &b[o..o + w],
                &this.inv_diag[o..o + w],
            );
            let parity = (first + top + r) % 2;
            for (i, ((x, &b), &d)) in row.iter_mut().zip(b).zip(inv).enumerate() {
                *x = if i % 2 == parity { b * d } else { 0.0 };
            }
        };
        // Pass 1: the first colour everywhere, the second on rows inside the band.
        let inner = |(k, ((p0, p1), p2)): Rows3<'_>| {
            let halo = &halo[6 * w * k..6 * w * (k + 1)];
            let top = k * BAND;
            let mut tmp = vec![0.0f32; w];
            for (c, band) in [p0, p1, p2].into_iter().enumerate() {
                let (halo, b) = (&halo[2 * c * w..(2 * c + 2) * w], &b[c * n..(c + 1) * n]);
                let rows = band.len() / w;
                for r in 0..rows {
                    if from_zero {
                        start_row(band, r, top, b);
                    } else {
                        this.relax_row(band, r, top, halo, b, first, &mut tmp);
                    }
                    if r >= 2 {
                        this.relax_row(band, r - 1, top, halo, b, second, &mut tmp);
                    }
                }
            }
        };
        this.over_bands(x, &inner);
        this.fill_halo(&mut halo, x);
        // Pass 2: the second colour on each band's first and last rows.
        let edges = |(k, ((p0, p1), p2)): Rows3<'_>| {
            let halo = &halo[6 * w * k..6 * w * (k + 1)];
            let top = k * BAND;
            let mut tmp = vec![0.0f32; w];
            for (c, band) in [p0, p1, p2].into_iter().enumerate() {
                let (halo, b) = (&halo[2 * c * w..(2 * c + 2) * w], &b[c * n..(c + 1) * n]);
                let rows = band.len() / w;
                this.relax_row(band, 0, top, halo, b, second, &mut tmp);
                if rows > 1 {
                    this.relax_row(band, rows - 1, top, halo, b, second, &mut tmp);
                }
            }
        };
        this.over_bands(x, &edges);
        self.halo = halo;
    }

    /// Runs `f` on every band of the three planes of `x`, in parallel on large levels.
    fn over_bands<F>(&self, x: &mut [f32], f: &F)
    where
        F: for<'a> Fn(Rows3<'a>) + Sync,
    {
        let n = self.dims.len();
        let (x0, rest) = x.split_at_mut(n);
        let (x1, x2) = rest.split_at_mut(n);
        let rows = BAND * self.dims.w;
        if n >= PARALLEL_CELLS {
            x0.par_chunks_mut(rows)
                .zip(x1.par_chunks_mut(rows))
                .zip(x2.par_chunks_mut(rows))
                .enumerate()
                .for_each(f);
        } else {
            x0.chunks_mut(rows)
                .zip(x1.chunks_mut(rows))
                .zip(x2.chunks_mut(rows))
                .enumerate()
                .for_each(f);
        }
    }

    /// Gauss-Seidel on the cells of `colour` in row `r` of `band` (one plane's rows from
    /// `top`); `halo` holds the rows above and below the band.
    #[allow(clippy::too_many_arguments)]
    fn relax_row(
        &self,
        band: &mut [f32],
        r: usize,
        top: usize,
        halo: &[f32],
        b: &[f32],
        colour: usize,
        tmp: &mut [f32],
    ) {
        let Dims { w, h } = self.dims;
        let rows = band.len() / w;
        let y = top + r;
        let (before, rest) = band.split_at_mut(r * w);
        let (cur, after) = rest.split_at_mut(w);
        let up = if r >= 1 {
            &before[(r - 1) * w..]
        } else {
            &halo[..w]
        };
        let down = if r + 1 < rows {
            &after[..w]
        } else {
            &halo[w..]
        };
        let o = y * w;
        let (ex, inv, br) = (&self.ex[o..o + w], &self.inv_diag[o..o + w], &b[o..o + w]);
        // Missing neighbours have weight 0 (the last row's `ey` is 0; above the first
        // row, `zeros` stands in).
        let ey_down = &self.ey[o..o + w];
        let (ey_up, up) = if y >= 1 {
            (&self.ey[o - w..o], up)
        } else {
            (&self.zeros[..], &self.zeros[..])
        };
        let down = if y + 1 < h { down } else { &self.zeros[..] };
        let first = (colour + y) % 2;
        relax_kernel(
            &mut tmp[..w],
            cur,
            [br, ey_up, up, ey_down, down, ex, inv],
            &self.mask[first..first + w],
        );
    }

    /// `coarse_b = P^T (b - A x)` on all three planes.
    fn restrict_residual(&self, x: &[f32], b: &[f32], coarse: Dims, coarse_b: &mut [f32]) {
        let Dims { w, h } = self.dims;
        let (n, cw, ch) = (w * h, coarse.w, coarse.h);
        let each = |row_buf: &mut Vec<f32>, (row, out): (usize, &mut [f32])| {
            let (c, cy) = (row / ch, row % ch);
            let (x, b) = (&x[c * n..(c + 1) * n], &b[c * n..(c + 1) * n]);
            out.fill(0.0);
            row_buf.resize(w, 0.0);
            for y in 2 * cy..(2 * cy + 2).min(h) {
                self.residual_row(x, b, y, row_buf);
                for (o, pair) in out.iter_mut().zip(row_buf.chunks(2)) {
                    *o += pair.iter().sum::<f32>();
                }
            }
        };
        if n >= PARALLEL_CELLS {
            coarse_b
                .par_chunks_mut(cw)
                .enumerate()
                .for_each_init(Vec::new, each);
        } else {
            let mut row_buf = Vec::new();
            coarse_b
                .chunks_mut(cw)
                .enumerate()
                .for_each(|item| each(&mut row_buf, item));
        }
    }

    /// `out = (b - A x)` on row `y` of one plane, branch-free inside the row (the weights of
    /// missing edges are 0, and the rows outside are skipped).
    fn residual_row(&self, x: &[f32], b: &[f32], y: usize, out: &mut [f32]) {
        let Dims { w, h } = self.dims;
        let o = y * w;
        let zeros = &self.zeros[..];
        let (ey_up, up) = if y >= 1 {
            (&self.ey[o - w..o], &x[o - w..o])
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
                &self.data[o..o + w],
                &self.ex[o..o + w],
                ey_up,
                up,
                &self.ey[o..o + w],
                down,
            ],
        );
    }

    /// `x += P coarse_x` on all three planes.
    fn prolong_add(&self, x: &mut [f32], coarse_x: &[f32], coarse: Dims) {
        let Dims { w, h } = self.dims;
        let (cw, ch) = (coarse.w, coarse.h);
        let each = |(row, out): (usize, &mut [f32])| {
            let (c, y) = (row / h, row % h);
            let o = c * cw * ch + (y / 2) * cw;
            for (pair, &v) in out.chunks_mut(2).zip(&coarse_x[o..o + cw]) {
                for x in pair {
                    *x += v;
                }
            }
        };
        if w * h >= PARALLEL_CELLS {
            x.par_chunks_mut(w).enumerate().for_each(each);
        } else {
            x.chunks_mut(w).enumerate().for_each(each);
        }
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

/// Gauss-Seidel on one row: every cell's new value from its current neighbours (in SIMD,
/// into `t`), kept where `keep` (the cells of one colour; the others are their neighbours).
/// Rust never fuses multiply-adds, so every target gives the same bits.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn relax_kernel(t: &mut [f32], cur: &mut [f32], rows: [&[f32]; 7], keep: &[bool]) {
    let w = t.len();
    let [b, ey_up, up, ey_down, down, ex, inv] = rows.map(|r| &r[..w]);
    let (cur, keep) = (&mut cur[..w], &keep[..w]);
    for i in 0..w {
        t[i] = b[i] + ey_up[i] * up[i] + ey_down[i] * down[i];
    }
    if w >= 2 {
        t[0] += ex[0] * cur[1];
        t[w - 1] += ex[w - 2] * cur[w - 2];
        for ((t, c3), e2) in t[1..w - 1]
            .iter_mut()
            .zip(cur.windows(3))
            .zip(ex.windows(2))
        {
            *t += e2[0] * c3[0] + e2[1] * c3[2];
        }
    }
    for i in 0..w {
        let new = t[i] * inv[i];
        cur[i] = if keep[i] { new } else { cur[i] };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `A u` for one plane of a level, written independently of the cycle's passes.
    fn apply(level: &Level, u: &[f32]) -> Vec<f32> {
        let Dims { w, h } = level.dims;
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
    fn pcg(op: &Level, b: &[f32], mut precondition: impl FnMut(&[f32], &mut [f32])) -> usize {
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
            let q = apply(op, &p);
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

    fn operator(w: usize, h: usize) -> (Multigrid, Vec<f32>, Vec<f32>, Vec<f32>) {
        let n = w * h;
        let wd = weights(n, 1);
        let mut wx = weights(n, 2);
        let mut wy = weights(n, 3);
        wx.chunks_mut(w).for_each(|r| r[w - 1] = 0.0);
        wy[(h - 1) * w..].fill(0.0);
        let mut mg = Multigrid::new(Dims { w, h }).unwrap();
        mg.set_operator(0.04, &wd, &wx, &wy);
        (mg, wd, wx, wy)
    }

    /// The coarse operator is the Galerkin product `P^T A P`: for random coarse `v`,
    /// `A_c v == P^T A (P v)`, with `A` applied independently.
    #[test]
    fn coarse_levels_are_galerkin_products() {
        for (w, h) in [(7, 5), (8, 6), (1, 9), (13, 1)] {
            let (mg, ..) = operator(w, h);
            for l in 0..mg.levels.len() - 1 {
                let (fine, coarse) = (&mg.levels[l], &mg.levels[l + 1]);
                let v: Vec<f32> = (0..coarse.dims.len())
                    .map(|i| (i as f32 * 0.7).sin())
                    .collect();
                let pv: Vec<f32> = (0..fine.dims.len())
                    .map(|p| {
                        let (y, x) = (p / fine.dims.w, p % fine.dims.w);
                        v[(y / 2) * coarse.dims.w + x / 2]
                    })
                    .collect();
                let apv = apply(fine, &pv);
                let mut ptapv = vec![0.0f32; coarse.dims.len()];
                for (p, a) in apv.iter().enumerate() {
                    let (y, x) = (p / fine.dims.w, p % fine.dims.w);
                    ptapv[(y / 2) * coarse.dims.w + x / 2] += a;
                }
                let av = apply(coarse, &v);
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
    fn the_cycle_is_spd_and_converges() {
        let (w, h) = (37, 23);
        let n = w * h;
        let (mut mg, ..) = operator(w, h);
        let u: Vec<f32> = (0..3 * n)
            .map(|i| ((i * 7 % 11) as f32 - 5.0) / 3.0)
            .collect();
        let v: Vec<f32> = (0..3 * n).map(|i| (i as f32 * 0.37).cos()).collect();
        let (mut bu, mut bv) = (vec![0.0; 3 * n], vec![0.0; 3 * n]);
        mg.apply(&u, &mut bu);
        mg.apply(&v, &mut bv);
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
        let op = Level {
            x: Vec::new(),
            b: Vec::new(),
            ..mg.levels[0].clone()
        };
        let cycle_its = pcg(&op, &b, |r, z| {
            let (mut r3, mut z3) = (vec![0.0; 3 * n], vec![0.0; 3 * n]);
            r3[..n].copy_from_slice(r);
            mg.apply(&r3, &mut z3);
            z.copy_from_slice(&z3[..n]);
        });
        let jacobi_its = pcg(&op, &b, |r, z| {
            for ((z, &r), &d) in z.iter_mut().zip(r).zip(&op.inv_diag) {
                *z = r * d;
            }
        });
        assert!(
            cycle_its <= 25 && 3 * cycle_its <= jacobi_its,
            "{cycle_its} vs {jacobi_its}"
        );
    }
}
