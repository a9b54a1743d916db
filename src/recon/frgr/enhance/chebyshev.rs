//! The enhancement's remaining descent steps at once, as one polynomial of the energy's Hessian.
//!
//! The energy is quadratic with Hessian `H` (per channel, shared by R, G, B: `(H v)_p = sum
//! over p's edges e = (p, q) of a_e (v_p - v_q)`). Plain gradient descent with step `s` from
//! `x_0` gives, after `N` steps, `x_N = x_0 + s q_N(sH) r_0` with `r_0 = -grad E(x_0)` and
//! `q_N(z) = sum_{j<N} (1 - z)^j = (1 - (1 - z)^N) / z` (Landweber's polynomial). Once
//! `s lambda_max(H) < 2` the steps lower the energy monotonically, so the schedule can revert
//! no more and its result is exactly those `N` steps; a bound `lambda_B >= lambda_max`
//! (Anderson and Morley's, `super::edge_bound`) tells when.
//!
//! `q_N` is smooth on `[0, z_max]`, `z_max = s lambda_B < 2`, so its Chebyshev series
//! converges fast: truncated where the remaining coefficients sum to less than [`TOLERANCE`]
//! of `q_N(0) = N`, it needs a degree of a few `sqrt(N z_max)` (250 steps at `z_max = 1.48`, as
//! on the bundled sample and the 720p synthetic frame: 46 products with `H`; 1000: 92) instead
//! of `N` steps. The series is evaluated by the
//! three-term recurrence `v_{k+1} = 2 T v_k - v_{k-1}`, `T = (2 / z_max) sH - I` (spectrum in
//! `[-1, 1]`, so `|v_k| <= |r_0|` and rounding grows only linearly with the degree), its terms
//! summed apart and added to the image at the end. Each channel is done alone (the channels
//! share `H` and are independent), so that the planes a product touches (two terms of the
//! recurrence, their sum, the weights) stay in the last-level cache at 1280 x 720; its rows run
//! in parallel, each row's values computed the same way for any thread count. A product reads
//! five planes and writes two for about ten operations a pixel, so memory is its cost: past the
//! first, the terms go two to a sweep over the rows (`Operator::two_terms`), the second term's
//! row following the first's one row behind, while the rows it reads are in cache (the same
//! values, tested bit for bit).

use rayon::prelude::*;

use super::{edge_fluxes, flush, Sweeper};
use crate::progress::Progress;

/// Truncation: the series stops where the magnitudes of the remaining coefficients sum to
/// less than this fraction of `q_N(0) = N`, which bounds the error of the step sum relative to
/// its largest gain. At 1e-7 (until the sixty-second session) the image's error was f32
/// rounding (in the tests: 1e-6 gave 3.1e-6 of the image against exact arithmetic, 1e-7
/// 1.5e-6, 1e-8 and 1e-10 1.4e-6, the f32 steps 5e-7). 1e-4 takes 46 products instead of 65
/// at 250 steps (the enhancement about 15 % faster) and moves FRGR's output by at most 2.1e-4
/// of its peak on the validation frames (relMSE between the two outputs at most 4e-9), its
/// relMSE against the references by at most 0.001 % on validation and 0.008 % on test
/// (`docs/benchmarks.md`, sixty-second session); 1e-3 (38 products) moved it by 1.2e-3.
pub(super) const TOLERANCE: f64 = 1e-4;

/// Rows per parallel task.
const ROWS: usize = 8;

