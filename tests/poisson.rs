//! Screened Poisson L2 and L1 against independent references and analytic cases.

mod common;

use common::*;
use gdrecon::recon::{reconstruct, PoissonL1Config, PoissonL2Config, Preconditioner, Value};
use gdrecon::{metrics, Context, ContextOptions, Image, Method, MethodConfig, Plan, Progress};

fn l2(frame: &gdrecon::Frame, alpha: f32) -> Image {
    let mut config = MethodConfig::default_for(Method::PoissonL2);
    config.set("alpha", Value::Float(alpha)).unwrap();
    reconstruct(frame, &config).unwrap().0
}

fn l1(frame: &gdrecon::Frame, config: PoissonL1Config) -> Image {
    reconstruct(frame, &MethodConfig::PoissonL1(config))
        .unwrap()
        .0
}

/// Tolerance: the DCT solve runs in f32; 1e-5 of the image's range is the bound.
#[test]
fn l2_matches_sparse_reference_solve() {
    for (w, h, alpha, seed) in [
        (16, 12, 0.2, 1),
        (7, 23, 0.05, 2),
        (31, 9, 1.0, 3),
        (1, 10, 0.2, 4),
        (10, 1, 0.3, 5),
    ] {
        let (frame, _) = noisy_frame(w, h, seed);
        let ours = to_f64(&l2(&frame, alpha));
        let reference = reference_l2(&frame, f64::from(alpha));
        let d = rel_max_diff(&ours, &reference);
        assert!(d < 1e-5, "{w}x{h} alpha {alpha}: relative difference {d:e}");
    }
}

#[test]
fn exact_gradients_and_base_reproduce_the_image() {
    let img = test_image(40, 25);
    let (dx, dy) = exact_gradients(&img);
    let out = l2(&frame(img.clone(), dx, dy), 0.2);
    let d = rel_max_diff(&to_f64(&out), &to_f64(&img));
    assert!(d < 1e-5, "{d:e}");
}

#[test]
fn exact_gradients_recover_the_image_from_any_zero_mean_noisy_base_at_alpha_zero() {
    let (w, h) = (33, 17);
    let img = test_image(w, h);
    let (dx, dy) = exact_gradients(&img);
    let mut rng = Lcg(9);
    let noise: Vec<f32> = (0..3 * w * h).map(|_| 0.1 * rng.signed() as f32).collect();
    let mut base = img.clone();
    for c in 0..3 {
        let plane = &noise[c * w * h..(c + 1) * w * h];
        let mean = plane.iter().sum::<f32>() / plane.len() as f32;
        for (v, n) in base.plane_mut(c).iter_mut().zip(plane) {
            *v += n - mean;
        }
    }
    let out = l2(&frame(base, dx, dy), 0.0);
    let d = rel_max_diff(&to_f64(&out), &to_f64(&img));
    assert!(d < 1e-5, "{d:e}");
}

#[test]
fn constant_base_with_zero_gradients_stays_constant() {
    let (w, h) = (20, 11);
    let base = Image::from_fn(3, w, h, |(c, _, _)| 0.5 + c as f32);
    let out = l2(
        &frame(base.clone(), Image::zeros(3, w, h), Image::zeros(3, w, h)),
        0.2,
    );
    for c in 0..3 {
        for v in out.plane(c) {
            assert!((v - (0.5 + c as f32)).abs() < 1e-5, "{v}");
        }
    }
    let out = l1(
        &frame(base, Image::zeros(3, w, h), Image::zeros(3, w, h)),
        PoissonL1Config::default(),
    );
    for c in 0..3 {
        for v in out.plane(c) {
            assert!((v - (0.5 + c as f32)).abs() < 1e-4, "{v}");
        }
    }
}

#[test]
fn large_alpha_returns_the_base() {
    let (frame, _) = noisy_frame(24, 16, 7);
    let out = l2(&frame, 1e3);
    let d = rel_max_diff(&to_f64(&out), &to_f64(frame.color()));
    assert!(d < 1e-5, "{d:e}");
}

#[test]
fn zero_gradients_smooth_the_base() {
    let (frame0, _) = noisy_frame(32, 32, 8);
    let (w, h) = frame0.size();
    let f = frame(
        frame0.color().clone(),
        Image::zeros(3, w, h),
        Image::zeros(3, w, h),
    );
    let out = l2(&f, 0.2);
    let tv = |img: &Image| -> f64 {
        let (dx, _) = exact_gradients(img);
        dx.as_slice().iter().map(|v| f64::from(v.abs())).sum()
    };
    assert!(
        tv(&out) < 0.25 * tv(f.color()),
        "{} vs {}",
        tv(&out),
        tv(f.color())
    );
    // The mean is preserved: the data term is the only one that sees it.
    let mean = |img: &Image| img.as_slice().iter().map(|&v| f64::from(v)).sum::<f64>();
    assert!((mean(&out) - mean(f.color())).abs() / mean(f.color()) < 1e-5);
}

