//! `auto` picks per frame and says why: the prior path (the combiner, else L1 on the prior)
//! when a prior is given or Open Image Denoise loads (tests/prior.rs); without it (`use_prior`
//! false here, so that OIDN's presence does not matter) GradNet whenever it can run, else FRGR
//! (`frgr`) when the spp is known, else L1.

use std::path::Path;

use gdrecon::recon::AutoConfig;
use gdrecon::{io, Context, ContextOptions, Frame, MethodConfig, Plan, Policy, Progress, Report};

fn sample() -> Frame {
    io::read_bundle(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/gradnet/crop_b.exr"),
        Policy::Replace,
    )
    .unwrap()
}

/// `auto` without its prior path.
fn no_prior() -> AutoConfig {
    let mut config = AutoConfig::default();
    config.use_prior = false;
    config
}

fn run(frame: &Frame, config: AutoConfig) -> Report {
    let ctx = Context::new(ContextOptions::with_threads(Some(2))).unwrap();
    let mut plan = Plan::new(
        &ctx,
        &MethodConfig::Auto(config),
        frame.width(),
        frame.height(),
    )
    .unwrap();
    let (out, report) = plan.execute(frame, &Progress::none()).unwrap();
    assert!(out.all_finite());
    report
}

fn note(report: &Report) -> &str {
    report
        .notes
        .iter()
        .find(|n| n.starts_with("auto: "))
        .expect("auto says why")
}

/// A model path that does not exist: GradNet cannot run.
fn without_gradnet() -> AutoConfig {
    let mut config = no_prior();
    config.gradnet.model = Some("/nonexistent/gradnet.onnx".into());
    config
}

#[test]
fn gradnet_runs_whatever_the_spp() {
    if !cfg!(feature = "gradnet") {
        return;
    }
    let known = sample();
    assert!(known.spp().is_some());
    let unknown = sample()
        .into_builder()
        .spp(None)
        .build(Policy::Replace)
        .unwrap();
    for frame in [known, unknown] {
        let report = run(&frame, no_prior());
        assert_eq!(report.method, "auto -> gradnet", "{:?}", report.notes);
        assert!(note(&report).contains("no prior (use_prior is false)"));
        assert!(note(&report).contains("with features"), "{}", note(&report));
    }
}

#[test]
fn without_gradnet_known_spp_runs_frgr_and_unknown_runs_l1_with_the_reason() {
    let frame = sample();
    let report = run(&frame, without_gradnet());
    assert_eq!(report.method, "auto -> frgr", "{:?}", report.notes);
    let why = note(&report);
    assert!(
        why.contains("GradNet cannot run") && why.contains("is known"),
        "{why}"
    );

    let frame = frame
        .into_builder()
        .spp(None)
        .build(Policy::Replace)
        .unwrap();
    let report = run(&frame, without_gradnet());
    assert_eq!(report.method, "auto -> l1");
    let why = note(&report);
    assert!(
        why.contains("GradNet cannot run") && why.contains("spp unknown"),
        "{why}"
    );
}

/// `fallback` false: a frame whose preferred path cannot run here is an error naming why, not
/// another method's image (one frame, one image on every machine).
#[test]
fn without_fallback_a_missing_path_is_an_error() {
    let frame = sample();
    let mut config = without_gradnet();
    config.fallback = false;
    let ctx = Context::new(ContextOptions::with_threads(Some(2))).unwrap();
    let (w, h) = frame.size();
    let mut plan = Plan::new(&ctx, &MethodConfig::Auto(config.clone()), w, h).unwrap();
    let e = plan.execute(&frame, &Progress::none()).unwrap_err();
    assert!(
        e.to_string().contains("GradNet cannot run here")
            && e.to_string().contains("fallback is false"),
        "{e}"
    );
    // The prior path, with OIDN named at a path that does not exist and no prior layer.
    let ctx = Context::new(
        ContextOptions::with_threads(Some(2)).with_oidn("/nonexistent/libOpenImageDenoise.so.2"),
    )
    .unwrap();
    let mut config = AutoConfig::default();
    config.fallback = false;
    let mut plan = Plan::new(&ctx, &MethodConfig::Auto(config.clone()), w, h).unwrap();
    let e = plan.execute(&frame, &Progress::none()).unwrap_err();
    assert!(
        e.to_string().contains("the prior path cannot run here"),
        "{e}"
    );
    // The same frames with fallback (the default) run, and say what they fell back to.
    config.fallback = true;
    let mut plan = Plan::new(&ctx, &MethodConfig::Auto(config), w, h).unwrap();
    let (_, report) = plan.execute(&frame, &Progress::none()).unwrap();
    let expected = if cfg!(feature = "gradnet") {
        "auto -> gradnet"
    } else {
        "auto -> frgr"
    };
    assert_eq!(report.method, expected, "{:?}", report.notes);
}