/// The Chebyshev coefficients of `q_steps(z)` on `[0, z_max]` (the first halved, so that
/// `q = sum_k c_k T_k(t)`, `z = z_max (1 + t) / 2`), truncated per [`TOLERANCE`]; `None` when
/// the series would be no shorter than the steps themselves (few steps) or does not resolve.
pub(super) fn series(steps: usize, z_max: f64) -> Option<Vec<f64>> {
    if steps < 2 || !(z_max > 0.0 && z_max < 2.0) {
        return None;
    }
    let n = steps as f64;
    // Interpolation nodes: enough that the coefficients past the truncation are resolved (they
    // decay faster than exponentially beyond a degree of a few sqrt(N z_max)).
    let m = ((12.0 * (n * z_max).sqrt()).ceil() as usize + 32).min(4096);
    let q = |z: f64| -> f64 {
        if z <= 0.0 {
            n
        } else if z < 1.0 {
            // 1 - (1 - z)^N without cancellation for small z.
            -(n * (-z).ln_1p()).exp_m1() / z
        } else {
            (1.0 - (1.0 - z).powi(steps.min(i32::MAX as usize) as i32)) / z
        }
    };
    let theta = |j: usize| std::f64::consts::PI * (j as f64 + 0.5) / m as f64;
    let values: Vec<f64> = (0..m)
        .map(|j| q(z_max * (1.0 + theta(j).cos()) / 2.0))
        .collect();
    let mut c: Vec<f64> = (0..m)
        .map(|k| {
            let sum: f64 = (0..m)
                .map(|j| values[j] * (k as f64 * theta(j)).cos())
                .sum();
            2.0 * sum / m as f64
        })
        .collect();
    c[0] /= 2.0;
    // The shortest series whose tail is below the tolerance, the tail taken over the second
    // half of the nodes' coefficients as well (which must be negligible: resolved).
    let mut tail = 0.0;
    let mut degree = m - 1;
    for k in (0..m).rev() {
        tail += c[k].abs();
        if tail > TOLERANCE * n {
            degree = k;
            break;
        }
    }
    (degree + 1 < steps.min(m / 2)).then(|| {
        c.truncate(degree + 1);
        c
    })
}

/// `x <- x + s q(sH) (-grad E(x))` for the three channel planes of `x`, `q` given by its
/// Chebyshev coefficients on `[0, z_max]` ([`series`], at least two); `scratch` holds at least
/// three planes. Returns `false` when `stop` was cancelled (then `x` is partly updated). The
/// terms are summed apart and added to `x` at the end: added to the image one by one, each
/// would be rounded at the image's magnitude, not the update's (measured: 6x the error of the
/// f32 steps against exact arithmetic, instead of less).
pub(super) fn descend(
    sweeper: &Sweeper,
    x: &mut [f32],
    scratch: &mut [f32],
    step: f32,
    z_max: f64,
    coefficients: &[f64],
    stop: &Progress,
) -> bool {
    assert!(coefficients.len() >= 2, "a series of degree 1 at least");
    let (w, n) = (sweeper.w, sweeper.w * sweeper.h);
    let (va, rest) = scratch.split_at_mut(n);
    let (vb, rest) = rest.split_at_mut(n);
    let sum = &mut rest[..n];
    let alpha = (2.0 * f64::from(step) / z_max) as f32;
    let coef = |k: usize| (f64::from(step) * coefficients[k]) as f32;
    for (c, x) in x.chunks_exact_mut(n).enumerate() {
        let op = Operator { sweeper, c };
        // v_0 = -grad E(x) into va.
        {
            let x = &*x;
            va.par_chunks_mut(ROWS * w).enumerate().for_each_init(
                || (vec![0.0f32; w + 1], vec![0.0f32; w]),
                |(across, fluxes), (i, out)| {
                    for (j, row) in out.chunks_exact_mut(w).enumerate() {
                        op.descent_row(x, i * ROWS + j, row, across, fluxes);
                    }
                },
            );
        }
        // v_1 = T v_0 into vb, and sum = s (c_0 v_0 + c_1 v_1); then each v_k into the older
        // of the two, and sum += s c_k v_k; at the end x += sum.
        let (mut older, mut newer) = (&mut *va, &mut *vb);
        let mut k = 1;
        while k < coefficients.len() {
            if stop.stopped() {
                return false;
            }
            // Past the first term, two terms at a time while two are left: one sweep over
            // memory instead of two.
            if k >= 2 && k + 1 < coefficients.len() {
                op.two_terms(older, newer, sum, alpha, [coef(k), coef(k + 1)]);
                k += 2;
                continue;
            }
            let (ck, first) = (coef(k), (k == 1).then(|| coef(0)));
            // k == 1: `older` holds v_0 (the term multiplied), `newer` receives v_1.
            let (cur, out): (&[f32], &mut [f32]) = if k == 1 {
                (&*older, &mut *newer)
            } else {
                (&*newer, &mut *older)
            };
            out.par_chunks_mut(ROWS * w)
                .zip(sum.par_chunks_mut(ROWS * w))
                .enumerate()
                .for_each(|(i, (out, sum))| {
                    let rows = out.chunks_exact_mut(w).zip(sum.chunks_exact_mut(w));
                    for (j, (o, su)) in rows.enumerate() {
                        op.product_row(cur, i * ROWS + j, o, su, alpha, ck, first);
                    }
                });
            if k > 1 {
                std::mem::swap(&mut older, &mut newer);
            }
            k += 1;
        }
        x.par_chunks_mut(ROWS * w)
            .zip(sum.par_chunks(ROWS * w))
            .for_each(|(x, sum)| {
                for (x, &d) in x.iter_mut().zip(sum) {
                    *x = flush(*x + d);
                }
            });
    }
    true
}

