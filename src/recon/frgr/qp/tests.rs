//! Tests of the lane-parallel filter: the solver against a dense evaluation, the exact
//! optimum (KKT) and the scalar release solver (within 1e-5; lanes independent bit for bit);
//! the whole filter against the one-pixel-at-a-time reference.

use super::*;

struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 40) as f32) / (1u64 << 24) as f32
    }
}

/// One problem in the scalar layout: rows `b[r][q]`, diagonal, start on the simplex.
type Problem = (Vec<[f32; MAX_N]>, Vec<f32>, Vec<f32>);

fn random_problem(rng: &mut Lcg, k: usize, n: usize) -> Problem {
    let b: Vec<[f32; MAX_N]> = (0..k)
        .map(|_| std::array::from_fn(|j| if j < n { rng.next() - 0.5 } else { 0.0 }))
        .collect();
    let v: Vec<f32> = (0..n).map(|_| 0.01 + 0.1 * rng.next()).collect();
    let mut w: Vec<f32> = (0..MAX_N)
        .map(|j| if j < n { 0.1 + rng.next() } else { 0.0 })
        .collect();
    let s: f32 = w.iter().sum();
    w.iter_mut().for_each(|x| *x /= s);
    (b, v, w)
}

/// Lane `l` gets `problems[l % len]`; rows past a problem's own are zero.
fn pack<const K: usize>(problems: &[Problem], n: usize) -> (Vec<[F32x; K]>, Vec<F32x>, Vec<F32x>) {
    let pick = |l: usize| &problems[l % problems.len()];
    let lanes = |f: &dyn Fn(&Problem) -> f32| F32x(std::array::from_fn(|l| f(pick(l))));
    let b = (0..n)
        .map(|q| std::array::from_fn(|r| lanes(&|p| p.0.get(r).map_or(0.0, |row| row[q]))))
        .collect();
    let v = (0..n).map(|q| lanes(&|p| p.1[q])).collect();
    let w = (0..MAX_N).map(|q| lanes(&|p| p.2[q])).collect();
    (b, v, w)
}

/// The same iteration evaluated densely: explicit Q, explicit renormalised w.
fn naive(b: &[[f32; MAX_N]], v: &[f32], n: usize, w: &mut [f64], max_iter: usize) {
    let q = |i: usize, j: usize| -> f64 {
        let mut s: f64 = b.iter().map(|r| f64::from(r[i]) * f64::from(r[j])).sum();
        if i == j {
            s += f64::from(v[i]);
        }
        s
    };
    let mut quiet = 0;
    let mut it = 0;
    while it < max_iter && quiet < n {
        it += 1;
        let i = it % n;
        let qw: Vec<f64> = (0..n)
            .map(|a| (0..n).map(|c| q(a, c) * w[c]).sum())
            .collect();
        let wqw: f64 = (0..n).map(|a| w[a] * qw[a]).sum();
        let dqw = qw[i] - wqw;
        let dqd = q(i, i) - 2.0 * qw[i] + wqw;
        let t = (-dqw / dqd).clamp(0.0, 1.0);
        if t < 1e-8 {
            quiet += 1;
            continue;
        }
        quiet = 0;
        for x in w[..n].iter_mut() {
            *x *= 1.0 - t;
        }
        w[i] += t;
        let s: f64 = w[..n].iter().sum();
        w[..n].iter_mut().for_each(|x| *x /= s);
    }
}

#[test]
fn incremental_solver_equals_a_dense_evaluation() {
    fn check<const K: usize>(rng: &mut Lcg, n: usize) {
        let problems: Vec<Problem> = (0..LANES).map(|_| random_problem(rng, K, n)).collect();
        let (b, v, mut fast) = pack::<K>(&problems, n);
        Simplex::<K> { b: &b, v: &v, n }.solve(
            &mut fast,
            Mask::from_bools([true; LANES]),
            3 * n + 1,
        );
        for (l, (pb, pv, w0)) in problems.iter().enumerate() {
            let mut slow: Vec<f64> = w0.iter().map(|&x| f64::from(x)).collect();
            naive(pb, pv, n, &mut slow, 3 * n + 1);
            let diff = (0..n)
                .map(|j| (f64::from(fast[j].0[l]) - slow[j]).abs())
                .fold(0.0, f64::max);
            assert!(
                diff < 1e-4,
                "k {K} n {n} lane {l}: max |w_fast - w_dense| = {diff:e}"
            );
        }
    }
    let mut rng = Lcg(7);
    check::<15>(&mut rng, 81);
    check::<6>(&mut rng, 49);
    check::<3>(&mut rng, 9);
    check::<1>(&mut rng, 25);
}