/// The L1 solver converges to the same IRLS iterate as a naive f64 implementation of the
/// published weight rule (tight tolerance, so this checks the algorithm, not the schedule),
/// with and without the regularisation floor.
#[test]
fn l1_matches_naive_irls_reference() {
    let (frame, _) = noisy_frame(12, 10, 11);
    for floor in [0.0, 1e-2, 0.2] {
        let reference = reference_l1(&frame, 0.2, 6, f64::from(floor));
        for preconditioner in [
            Preconditioner::Multigrid,
            Preconditioner::Dct,
            Preconditioner::Jacobi,
        ] {
            let mut config = PoissonL1Config::default();
            config.reweight_steps = 6;
            config.cg_iterations = 500;
            config.cg_tolerance = 1e-6;
            if preconditioner == Preconditioner::Jacobi {
                // Its iterations move the image too little for `cg_change` and `cg_relative`
                // to mean converged (the `prior` preset, which uses it, turns both off).
                config.cg_iterations = 5000;
                config.cg_change = 0.0;
                config.cg_relative = 0.0;
            }
            config.reg_floor = floor;
            config.preconditioner = preconditioner;
            let ours = to_f64(&l1(&frame, config));
            let d = rel_max_diff(&ours, &reference);
            assert!(
                d < 2e-4,
                "floor {floor}, {preconditioner:?}: relative difference {d:e}"
            );
        }
    }
}

/// The default configuration is the converged answer of its own IRLS (the bar):
/// its relMSE against the clean image is within 5 % of that of the naive f64 IRLS with every
/// step solved to 1e-12, on a noisy frame and on the same frame with a 1000:1 dynamic range.
#[test]
fn default_l1_is_converged() {
    let (w, h) = (64, 48);
    let (frame, clean) = noisy_frame(w, h, 12);
    // The same frame with a bright emitter-like block (x 1000) in one corner.
    let gain = |x: usize, y: usize| if x < 12 && y < 9 { 1000.0 } else { 1.0 };
    let bright = Image::from_fn(3, w, h, |(c, x, y)| clean.at(c, x, y) * gain(x, y));
    let hdr = {
        let (mut dx, mut dy) = bright.forward_differences();
        // The base frame's noise, relative to the level.
        let color = Image::from_fn(3, w, h, |(c, x, y)| {
            frame.color().at(c, x, y) / clean.at(c, x, y).max(1e-3) * bright.at(c, x, y)
        });
        for (d, n) in dx.as_mut_slice().iter_mut().zip(frame.dx().as_slice()) {
            *d += n;
        }
        for (d, n) in dy.as_mut_slice().iter_mut().zip(frame.dy().as_slice()) {
            *d += n;
        }
        gdrecon::FrameBuilder::new()
            .image(gdrecon::Layer::Color, color)
            .image(gdrecon::Layer::Dx, dx)
            .image(gdrecon::Layer::Dy, dy)
            .build(gdrecon::Policy::Replace)
            .unwrap()
    };
    let default = PoissonL1Config::default();
    for (f, truth) in [(&frame, &clean), (&hdr, &bright)] {
        let converged = reference_l1(f, 0.2, default.reweight_steps, default.reg_floor.into());
        // Negative values set to 0, as the plan does to every output.
        let converged = Image::from_fn(3, w, h, |(c, x, y)| {
            (converged[c][y * w + x] as f32).max(0.0)
        });
        let conv = metrics::compare(&converged, truth).unwrap().rel_mse;
        let ours = metrics::compare(&l1(f, default), truth).unwrap().rel_mse;
        let fast = metrics::compare(&l1(f, PoissonL1Config::fast()), truth)
            .unwrap()
            .rel_mse;
        eprintln!("converged {conv:e}, default {ours:e}, fast {fast:e}");
        assert!(
            (ours / conv - 1.0).abs() < 0.05,
            "default {ours:e} vs converged {conv:e}"
        );
        // The test can tell: the truncated solve misses the HDR frame's converged answer.
        if std::ptr::eq(f, &hdr) {
            assert!(fast > 2.0 * conv, "fast {fast:e} vs converged {conv:e}");
        }
    }
}

