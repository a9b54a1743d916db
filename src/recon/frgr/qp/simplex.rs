//! The lane-parallel simplex QP solver: the release's vertex sweeps with exact line search,
//! [`LANES`] pixels in lockstep, on the low-rank form of `Q`.

use super::lanes::{F32x, I32x, Mask, LANES};
use super::level::MAX_N;

/// The solver's O(K n) start: projections `s = B w`, `w^T diag(v) w` and the squared column
/// norms of `B`. Sums start from -0.0 like `Iterator::sum`, in the scalar solver's order.
pub(crate) struct Start<const K: usize> {
    pub(super) s: [F32x; K],
    pub(super) svw: F32x,
    pub(super) col2: [F32x; MAX_N],
}

impl<const K: usize> Start<K> {
    pub(super) fn new() -> Self {
        Start {
            s: [F32x::splat(-0.0); K],
            svw: F32x::splat(-0.0),
            col2: [F32x::splat(0.0); MAX_N],
        }
    }
}

/// [`LANES`] independent simplex QPs, lane `l` with `Q_l = B_l^T B_l + diag(v_l)`, `K` bias
/// rows each (rows of zeros are allowed).
pub(crate) struct Simplex<'a, const K: usize> {
    /// `b[q][r]`: entry `q` of bias row `r`, per lane.
    pub b: &'a [[F32x; K]],
    /// `v[q]`: the diagonal, per lane.
    pub v: &'a [F32x],
    pub n: usize,
}

impl<const K: usize> Simplex<'_, K> {
    /// Runs the cyclic vertex line search from `w` (`w[q]`, each lane on the simplex) on the
    /// lanes in `active`, in O(K) per iteration; returns each lane's number of iterations.
    ///
    /// Every lane follows the scalar release iteration (up to the order of sums: see the
    /// module `qp`): the lanes share the iteration counter (so the vertex `it mod n` and the
    /// once-per-sweep renormalisation), and a lane whose stopping rule fired, or that takes a
    /// tiny step, is masked out of the updates; no lane's bits depend on another's.
    #[cfg(test)]
    pub fn solve(&self, w: &mut [F32x], active: Mask, max_iter: usize) -> [u32; LANES] {
        self.solve_from::<true>(self.start(w), w, active, max_iter)
    }

    /// The O(K n) start of [`Simplex::solve`] from `w` (the filter gathers it while building
    /// the rows).
    #[cfg(test)]
    pub fn start(&self, w: &[F32x]) -> Start<K> {
        let mut st = Start::new();
        for (col2, bq) in st.col2.iter_mut().zip(&self.b[..self.n]) {
            for &br in bq {
                *col2 = *col2 + br * br;
            }
        }
        (st.s, st.svw) = self.project(w);
        st
    }

    /// `(B w, w^T diag(v) w)`, every sum over the neighbours in order from -0.0 (as
    /// `Iterator::sum`).
    #[cfg(test)]
    pub(super) fn project(&self, w: &[F32x]) -> ([F32x; K], F32x) {
        let (n, b, v) = (self.n, self.b, self.v);
        let mut s = [F32x::splat(-0.0); K];
        for (bq, &wq) in b[..n].iter().zip(&w[..n]) {
            for (sr, &br) in s.iter_mut().zip(bq) {
                *sr = *sr + br * wq;
            }
        }
        let mut svw = F32x::splat(-0.0);
        for (&vq, &wq) in v[..n].iter().zip(&w[..n]) {
            svw = svw + vq * wq * wq;
        }
        (s, svw)
    }

    /// `Simplex::solve` (the tests' entry point) from its start (which must be `self.start(w)`, bit for bit).
    #[inline(always)]
    pub fn solve_from<const FUSED: bool>(
        &self,
        start: Start<K>,
        w: &mut [F32x],
        active: Mask,
        max_iter: usize,
    ) -> [u32; LANES] {
        let (n, b, v) = (self.n, self.b, self.v);
        let Start {
            mut s,
            mut svw,
            col2,
        } = start;
        // `|s|^2`, kept up to date by each step (a lane that does not move keeps its bits).
        let mut ss = norm2(&s);
        let mut scale = F32x::splat(1.0);
        let mut quiet = I32x::default();
        let mut iters = I32x::default();
        let mut live = active;
        // `(Qw)_i` for the coming iteration, when the previous one computed it while updating
        // `s` (one pass over `s` per iteration instead of two).
        let mut ahead = None;
        let next = |i: usize| if i + 1 == n { 0 } else { i + 1 };
        let (mut it, mut i) = (0, 0);
        while it < max_iter {
            live = live & quiet.lt(n as i32);
            if !live.any() {
                break;
            }
            iters = iters.inc(live);
            it += 1;
            i = next(i);
            if i == 0 {
                self.renormalise(w, &mut s, &mut svw, &mut scale, live);
                ss = norm2(&s);
                ahead = None;
            }
            let (bi, vi) = (&b[i], v[i]);
            let wi = scale * w[i];
            // A `match`, not `unwrap_or_else`: a closure is not inlined into the multiversioned
            // solver, and compiled for the baseline CPU (where `madd` would fuse in software).
            let qw = match ahead.take() {
                Some(qw) => qw,
                None => vi * wi + dot3::<K, FUSED>(bi, &s),
            };
            let wqw = ss + svw;
            let dqw = qw - wqw;
            let dqd = col2[i] + vi - F32x::splat(2.0) * qw + wqw;
            let step = -dqw / dqd;
            let t = F32x::select(step.is_finite(), step.clamp01(), F32x::splat(0.0));
            let tiny = t.lt(F32x::splat(1e-8));
            let moving = live.and_not(tiny);
            quiet = quiet.inc_or_reset(live & tiny, moving);
            if !moving.any() {
                continue;
            }
            let keep = F32x::splat(1.0) - t;
            svw = F32x::select(moving, quadratic_step(svw, t, vi, wi), svw);
            let new_scale = keep * scale;
            let collapse = moving & new_scale.lt(F32x::splat(1e-12));
            let grow = moving.and_not(collapse);
            w[i] = F32x::select(grow, w[i] + t / new_scale, w[i]);
            scale = F32x::select(grow, new_scale, scale);
            if collapse.any() {
                // All weight on vertex i (the scale underflowed): rare.
                for wq in &mut w[..n] {
                    *wq = F32x::select(collapse, F32x::splat(0.0), *wq);
                }
                w[i] = F32x::select(collapse, F32x::splat(1.0), w[i]);
                scale = F32x::select(collapse, F32x::splat(1.0), scale);
            }
            // s <- keep s + t b_i, and the next iteration's sums of the new s, in the order
            // that iteration would use (unless it renormalises first). The lanes that do not
            // move take `1 s + 0 b_i` instead of a masked select: that is `s` again (up to the
            // sign of a zero `s`, which no magnitude, `t` or `w` ever depends on), and saves a
            // third of the loop.
            let t_s = F32x::select(moving, t, F32x::splat(0.0));
            let keep_s = F32x::splat(1.0) - t_s;
            // |keep s + t b_i|^2 from the sums already known: b_i . s = qw - v_i w_i.
            let bs = qw - vi * wi;
            ss = keep_s * keep_s * ss + F32x::splat(2.0) * keep_s * t_s * bs + t_s * t_s * col2[i];
            let j = next(i);
            let (bj, wj) = (&b[j], scale * w[j]);
            for (sr, &br) in s.iter_mut().zip(bi) {
                *sr = t_s.madd::<FUSED>(br, keep_s * *sr);
            }
            ahead = Some(v[j] * wj + dot3::<K, FUSED>(bj, &s));
        }
        for wq in &mut w[..n] {
            *wq = *wq * scale;
        }
        let mut counts = [0; LANES];
        for (count, &it) in counts.iter_mut().zip(&iters.0) {
            *count = it as u32;
        }
        counts
    }

    /// Once per sweep on the `live` lanes, in O(n + K): fold the scale in and renormalise the
    /// sum to 1 (the release's step, which also keeps f32 drift in `w` from accumulating), and
    /// scale the projections to match (the release recomputes them: O(K n), a fifth of the
    /// solve; the difference stays within the tests' 1e-5).
    #[inline(always)]
    pub(super) fn renormalise(
        &self,
        w: &mut [F32x],
        s: &mut [F32x; K],
        svw: &mut F32x,
        scale: &mut F32x,
        live: Mask,
    ) {
        let n = self.n;
        let mut total = F32x::splat(-0.0);
        for &wq in &w[..n] {
            total = total + wq;
        }
        // The true weights `scale w` sum to `sum`: divided by it, and so are the projections.
        let sum = total * *scale;
        let factor = *scale / sum;
        for wq in &mut w[..n] {
            *wq = F32x::select(live, *wq * factor, *wq);
        }
        let g = F32x::splat(1.0) / sum;
        for sr in s.iter_mut() {
            *sr = F32x::select(live, *sr * g, *sr);
        }
        *svw = F32x::select(live, *svw * g * g, *svw);
        *scale = F32x::select(live, F32x::splat(1.0), *scale);
    }
}