#[test]
fn lanes_follow_the_scalar_release_solver() {
    let mut rng = Lcg(11);
    let n = 49;
    let mut problems: Vec<Problem> = (0..LANES).map(|_| random_problem(&mut rng, 9, n)).collect();
    // Lane 1 starts at its optimum (stops after n quiet steps); lane 2 has a free vertex
    // (`Q e_5 = 0`: the step to it is 1 and the scale collapses); lane 3 is nearly flat.
    problems[1].0.iter_mut().for_each(|row| row.fill(0.0));
    problems[1].1.fill(0.05);
    problems[1].2[..n].fill(1.0 / n as f32);
    problems[2].0.iter_mut().for_each(|row| row[5] = 0.0);
    problems[2].1[5] = 0.0;
    problems[3]
        .0
        .iter_mut()
        .for_each(|row| row.iter_mut().for_each(|x| *x *= 1e-4));
    let (b, v, mut w) = pack::<9>(&problems, n);
    let active: [bool; LANES] = std::array::from_fn(|l| l != 6);
    let iters = Simplex::<9> { b: &b, v: &v, n }.solve(&mut w, Mask::from_bools(active), 3 * n + 1);
    let mut worst = 0.0f32;
    for (l, (pb, pv, w0)) in problems.iter().enumerate() {
        let mut scalar = w0.clone();
        let it = if active[l] {
            reference::Simplex { b: pb, v: pv, n }.solve(&mut scalar, 3 * n + 1)
        } else {
            0
        };
        assert_eq!(iters[l] as usize, it, "lane {l}");
        for q in 0..n {
            worst = worst.max((w[q].0[l] - scalar[q]).abs());
        }
        // A lane's result is its own: alone in a group, it is the same bits.
        let (b1, v1, mut alone) = pack::<9>(&[problems[l].clone()], n);
        let mask: [bool; LANES] = std::array::from_fn(|m| m == 0 && active[l]);
        Simplex::<9> { b: &b1, v: &v1, n }.solve(&mut alone, Mask::from_bools(mask), 3 * n + 1);
        for q in 0..n {
            assert_eq!(
                w[q].0[l].to_bits(),
                alone[q].0[0].to_bits(),
                "lane {l} q {q}"
            );
        }
    }
    // The release's arithmetic, up to the order of its sums (the projections are updated
    // rather than recomputed once per sweep, and summed in three chains): weights (which sum
    // to 1) within 1e-5. Measured: 3.0e-8.
    assert!(worst <= 1e-5, "max |w_lanes - w_release| = {worst:e}");
    assert!(
        iters[1] as usize == n && iters[0] as usize == 3 * n + 1,
        "{iters:?}"
    );
}

#[test]
fn solution_is_on_the_simplex_and_satisfies_kkt() {
    fn check<const K: usize>(rng: &mut Lcg, n: usize) {
        let (b, v, w0) = random_problem(rng, K, n);
        let problem = reference::Simplex { b: &b, v: &v, n };
        let mut exact = w0.clone();
        problem.solve_exact(&mut exact, 100_000, 1e-9);
        let (bl, vl, mut wl) = pack::<K>(&[(b.clone(), v.clone(), w0.clone())], n);
        Simplex::<K> { b: &bl, v: &vl, n }.solve(
            &mut wl,
            Mask::from_bools([true; LANES]),
            3 * n + 1,
        );
        let w: Vec<f32> = wl.iter().map(|x| x.0[0]).collect();
        // The release's early-stopped cyclic solver gets close to the optimum's objective.
        let obj = |w: &[f32]| -> f64 {
            let bw: f64 = b
                .iter()
                .map(|r| {
                    (0..n)
                        .map(|j| f64::from(r[j]) * f64::from(w[j]))
                        .sum::<f64>()
                        .powi(2)
                })
                .sum();
            bw + (0..n)
                .map(|j| f64::from(v[j]) * f64::from(w[j]).powi(2))
                .sum::<f64>()
        };
        let (start, fast, best) = (obj(&w0), obj(&w), obj(&exact));
        assert!(
            fast - best <= 0.25 * (start - best) + 1e-9,
            "n {n}: cyclic {fast} start {start} optimum {best}"
        );
        let w = exact;
        let sum: f32 = w[..n].iter().sum();
        assert!((sum - 1.0).abs() < 1e-5, "sum {sum}");
        assert!(w[..n].iter().all(|&x| x >= 0.0));
        // KKT: (Qw)_i = mu on the support, >= mu elsewhere, mu = w^T Q w.
        let qw: Vec<f64> = (0..n)
            .map(|i| {
                let bw: Vec<f64> = b
                    .iter()
                    .map(|r| (0..n).map(|j| f64::from(r[j]) * f64::from(w[j])).sum())
                    .collect();
                b.iter()
                    .zip(&bw)
                    .map(|(r, s)| f64::from(r[i]) * s)
                    .sum::<f64>()
                    + f64::from(v[i]) * f64::from(w[i])
            })
            .collect();
        let mu: f64 = (0..n).map(|i| f64::from(w[i]) * qw[i]).sum();
        for i in 0..n {
            assert!(qw[i] >= mu - 1e-5, "n {n} i {i}: {} < {mu}", qw[i]);
            if w[i] > 1e-3 {
                assert!((qw[i] - mu).abs() < 1e-5, "n {n} i {i}: {} vs {mu}", qw[i]);
            }
        }
    }
    let mut rng = Lcg(3);
    check::<3>(&mut rng, 9);
    check::<6>(&mut rng, 25);
    check::<15>(&mut rng, 81);
}