/// One row of one term of the recurrence, `t = alpha * H v - v` (`T v`, `v` = `v_k`, rows
/// `up`, `mid`, `down` of it; `a` of the row's horizontal edges, indexed by the left pixel, and
/// of the vertical ones above and below): with `first = Some(s c_0)` (k = 0 -> 1) `out = t`
/// (v_1) and `sum = s c_0 mid + coef * t`; else `out = 2 t - out` (v_{k+1} over v_{k-1}) and
/// `sum += coef * out`. A missing edge has `a = 0` (its neighbour row is then any finite row).
#[allow(clippy::too_many_arguments)]
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn product_row(
    [up, mid, down]: [&[f32]; 3],
    [ax, a_up, a_down]: [&[f32]; 3],
    out: &mut [f32],
    sum: &mut [f32],
    alpha: f32,
    coef: f32,
    first: Option<f32>,
) {
    let w = out.len();
    let img = sum;
    let (up, mid, down, img) = (&up[..w], &mid[..w], &down[..w], &mut img[..w]);
    let (ax, a_up, a_down) = (&ax[..w], &a_up[..w], &a_down[..w]);
    let vertical = |x: usize| a_up[x] * (mid[x] - up[x]) + a_down[x] * (mid[x] - down[x]);
    // H v at the row's two ends (one pixel: no horizontal edge), then its interior.
    let mut ends = [0.0f32; 2];
    if w == 1 {
        ends[0] = vertical(0);
    } else {
        ends[0] = ax[0] * (mid[0] - mid[1]) + vertical(0);
        ends[1] = ax[w - 2] * (mid[w - 1] - mid[w - 2]) + vertical(w - 1);
    }
    let term = |hv: f32, m: f32, prev: f32, im: f32| -> (f32, f32) {
        let t = alpha * hv - m;
        match first {
            Some(c0) => {
                let t = flush(t);
                (t, flush(c0 * m + coef * t))
            }
            None => {
                let v = flush(2.0 * t - prev);
                (v, flush(im + coef * v))
            }
        }
    };
    for (k, x) in [0, w - 1].into_iter().enumerate().take(w.min(2)) {
        (out[x], img[x]) = term(ends[k], mid[x], out[x], img[x]);
    }
    if w < 3 {
        return;
    }
    let m = w - 2;
    let (ml, mc, mr) = (&mid[..m], &mid[1..m + 1], &mid[2..m + 2]);
    let (al, ac) = (&ax[..m], &ax[1..m + 1]);
    let (u, d, au, ad) = (
        &up[1..m + 1],
        &down[1..m + 1],
        &a_up[1..m + 1],
        &a_down[1..m + 1],
    );
    let (o, im) = (&mut out[1..m + 1], &mut img[1..m + 1]);
    // Two loops rather than one with `term`: the branch on `first` inside would not vectorise.
    match first {
        Some(c0) => {
            for x in 0..m {
                let c = mc[x];
                let hv = al[x] * (c - ml[x])
                    + ac[x] * (c - mr[x])
                    + au[x] * (c - u[x])
                    + ad[x] * (c - d[x]);
                let t = flush(alpha * hv - c);
                o[x] = t;
                im[x] = flush(c0 * c + coef * t);
            }
        }
        None => {
            for x in 0..m {
                let c = mc[x];
                let hv = al[x] * (c - ml[x])
                    + ac[x] * (c - mr[x])
                    + au[x] * (c - u[x])
                    + ad[x] * (c - d[x]);
                let v = flush(2.0 * (alpha * hv - c) - o[x]);
                o[x] = v;
                im[x] = flush(im[x] + coef * v);
            }
        }
    }
}