/// Total CG iterations from an L1 report's summary note.
fn cg_iterations(report: &gdrecon::Report) -> u32 {
    report
        .notes
        .iter()
        .find_map(|n| {
            let (head, _) = n.split_once(" CG iterations")?;
            head.rsplit(' ').next()?.parse().ok()
        })
        .unwrap_or_else(|| panic!("no CG iteration count in {:?}", report.notes))
}

/// `cg_change` stops a step once CG has stopped moving the image (in the error metric's
/// units): fewer iterations than the residual rule alone, and the same answer to 0.5 %.
/// The frame is large enough (200 x 150) that the multigrid needs several iterations a step.
#[test]
fn cg_change_stops_early_without_moving_the_answer() {
    let (frame, clean) = noisy_frame(200, 150, 31);
    let run = |config: PoissonL1Config| {
        let (out, report) = reconstruct(&frame, &MethodConfig::PoissonL1(config)).unwrap();
        let err = metrics::compare(&out, &clean).unwrap().rel_mse;
        (err, cg_iterations(&report))
    };
    let default = PoissonL1Config::default();
    assert!(default.cg_change > 0.0);
    let mut residual_only = default;
    residual_only.cg_change = 0.0;
    let ((e, its), (e0, its0)) = (run(default), run(residual_only));
    eprintln!("cg_change: {its} iterations, relMSE {e:e}; residual only: {its0}, {e0:e}");
    assert!(its < its0, "{its} vs {its0} iterations");
    assert!((e / e0 - 1.0).abs() < 5e-3, "{e:e} vs {e0:e}");
}

/// Inject gradient outliers: L1 must be closer to the clean image than L2, and its group-L1
/// energy lower than L2's solution's.
#[test]
fn l1_is_more_robust_than_l2_to_gradient_outliers() {
    let (w, h) = (48, 40);
    let (frame0, clean) = noisy_frame(w, h, 21);
    let mut dx = frame0.dx().clone();
    let mut dy = frame0.dy().clone();
    let mut rng = Lcg(5);
    for _ in 0..40 {
        let (x, y) = (
            (rng.uniform() * (w - 1) as f64) as usize,
            (rng.uniform() * (h - 1) as f64) as usize,
        );
        let v = 20.0 * rng.signed() as f32;
        for c in 0..3 {
            dx.plane_mut(c)[[y, x]] += v;
            dy.plane_mut(c)[[y, x]] -= v;
        }
    }
    let f = frame(frame0.color().clone(), dx, dy);
    let out2 = l2(&f, 0.2);
    let out1 = l1(&f, PoissonL1Config::default());
    let e2 = metrics::compare(&out2, &clean).unwrap().rel_mse;
    let e1 = metrics::compare(&out1, &clean).unwrap().rel_mse;
    assert!(
        e1 < 0.2 * e2,
        "L1 relMSE {e1:e} should be far below L2's {e2:e}"
    );
    let en1 = l1_energy(&f, 0.2, &to_f64(&out1));
    let en2 = l1_energy(&f, 0.2, &to_f64(&out2));
    assert!(en1 < en2, "L1 energy {en1} vs L2 solution's {en2}");
}

#[test]
fn published_preset_runs_its_fixed_schedule() {
    let (frame, clean) = noisy_frame(20, 20, 3);
    let (out, report) = reconstruct(
        &frame,
        &MethodConfig::PoissonL1(PoissonL1Config::published()),
    )
    .unwrap();
    assert!(
        report
            .notes
            .iter()
            .any(|n| n.contains("1000 CG iterations") && n.contains("unpreconditioned")),
        "{:?}",
        report.notes
    );
    let fast = l1(&frame, PoissonL1Config::default());
    let (ep, ef) = (
        metrics::compare(&out, &clean).unwrap().rel_mse,
        metrics::compare(&fast, &clean).unwrap().rel_mse,
    );
    assert!(
        (ep - ef).abs() < 0.2 * ep,
        "published {ep:e} vs fast {ef:e}"
    );
}

#[test]
fn results_are_bit_identical_for_any_thread_count() {
    let frame = gdrecon::synth::synthetic_frame(97, 61, 8.0, 4);
    let mut small = gdrecon::recon::FrgrConfig::default();
    small.enhance_iterations = 50;
    for config in [
        MethodConfig::PoissonL2(PoissonL2Config::default()),
        MethodConfig::PoissonL1(PoissonL1Config::default()),
        MethodConfig::Frgr(small),
    ] {
        check_threads(&config, &frame);
    }
    // A frame large enough for the multigrid's parallel passes (more than 2^15 pixels),
    // with odd sides.
    let large = gdrecon::synth::synthetic_frame(257, 131, 8.0, 5);
    let mut short = PoissonL1Config::default();
    short.reweight_steps = 3;
    check_threads(&MethodConfig::PoissonL1(short), &large);
}