/// A synthetic level: smooth shading, hashed noise, a black zero-variance rectangle.
struct Synthetic {
    img: Image,
    var: Image,
    enhanced: Image,
    guide: Image,
    albedo: Image,
    normal: Image,
    up: Image,
    up_var: Image,
    converged: Vec<bool>,
}

fn synthetic(w: usize, h: usize, seed: u64) -> Synthetic {
    let hash = |c: usize, x: usize, y: usize, salt: u64| -> f32 {
        let mut z = (seed ^ salt)
            .wrapping_add((c as u64) << 40)
            .wrapping_add((y as u64) << 20)
            .wrapping_add(x as u64)
            .wrapping_mul(0x9E37_79B9_7F4A_7C15);
        z ^= z >> 29;
        z = z.wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z ^= z >> 32;
        (z >> 40) as f32 / (1u64 << 24) as f32
    };
    let black = |x: usize, y: usize| x < w / 2 && y < h / 2 && w >= 24;
    let shade = |c: usize, x: usize, y: usize| {
        let (fx, fy) = (x as f32 / w as f32, y as f32 / h as f32);
        0.2 + 0.5 * fx * fy + 0.1 * c as f32 + if x > 2 * w / 3 { 0.4 } else { 0.0 }
    };
    let img = Image::from_fn(3, w, h, |(c, x, y)| {
        if black(x, y) {
            0.0
        } else {
            shade(c, x, y) * (0.5 + hash(c, x, y, 1))
        }
    });
    let var = Image::from_fn(3, w, h, |(c, x, y)| {
        if black(x, y) {
            0.0
        } else {
            0.01 * hash(c, x, y, 2)
        }
    });
    let near = |salt: u64, amp: f32| {
        Image::from_fn(3, w, h, move |(c, x, y)| {
            shade(c, x, y) + amp * (hash(c, x, y, salt) - 0.5)
        })
    };
    Synthetic {
        enhanced: near(3, 0.05),
        guide: near(4, 0.02),
        albedo: Image::from_fn(
            3,
            w,
            h,
            |(c, x, _)| if x > w / 3 { 0.8 } else { 0.3 + 0.1 * c as f32 },
        ),
        normal: Image::from_fn(
            3,
            w,
            h,
            |(c, _, y)| if y > h / 2 { c as f32 / 3.0 } else { 0.5 },
        ),
        up: near(5, 0.1),
        up_var: Image::from_fn(3, w, h, |(c, x, y)| 0.002 * hash(c, x, y, 6) - 0.0002),
        converged: (0..w * h).map(|p| p % 7 == 3).collect(),
        img,
        var,
    }
}