/// One channel of the energy's operator.
struct Operator<'a> {
    sweeper: &'a Sweeper,
    c: usize,
}

/// Rows per parallel task of [`Operator::two_terms`]: its first and last rows take a second,
/// shorter pass.
const BAND: usize = 32;

/// One band of rows of `v_{k-1}` for [`Operator::two_terms`]: its first and last rows (read
/// only while the bands run: the bands beside read them), the rows between (overwritten by
/// `v_{k+1}`), and the neighbouring bands' last and first rows.
struct Band<'a> {
    /// The band's first row and its number of rows.
    start: usize,
    rows: usize,
    above: Option<&'a [f32]>,
    first: &'a [f32],
    inner: &'a mut [f32],
    last: &'a [f32],
    below: Option<&'a [f32]>,
}

impl Band<'_> {
    /// Row `y` of `v_{k-1}`, `y` in the band or next to it.
    fn row(&self, y: usize, w: usize) -> &[f32] {
        let end = self.start + self.rows;
        if y + 1 == self.start {
            self.above.expect("a band above")
        } else if y == self.start {
            self.first
        } else if y + 1 == end {
            self.last
        } else if y == end {
            self.below.expect("a band below")
        } else {
            &self.inner[(y - self.start - 1) * w..][..w]
        }
    }
}