/// `config` on `frame` gives the same bits on 1, 2, 3 and 5 threads.
fn check_threads(config: &MethodConfig, frame: &gdrecon::Frame) {
    let run = |threads| {
        let ctx = Context::new(ContextOptions::with_threads(Some(threads))).unwrap();
        let mut plan = Plan::new(&ctx, config, frame.width(), frame.height()).unwrap();
        plan.execute(frame, &Progress::none()).unwrap().0
    };
    let one = run(1);
    for t in [2, 3, 5] {
        assert!(
            one.as_slice()
                .iter()
                .zip(run(t).as_slice())
                .all(|(a, b)| a.to_bits() == b.to_bits()),
            "{config:?} differs at {t} threads"
        );
    }
}

#[test]
fn plans_are_reusable_and_check_sizes() {
    let ctx = Context::new(ContextOptions::default()).unwrap();
    let config = MethodConfig::PoissonL1(PoissonL1Config::default());
    let mut plan = Plan::new(&ctx, &config, 20, 10).unwrap();
    let (a, _) = noisy_frame(20, 10, 1);
    let (b, _) = noisy_frame(20, 10, 2);
    let first = plan.execute(&a, &Progress::none()).unwrap().0;
    plan.execute(&b, &Progress::none()).unwrap();
    assert_eq!(
        plan.execute(&a, &Progress::none()).unwrap().0,
        first,
        "no state leaks between frames"
    );
    let (c, _) = noisy_frame(21, 10, 2);
    let e = plan.execute(&c, &Progress::none()).unwrap_err();
    assert!(
        e.to_string().contains("21 x 10") && e.to_string().contains("20 x 10"),
        "{e}"
    );
}

#[test]
fn progress_reaches_one_and_cancellation_stops() {
    let (frame, _) = noisy_frame(30, 30, 1);
    let ctx = Context::new(ContextOptions::default()).unwrap();
    let config = MethodConfig::PoissonL1(PoissonL1Config::published());
    let mut plan = Plan::new(&ctx, &config, 30, 30).unwrap();
    let seen = std::sync::Mutex::new(Vec::new());
    let record = |f: f64| {
        seen.lock().unwrap().push(f);
        true
    };
    plan.execute(&frame, &Progress::new(&record)).unwrap();
    let seen = seen.into_inner().unwrap();
    assert!(seen.windows(2).all(|p| p[0] <= p[1]), "monotone");
    assert_eq!(*seen.last().unwrap(), 1.0);
    let calls = std::sync::atomic::AtomicUsize::new(0);
    let cancel = |_| calls.fetch_add(1, std::sync::atomic::Ordering::Relaxed) < 5;
    let e = plan.execute(&frame, &Progress::new(&cancel)).unwrap_err();
    assert!(matches!(e, gdrecon::Error::Cancelled), "{e}");
    assert_eq!(
        calls.load(std::sync::atomic::Ordering::Relaxed),
        6,
        "stops at the first false"
    );
}

#[test]
fn invalid_settings_are_rejected_with_the_value() {
    let (frame, _) = noisy_frame(8, 8, 1);
    // Fields set directly (bypassing `MethodConfig::set`'s checks) are checked at plan time.
    let l2 = |alpha: f32| {
        let mut c = PoissonL2Config::default();
        c.alpha = alpha;
        MethodConfig::PoissonL2(c)
    };
    let l1 = |set: fn(&mut PoissonL1Config)| {
        let mut c = PoissonL1Config::default();
        set(&mut c);
        MethodConfig::PoissonL1(c)
    };
    for (config, needle) in [
        (l2(-1.0), "alpha is -1"),
        (l2(f32::NAN), "alpha is NaN"),
        (l1(|c| c.alpha = 0.0), "alpha is 0"),
        (l1(|c| c.reweight_steps = 0), "reweight_steps is 0"),
        (l1(|c| c.cg_tolerance = 2.0), "cg_tolerance is 2"),
    ] {
        let e = reconstruct(&frame, &config).unwrap_err();
        assert!(
            matches!(e, gdrecon::Error::InvalidArgument(_)) && e.to_string().contains(needle),
            "{e}"
        );
    }
}