/// Under a memory limit `auto` leaves out each path still over it once fitted, as it leaves
/// out a path whose library is missing, and says what that path needs; `l1`, the last resort,
/// is refused only under its own estimate. With `fallback` false a path over the limit
/// refuses the plan.
#[test]
fn a_memory_limit_leaves_out_the_paths_over_it() {
    if !cfg!(feature = "gradnet") {
        return;
    }
    const MIB: u64 = 1 << 20;
    let frame = sample();
    let (w, h) = (frame.width(), frame.height());
    let config = no_prior();
    let least = |c: MethodConfig| c.fitted_to(w, h, 0).memory_estimate(w, h).div_ceil(MIB);
    let gradnet = least(MethodConfig::GradNet(config.gradnet.clone()));
    let frgr = least(MethodConfig::Frgr(config.frgr));
    let l1 = least(MethodConfig::PoissonL1(config.l1));
    assert!(l1 < frgr && frgr < gradnet, "{l1} {frgr} {gradnet}");
    let plan = |config: AutoConfig, mb: u64| {
        let options = ContextOptions::with_threads(Some(2)).with_max_memory_mb(mb);
        Plan::new(
            &Context::new(options).unwrap(),
            &MethodConfig::Auto(config),
            w,
            h,
        )
    };
    let run = |mb: u64| {
        let (out, report) = plan(no_prior(), mb)
            .unwrap()
            .execute(&frame, &Progress::none())
            .unwrap();
        assert!(out.all_finite());
        report
    };
    assert_eq!(run(gradnet).method, "auto -> gradnet");
    let report = run(gradnet - 1);
    assert_eq!(report.method, "auto -> frgr");
    let why = format!(
        "GradNet cannot run (needs about {gradnet} MiB, more than the limit of {} MiB)",
        gradnet - 1
    );
    assert!(note(&report).contains(&why), "{}", note(&report));
    let report = run(frgr - 1);
    assert_eq!(report.method, "auto -> l1");
    assert!(
        note(&report).contains(&format!("frgr, but it needs about {frgr} MiB")),
        "{}",
        note(&report)
    );
    let err = plan(no_prior(), l1 - 1).unwrap_err();
    out_of_memory(&err, &format!("auto for {w} x {h} needs about {l1} MiB"));
    let mut strict = no_prior();
    strict.fallback = false;
    plan(strict.clone(), gradnet).unwrap();
    out_of_memory(&plan(strict, gradnet - 1).unwrap_err(), "");
}

/// At 3840 x 2160 GradNet's least (about 0.7 GB) is under L1's (about 1.2 GB): under a limit
/// between them `auto` plans with GradNet alone in, and a frame GradNet cannot run (here its
/// model file is missing) is refused with `OutOfMemory` naming what L1 needs.
#[test]
fn where_only_gradnet_fits_a_frame_it_cannot_run_is_refused() {
    const MIB: u64 = 1 << 20;
    let (w, h) = (3840, 2160);
    let config = no_prior();
    let least = |c: MethodConfig| c.fitted_to(w, h, 0).memory_estimate(w, h).div_ceil(MIB);
    let gradnet = least(MethodConfig::GradNet(config.gradnet.clone()));
    let l1 = least(MethodConfig::PoissonL1(config.l1));
    assert!(gradnet + 100 < l1, "{gradnet} {l1}");
    let limit = (gradnet + l1) / 2;
    let auto = MethodConfig::Auto(config).fitted_to(w, h, limit * MIB);
    assert!(auto.memory_estimate(w, h) <= limit * MIB);
    if !cfg!(feature = "gradnet") {
        return;
    }
    let options = ContextOptions::with_threads(Some(2)).with_max_memory_mb(limit);
    let context = Context::new(options).unwrap();
    let mut plan = Plan::new(&context, &MethodConfig::Auto(without_gradnet()), w, h).unwrap();
    let zeros = || gdrecon::Image::zeros(3, w, h);
    let frame = gdrecon::FrameBuilder::new()
        .image(gdrecon::Layer::Color, zeros())
        .image(gdrecon::Layer::Dx, zeros())
        .image(gdrecon::Layer::Dy, zeros())
        .build(Policy::Replace)
        .unwrap();
    let err = plan.execute(&frame, &Progress::none()).unwrap_err();
    out_of_memory(&err, &format!("but l1 needs about {l1} MiB"));
}

/// `err` is `OutOfMemory` and says `text`.
fn out_of_memory(err: &gdrecon::Error, text: &str) {
    assert!(
        matches!(err, gdrecon::Error::OutOfMemory(_)) && err.to_string().contains(text),
        "{err}"
    );
}