impl Operator<'_> {
    /// The rows above, at and below `y` of a plane, and the vertical edges' `a` above and
    /// below, as [`product_row`] takes them (at the image's first and last rows, the row itself
    /// and the zero `a` of the last row's missing edges).
    fn neighbours<'v>(
        &self,
        y: usize,
        row: impl Fn(usize) -> &'v [f32],
    ) -> ([&'v [f32]; 3], [&[f32]; 2])
    where
        Self: 'v,
    {
        let s = self.sweeper;
        let (w, h) = (s.w, s.h);
        let mid = row(y);
        let (up, a_up) = if y > 0 {
            (row(y - 1), &s.ay[(y - 1) * w..y * w])
        } else {
            (mid, &s.ay[(h - 1) * w..h * w])
        };
        let down = if y + 1 < h { row(y + 1) } else { mid };
        ([up, mid, down], [a_up, &s.ay[y * w..(y + 1) * w]])
    }

    /// Terms `k` and `k + 1` of the recurrence (`k >= 2`) in one sweep: `older` holds
    /// `v_{k-2}` and becomes `v_k`, `newer` holds `v_{k-1}` and becomes `v_{k+1}`, and `sum +=
    /// coefs[0] v_k` then `+= coefs[1] v_{k+1}`: per row the values and the order of two calls
    /// of [`Operator::product_row`], but row `y - 1` of `v_{k+1}` follows row `y` of `v_k`
    /// while the rows it reads are still in cache (the product reads five planes and writes
    /// two: memory, not arithmetic, is its cost). Bands of [`BAND`] rows run in parallel;
    /// `v_{k+1}` on a band's first and last rows needs `v_k` from the bands beside, and it
    /// would overwrite rows of `v_{k-1}` they read, so those rows follow once every band is
    /// done.
    fn two_terms(
        &self,
        older: &mut [f32],
        newer: &mut [f32],
        sum: &mut [f32],
        alpha: f32,
        coefs: [f32; 2],
    ) {
        let s = self.sweeper;
        let (w, h) = (s.w, s.h);
        let ax = |y: usize| &s.ax[y * w..(y + 1) * w];
        // `newer` cut into bands: first and last rows shared, the rows between owned.
        let mut bands: Vec<Band> = Vec::with_capacity(h.div_ceil(BAND));
        let mut rest = &mut *newer;
        for start in (0..h).step_by(BAND) {
            let rows = BAND.min(h - start);
            let (band, tail) = std::mem::take(&mut rest).split_at_mut(rows * w);
            rest = tail;
            let (first, band) = band.split_at_mut(w);
            let (inner, last): (&mut [f32], &[f32]) = if rows == 1 {
                (&mut [], &*first)
            } else {
                let (inner, last) = band.split_at_mut((rows - 2) * w);
                (inner, last)
            };
            bands.push(Band {
                start,
                rows,
                above: None,
                first,
                inner,
                last,
                below: None,
            });
        }
        for i in 1..bands.len() {
            (bands[i].above, bands[i - 1].below) = (Some(bands[i - 1].last), Some(bands[i].first));
        }
        bands
            .into_par_iter()
            .zip(older.par_chunks_mut(BAND * w))
            .zip(sum.par_chunks_mut(BAND * w))
            .for_each(|((band, older), sum)| {
                let start = band.start;
                for t in 0..band.rows {
                    let y = start + t;
                    // v_k at row y, over v_{k-2}.
                    let (v, [a_up, a_down]) = self.neighbours(y, |r| band.row(r, w));
                    let (out, su) = (&mut older[t * w..][..w], &mut sum[t * w..][..w]);
                    product_row(v, [ax(y), a_up, a_down], out, su, alpha, coefs[0], None);
                    // v_{k+1} at row y - 1 (inside the band), over v_{k-1}.
                    if t >= 2 {
                        let older = &*older;
                        let (v, [a_up, a_down]) =
                            self.neighbours(y - 1, |r| &older[(r - start) * w..][..w]);
                        let out = &mut band.inner[(t - 2) * w..][..w];
                        let su = &mut sum[(t - 1) * w..][..w];
                        product_row(v, [ax(y - 1), a_up, a_down], out, su, alpha, coefs[1], None);
                    }
                }
            });
        // v_{k+1} on each band's first and last rows, from v_k now complete.
        let older = &*older;
        newer
            .par_chunks_mut(w)
            .zip(sum.par_chunks_mut(w))
            .enumerate()
            .filter(|&(y, _)| y % BAND == 0 || y % BAND == BAND - 1 || y + 1 == h)
            .for_each(|(y, (out, su))| {
                let (v, [a_up, a_down]) = self.neighbours(y, |r| &older[r * w..][..w]);
                product_row(v, [ax(y), a_up, a_down], out, su, alpha, coefs[1], None);
            });
    }

    /// Row `y` of one term of the recurrence from `v` (= `v_k`, a channel plane): see
    /// [`product_row`]; the missing edges of the image's first and last rows and columns have
    /// `a = 0` in the sweeper's planes, but for the row above the first, read as `zeros`.
    #[allow(clippy::too_many_arguments)]
    fn product_row(
        &self,
        v: &[f32],
        y: usize,
        out: &mut [f32],
        img: &mut [f32],
        alpha: f32,
        coef: f32,
        first: Option<f32>,
    ) {
        let w = self.sweeper.w;
        let (rows, [a_up, a_down]) = self.neighbours(y, |r| &v[r * w..(r + 1) * w]);
        let ax = &self.sweeper.ax[y * w..(y + 1) * w];
        product_row(rows, [ax, a_up, a_down], out, img, alpha, coef, first);
    }

    /// Row `y` of `-grad E(v)` into `out`, `v` one channel plane: per pixel `right - left +
    /// below - above` over its edges' fluxes, each row of fluxes by the steps' own kernel
    /// ([`edge_fluxes`]); `across` (`w + 1`) and `fluxes` (`w`) are scratch.
    fn descent_row(
        &self,
        v: &[f32],
        y: usize,
        out: &mut [f32],
        across: &mut [f32],
        fluxes: &mut [f32],
    ) {
        let s = self.sweeper;
        let (w, h, n) = (s.w, s.h, s.w * s.h);
        let o = y * w;
        let mid = &v[o..o + w];
        // Horizontal fluxes with a zero on either side: `across[x + 1]` is edge `x -> x + 1`.
        across[0] = 0.0;
        across[w] = 0.0;
        let b = &s.bx[self.c * n + o..][..w - 1];
        edge_fluxes(
            &s.ax[o..o + w - 1],
            b,
            &mid[..w - 1],
            &mid[1..],
            &mut across[1..w],
        );
        for (x, out) in out.iter_mut().enumerate() {
            *out = across[x + 1] - across[x];
        }
        // The vertical edges: - flux(y - 1 -> y), + flux(y -> y + 1).
        for (r, sign) in [(y.wrapping_sub(1), -1.0f32), (y, 1.0)] {
            if r >= h - 1 {
                continue;
            }
            let (lo, hi) = (&v[r * w..(r + 1) * w], &v[(r + 1) * w..(r + 2) * w]);
            let b = &s.by[self.c * n + r * w..][..w];
            edge_fluxes(&s.ay[r * w..(r + 1) * w], b, lo, hi, fluxes);
            for (out, &f) in out.iter_mut().zip(&*fluxes) {
                *out += sign * f;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `sum_k c_k T_k(t)` by the recurrence, in f64.
    fn evaluate(c: &[f64], t: f64) -> f64 {
        let (mut prev, mut cur) = (1.0, t);
        let mut sum = c[0] + c.get(1).map_or(0.0, |c1| c1 * t);
        for &ck in c.iter().skip(2) {
            (prev, cur) = (cur, 2.0 * t * cur - prev);
            sum += ck * cur;
        }
        sum
    }

    #[test]
    fn the_series_is_landweber_polynomial_within_its_tolerance() {
        // The reference is the sum of the steps' factors itself, sum_{j<N} (1 - z)^j.
        for steps in [30, 250, 1000, 5000] {
            for z_max in [0.3, 1.0, 1.48, 1.99] {
                let c = series(steps, z_max).expect("shorter than the steps");
                assert!(c.len() < steps, "{steps} {z_max}: degree {}", c.len() - 1);
                for i in 0..=400 {
                    let z = z_max * i as f64 / 400.0;
                    let want: f64 = (0..steps).map(|j| (1.0 - z).powi(j as i32)).sum();
                    let got = evaluate(&c, 2.0 * z / z_max - 1.0);
                    let err = (got - want).abs() / steps as f64;
                    assert!(
                        err <= TOLERANCE,
                        "{steps} steps, z_max {z_max}, z {z}: {err:e}"
                    );
                }
            }
        }
    }

    #[test]
    fn two_terms_in_one_sweep_equal_two_sweeps_bit_for_bit() {
        // Heights around the band's (one and two rows left over, a band of one row, bands
        // of the whole image), widths of one pixel and odd ones.
        for (w, h) in [
            (1, 1),
            (5, 2),
            (3, 3),
            (17, 31),
            (4, 32),
            (9, 33),
            (6, 34),
            (5, 65),
            (1, 70),
        ] {
            let wave = |k| super::super::wave(3, w, h, k);
            let (dx, dy, albedo) = (wave(1), wave(2), wave(3));
            let wt = super::super::EnhanceWeights::new(&dx, &dy, Some(&albedo), None, 0.7).unwrap();
            let sweeper = Sweeper::new(dx.as_slice(), dy.as_slice(), &wt).unwrap();
            let n = w * h;
            let plane = |k| super::super::wave(1, w, h, k).as_slice().to_vec();
            let (alpha, coefs) = (0.37f32, [0.61f32, -0.23]);
            for c in 0..3 {
                let op = Operator {
                    sweeper: &sweeper,
                    c,
                };
                let (mut older, mut newer, mut sum) = (plane(4), plane(5), plane(6));
                // Two sweeps: v_k over v_{k-2}, then v_{k+1} over v_{k-1}.
                let (mut p, mut q, mut su) = (older.clone(), newer.clone(), sum.clone());
                for (k, coef) in coefs.into_iter().enumerate() {
                    let (cur, out) = if k == 0 {
                        (q.clone(), &mut p)
                    } else {
                        (p.clone(), &mut q)
                    };
                    for y in 0..h {
                        let (o, s) = (&mut out[y * w..][..w], &mut su[y * w..][..w]);
                        op.product_row(&cur, y, o, s, alpha, coef, None);
                    }
                }
                op.two_terms(&mut older, &mut newer, &mut sum, alpha, coefs);
                let bits = |v: &[f32]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&older), bits(&p), "{w} x {h}, v_k");
                assert_eq!(bits(&newer), bits(&q), "{w} x {h}, v_k+1");
                assert_eq!(bits(&sum), bits(&su), "{w} x {h}, sum");
                assert_eq!(older.len(), n);
            }
        }
    }

    #[test]
    fn few_steps_or_an_unstable_step_have_no_series() {
        assert!(series(8, 1.5).is_none());
        assert!(series(1000, 2.0).is_none());
        assert!(series(1000, 0.0).is_none());
        assert!(series(1000, f64::NAN).is_none());
    }
}