#[test]
fn filter_equals_the_per_pixel_reference() {
    let single = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");
    // (width, height, radius, features, finer level, converged mask, spp): K = 15, 12, 9, 6;
    // term weights whose roots are powers of two or not; one to three bands of rows, the last
    // one short (a worker's padded buffers are reused from band to band).
    let cases = [
        (45, 31, 4, true, true, false, 16.0),
        (37, 41, 3, true, true, true, 16.0),
        (45, 31, 4, true, false, true, 4.0),
        (33, 26, 3, false, true, true, 16.0),
        (29, 17, 4, false, false, false, 7.0),
        (6, 5, 4, true, true, false, 1.0),
        (1, 3, 3, false, false, false, 16.0),
    ];
    for (i, &(w, h, radius, features, finer, conv, spp)) in cases.iter().enumerate() {
        let s = synthetic(w, h, i as u64);
        let level = QpLevel {
            img: &s.img,
            var: &s.var,
            enhanced: &s.enhanced,
            guide: &s.guide,
            albedo: features.then_some(&s.albedo),
            normal: features.then_some(&s.normal),
            up: finer.then_some((&s.up, &s.up_var)),
            spp,
            radius,
            converged: conv.then_some(&s.converged[..]),
            dropped: [false; 5],
        };
        let (ro, rv, rskip, _) = reference::gradient_guided_filter(&level);
        let (fo, fv, fskip) = gradient_guided_filter(&level);
        let (so, sv, sskip) = single.install(|| gradient_guided_filter(&level));
        assert_eq!(rskip, fskip, "case {i}");
        assert_eq!(rskip, sskip, "case {i}");
        assert_eq!(
            (w >= 24, conv),
            (rskip.empty > 0, rskip.converged > 0),
            "case {i}"
        );
        for (reference, fast, one) in [(&ro, &fo, &so), (&rv, &fv, &sv)] {
            let peak = reference
                .as_slice()
                .iter()
                .fold(0.0f32, |m, v| m.max(v.abs()));
            let diff = reference
                .as_slice()
                .iter()
                .zip(fast.as_slice())
                .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
            // Tolerance: 1e-5 of the peak. Measured: at most 8.3e-7 (the fast path sums the
            // solver's projections in another order, see `lanes_follow_the_scalar_release_solver`).
            assert!(
                diff <= 1e-5 * peak,
                "case {i}: max |fast - reference| = {diff:e}"
            );
            assert_eq!(
                fast.as_slice(),
                one.as_slice(),
                "case {i}: thread count matters"
            );
        }
    }
}

#[test]
fn terms_whose_weight_vanishes_are_dropped_at_very_high_spp_only() {
    let (w, h) = (40, 30);
    let s = synthetic(w, h, 11);
    let level = |spp: f32| QpLevel {
        img: &s.img,
        var: &s.var,
        enhanced: &s.enhanced,
        guide: &s.guide,
        albedo: Some(&s.albedo),
        normal: Some(&s.normal),
        up: Some((&s.up, &s.up_var)),
        spp,
        radius: 4,
        converged: None,
        dropped: [false; 5],
    };
    // Up to 1e6 spp every term carries its weight.
    for spp in [1.0, 16.0, 1024.0, 1e6] {
        assert_eq!(vanishing_terms(&level(spp)), [false; 5], "{spp} spp");
    }
    // At 1e14 spp the optional terms' weights (16, 0.16 and 8 over 1e7) vanish; the enhanced
    // and guide terms are never dropped.
    let full = level(1e14);
    let dropped = vanishing_terms(&full);
    assert!(!dropped[0] && !dropped[3], "{dropped:?}");
    assert!(dropped[2] && dropped[4], "{dropped:?}");
    let reduced = QpLevel {
        dropped,
        ..level(1e14)
    };
    assert!(reduced.alphas().iter().filter(|&&a| a > 0.0).count() < 5);
    // The fast path still follows the reference (which builds every row, starts from all of
    // them, then removes the dropped ones), within the tolerance of
    // `filter_equals_the_per_pixel_reference`.
    let (ro, rv, _, _) = reference::gradient_guided_filter(&reduced);
    let (fo, fv, _) = gradient_guided_filter(&reduced);
    for (x, y) in [(&ro, &fo), (&rv, &fv)] {
        let peak = x.as_slice().iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let diff = x.max_abs_diff(y);
        assert!(diff <= 1e-5 * peak, "{diff:e} vs peak {peak:e}");
    }
    // And dropping them hardly moves the result: three terms of under 1e-4 of the objective
    // each, through a truncated solve. Tolerance 1e-3 of the peak; measured 3.5e-4 (and 4.6e-3
    // when the dropped terms were also left out of the start).
    let (a, av, _) = gradient_guided_filter(&full);
    for (x, y) in [(&a, &fo), (&av, &fv)] {
        let peak = x.as_slice().iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let diff = x.max_abs_diff(y);
        assert!(diff <= 1e-3 * peak, "{diff:e} vs peak {peak:e}");
    }
}
