//! `auto` picks per frame and says why: the L1 prior path when a prior is given or Open Image
//! Denoise loads (tests/prior.rs); without it (`use_prior` false here, so that OIDN's presence
//! does not matter) FRGR (`frgr`) when the spp is known, GradNet when it is not, L1 when
//! GradNet cannot run.

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

#[test]
fn known_spp_runs_frgr() {
    let frame = sample();
    assert!(frame.spp().is_some());
    let report = run(&frame, no_prior());
    assert_eq!(report.method, "auto -> frgr");
    assert!(note(&report).contains("no prior (use_prior is false)"));
    assert!(note(&report).contains("is known"), "{}", note(&report));
}

#[test]
fn unknown_spp_runs_gradnet_or_falls_back_to_l1_with_the_reason() {
    let frame = sample()
        .into_builder()
        .spp(None)
        .build(Policy::Replace)
        .unwrap();
    if cfg!(feature = "gradnet") {
        let report = run(&frame, no_prior());
        assert_eq!(report.method, "auto -> gradnet", "{:?}", report.notes);
        assert!(note(&report).contains("with features"));
    }
    let mut config = no_prior();
    config.gradnet.model = Some("/nonexistent/gradnet.onnx".into());
    let report = run(&frame, config);
    assert_eq!(report.method, "auto -> l1");
    let why = note(&report);
    assert!(why.contains("GradNet cannot run"), "{why}");
}