/// `w^T diag(v) w` after the step `w <- (1 - t) w + t e_i`, with `wi` the old `w_i`: the
/// release's expression, operation for operation. Its result passes through `black_box`:
/// otherwise, inside the solver loop, LLVM's SLP vectoriser splits this four-factor product
/// into scalar lanes (measured: ~250 instructions per iteration instead of ~30). The barrier
/// costs a store and a load of the result; the call it replaces (`#[inline(never)]`, compiled
/// for the baseline CPU) cost a spill of the solver's registers and a store-forwarding stall
/// on its 16-byte stores (measured: QP 12-15 % faster without the call, the same bits).
#[inline(always)]
pub(super) fn quadratic_step(svw: F32x, t: F32x, vi: F32x, wi: F32x) -> F32x {
    let keep = F32x::splat(1.0) - t;
    std::hint::black_box(keep * keep * svw + F32x::splat(2.0) * t * keep * vi * wi + t * t * vi)
}

/// `|s|^2`.
#[inline(always)]
fn norm2<const K: usize>(s: &[F32x; K]) -> F32x {
    let mut ss = F32x::splat(0.0);
    for &sr in s {
        ss = ss + sr * sr;
    }
    ss
}

/// `b . s` in three partial sums (rows `r mod 3`: every `K` is a multiple of 3), so that the
/// solver's critical path is a third as long as one chain of `K` additions.
#[inline(always)]
fn dot3<const K: usize, const FUSED: bool>(b: &[F32x; K], s: &[F32x; K]) -> F32x {
    let mut acc = [F32x::splat(0.0); 3];
    for (r, (&br, &sr)) in b.iter().zip(s).enumerate() {
        acc[r % 3] = br.madd::<FUSED>(sr, acc[r % 3]);
    }
    acc[0] + acc[1] + acc[2]
}
