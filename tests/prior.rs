//! The prior paths through the public API and the CLI: the library's own Open Image Denoise
//! prior against the Python reference (`pyoidn`, fixtures from `python -m gdrecon_py.oidn
//! --fixtures`), a caller's prior used as given, the prior paths against the prior alone on
//! the guard frames, and each way of not finding OIDN a distinct, clear error.
//!
//! Needs Open Image Denoise 2 (found by the library's discovery: `bash onnx/setup.sh` installs
//! `pyoidn`, which carries it). Tolerance of the parity: OIDN's CPU kernels differ by
//! instruction set, so outputs agree to 1e-3 relative (|a - b| <= 1e-3 (|b| + 1e-2)), not bits.

#![cfg(feature = "oidn")]

mod common;

use std::path::{Path, PathBuf};

use assert_cmd::Command;
use gdrecon::recon::{AutoConfig, PoissonL1Config};
use gdrecon::{
    io, metrics, Context, ContextOptions, Frame, Image, Layer, Method, MethodConfig, Plan, Policy,
    Progress, Report,
};
use ndarray::{Array3, ArrayD};

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn guard_frames() -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(root().join("tests/data/guard"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "exr"))
        .collect();
    files.sort();
    assert!(files.len() >= 4, "guard frames missing: {files:?}");
    files
}

fn run(frame: &Frame, config: &MethodConfig) -> (Image, Report) {
    let context = Context::new(ContextOptions::with_threads(Some(2))).unwrap();
    let mut plan = Plan::new(&context, config, frame.width(), frame.height()).unwrap();
    plan.execute(frame, &Progress::none()).unwrap()
}

fn rel_mse(image: &Image, frame: &Frame) -> f64 {
    metrics::compare(image, frame.reference().unwrap())
        .unwrap()
        .rel_mse
}

#[test]
fn oidn_prior_matches_pyoidn_on_every_guard_frame() {
    for path in guard_frames() {
        let stem = path.file_stem().unwrap().to_string_lossy().into_owned();
        let frame = io::read_bundle(&path, Policy::Replace).unwrap();
        let (got, report) = run(&frame, &MethodConfig::default_for(Method::Prior));
        let want: ArrayD<f32> =
            ndarray_npy::read_npy(root().join(format!("tests/fixtures/prior/{stem}_oidn.npy")))
                .unwrap();
        let mut want: Array3<f32> = want.into_dimensionality().unwrap();
        // The library confines OIDN's output to [0, max colour] (its network overshoots a
        // little; see recon/prior): the reference gets the same clamp.
        let peak = frame.color().as_slice().iter().copied().fold(0.0, f32::max);
        let mut clamped = 0;
        want.iter_mut().for_each(|v| {
            clamped += usize::from(*v < 0.0 || *v > peak);
            *v = v.clamp(0.0, peak)
        });
        println!("{stem}: {clamped} reference values clamped to [0, {peak}]");
        let want = Image::from_hwc(want.view());
        let mut worst = 0.0f32;
        for (g, w) in got.as_slice().iter().zip(want.as_slice()) {
            worst = worst.max((g - w).abs() / (w.abs() + 1e-2));
        }
        println!("{stem}: worst relative difference {worst:e}");
        assert!(worst <= 1e-3, "{stem}: worst relative difference {worst:e}");
        assert!(
            report
                .notes
                .iter()
                .any(|n| n.starts_with("prior: Open Image Denoise 2.")
                    && n.contains("albedo + normal")),
            "{stem}: the report names the prior's source: {:?}",
            report.notes
        );
        assert!(report.stages.iter().any(|s| s.name == "prior (oidn)"));
    }
}

#[test]
fn a_given_prior_is_used_as_is() {
    let frame = io::read_bundle(root().join("examples/data/sample.exr"), Policy::Replace).unwrap();
    // Any image will do as the caller's prior: here the reference, halved.
    let mut given = frame.reference().unwrap().clone();
    given.as_mut_slice().iter_mut().for_each(|v| *v *= 0.5);
    let with_prior = common::with_prior(frame.clone(), given.clone());
    let (out, report) = run(&with_prior, &MethodConfig::default_for(Method::Prior));
    assert_eq!(out.as_slice(), given.as_slice());
    assert!(report
        .notes
        .iter()
        .any(|n| n.contains("given by the caller")));
    assert!(report.stages.iter().all(|s| s.name != "prior (oidn)"));
    // The L1 prior path anchors to it: halving the prior moves the result toward it.
    let l1 = MethodConfig::PoissonL1(PoissonL1Config::prior());
    let (own, _) = run(&frame, &l1);
    let (anchored, _) = run(&with_prior, &l1);
    let mean = |i: &Image| i.as_slice().iter().map(|&v| f64::from(v)).sum::<f64>();
    let (m_own, m_anchored) = (mean(&own), mean(&anchored));
    assert!(
        m_anchored < 0.75 * m_own,
        "the given prior is the data term: mean {m_anchored} vs {m_own} with OIDN's"
    );
}

/// The bar of the prior path on frames the tests can afford: never more than 5 % behind the
/// prior alone, and ahead of it on the frames whose prior is not already near the reference.
#[test]
fn the_l1_prior_path_is_never_more_than_5_percent_behind_the_prior() {
    let mut ratios = Vec::new();
    for path in guard_frames() {
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        let frame = io::read_bundle(&path, Policy::Replace).unwrap();
        let (prior, _) = run(&frame, &MethodConfig::default_for(Method::Prior));
        let (l1, report) = run(&frame, &MethodConfig::PoissonL1(PoissonL1Config::prior()));
        assert!(l1.all_finite());
        assert!(report.notes.iter().any(|n| n == "data term: the prior"));
        let ratio = rel_mse(&l1, &frame) / rel_mse(&prior, &frame);
        println!("{name}: l1:prior / prior = {ratio:.4}");
        assert!(ratio <= 1.05, "{name}: l1:prior is {ratio:.3}x the prior");
        ratios.push(ratio);
    }
    let geomean = (ratios.iter().map(|r| r.ln()).sum::<f64>() / ratios.len() as f64).exp();
    assert!(geomean < 0.97, "geometric mean ratio {geomean:.3}");
}

/// `auto` with a prior: the combiner where it can run (ONNX Runtime, and the sample has
/// variance, albedo and normal), else L1 on the prior; with `use_combiner=false` L1 on the
/// prior; each says why.
#[test]
fn auto_takes_the_prior_path_and_says_so() {
    let frame = io::read_bundle(root().join("examples/data/sample.exr"), Policy::Replace).unwrap();
    let said = |report: &Report, part: &str| {
        assert!(
            report.notes.iter().any(|n| n.contains(part)),
            "{part}: {:?}",
            report.notes
        );
    };
    let (l1, _) = run(&frame, &MethodConfig::PoissonL1(PoissonL1Config::prior()));
    let config = MethodConfig::default_for(Method::Auto);
    let (auto, report) = run(&frame, &config);
    said(&report, "auto: Open Image Denoise computes the prior");
    if cfg!(all(feature = "gradnet", feature = "embed-model")) {
        assert_eq!(report.method, "auto -> combiner");
        let (combined, _) = run(&frame, &MethodConfig::default_for(Method::Combiner));
        assert_eq!(auto.as_slice(), combined.as_slice());
    } else {
        assert_eq!(report.method, "auto -> l1 (prior)");
        said(&report, "no combiner (");
        assert_eq!(auto.as_slice(), l1.as_slice());
    }

    let mut off = MethodConfig::default_for(Method::Auto);
    off.set_assignment("use_combiner=false").unwrap();
    let (auto, report) = run(&frame, &off);
    assert_eq!(report.method, "auto -> l1 (prior)");
    said(&report, "no combiner (use_combiner is false)");
    assert_eq!(auto.as_slice(), l1.as_slice());
    // Without a layer the combiner reads: L1 on the prior, saying which is missing.
    let bare = frame
        .into_builder()
        .without(Layer::Variance)
        .build(Policy::Replace)
        .unwrap();
    let (auto, report) = run(&bare, &config);
    assert_eq!(report.method, "auto -> l1 (prior)");
    said(&report, "no combiner (the frame lacks variance)");
    let (l1, _) = run(&bare, &MethodConfig::PoissonL1(PoissonL1Config::prior()));
    assert_eq!(auto.as_slice(), l1.as_slice());
}

#[test]
fn every_prior_path_runs_with_the_prior_as_input() {
    let frame = io::read_bundle(root().join("examples/data/sample.exr"), Policy::Replace).unwrap();
    let (prior, _) = run(&frame, &MethodConfig::default_for(Method::Prior));
    let base = rel_mse(frame.color(), &frame);
    for (method, setting) in [
        (Method::Frgr, "guide=prior"),
        (Method::PoissonL2, "data=prior"),
        (Method::PoissonL1, "data=prior"),
    ] {
        let mut config = MethodConfig::default_for(method);
        config.set_assignment(setting).unwrap();
        let (out, _) = run(&frame, &config);
        let error = rel_mse(&out, &frame);
        println!(
            "{method}:{setting} {error:.4e} (prior {:.4e})",
            rel_mse(&prior, &frame)
        );
        assert!(
            error < 0.1 * base,
            "{method}:{setting}: {error:e}, base {base:e}"
        );
    }
}

fn gdrecon() -> Command {
    let mut c = Command::cargo_bin("gdrecon").unwrap();
    c.current_dir(root());
    c
}

/// Runs `gdrecon reconstruct` on the sample with OIDN's search pointed nowhere (no variable,
/// an empty Python environment) and `extra` arguments; returns (success, stderr).
fn reconstruct_without_oidn(method: &[&str], extra: &[&str]) -> (bool, String) {
    let dir = tempfile::tempdir().unwrap();
    let out = gdrecon()
        .args(["reconstruct", "examples/data/sample.exr", "-o"])
        .arg(dir.path().join("x.exr"))
        .args(method)
        .args(extra)
        .env_remove("OIDN_DYLIB_PATH")
        .env("GDRECON_VENV", dir.path().join("no-venv"))
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned() + &String::from_utf8_lossy(&out.stdout),
    )
}

#[test]
fn missing_oidn_is_one_clear_error_and_other_methods_still_work() {
    let (ok, err) = reconstruct_without_oidn(&["--method", "prior"], &[]);
    assert!(!ok);
    for part in [
        "needs Intel Open Image Denoise 2",
        "1. explicit path (ContextOptions::oidn, --oidn, \"oidn_path\"): not given",
        "2. OIDN_DYLIB_PATH: not set",
        "3. next to the gdrecon library",
        "4. the project's Python environment",
        "no pyoidn package there",
        "onnx/setup.sh",
    ] {
        assert!(err.contains(part), "'{part}' missing from:\n{err}");
    }
    for method in ["l2", "l1", "frgr"] {
        let (ok, err) = reconstruct_without_oidn(&["--method", method], &[]);
        assert!(ok, "{method} failed without OIDN:\n{err}");
    }
    // The prior paths fail the same way.
    let (ok, err) = reconstruct_without_oidn(&["--method", "l1", "--preset", "prior"], &[]);
    assert!(
        !ok && err.contains("needs Intel Open Image Denoise 2"),
        "{err}"
    );
    // auto falls back and says why.
    let (ok, err) = reconstruct_without_oidn(&["--method", "auto"], &[]);
    assert!(ok, "{err}");
    assert!(
        err.contains("auto: no prior (unsupported: this method needs Intel Open Image Denoise 2"),
        "{err}"
    );
}

#[test]
fn an_explicit_library_is_the_only_one_tried_and_its_fault_is_named() {
    let dir = tempfile::tempdir().unwrap();
    // Missing.
    let (ok, err) = reconstruct_without_oidn(
        &["--method", "prior"],
        &["--oidn", "/nonexistent/libOpenImageDenoise.so.2"],
    );
    assert!(!ok);
    assert!(
        err.contains("/nonexistent/libOpenImageDenoise.so.2 does not exist")
            && !err.contains("2. OIDN_DYLIB_PATH"),
        "{err}"
    );
    // Damaged: not a shared library at all.
    let damaged = dir.path().join("libOpenImageDenoise.so.2");
    std::fs::write(&damaged, b"\x7fELF but not really a library").unwrap();
    let (ok, err) = reconstruct_without_oidn(
        &["--method", "prior"],
        &["--oidn", damaged.to_str().unwrap()],
    );
    assert!(!ok);
    assert!(
        err.contains("cannot be loaded as a shared library"),
        "{err}"
    );
    // A real shared library that is not OIDN (gdrecon's own, built beside the CLI).
    let exe = assert_cmd::cargo::cargo_bin("gdrecon");
    let other = exe.parent().unwrap().join("libgdrecon.so");
    if other.is_file() {
        let (ok, err) =
            reconstruct_without_oidn(&["--method", "prior"], &["--oidn", other.to_str().unwrap()]);
        assert!(!ok);
        assert!(
            err.contains("is not Open Image Denoise 2: it lacks oidnNewDevice"),
            "{err}"
        );
    }
}

#[test]
fn a_bundle_with_a_prior_layer_needs_no_oidn() {
    let dir = tempfile::tempdir().unwrap();
    let frame = io::read_bundle(root().join("examples/data/sample.exr"), Policy::Replace).unwrap();
    let prior = frame.reference().unwrap().clone();
    let frame = common::with_prior(frame, prior);
    let bundle = dir.path().join("with-prior.exr");
    io::write_bundle(&bundle, &frame).unwrap();
    let back = io::read_bundle(&bundle, Policy::Replace).unwrap();
    assert_eq!(
        back.prior().unwrap().as_slice(),
        frame.prior().unwrap().as_slice()
    );
    let out = gdrecon()
        .args(["reconstruct", "--method", "l1", "--preset", "prior", "-o"])
        .arg(dir.path().join("x.exr"))
        .arg(&bundle)
        .args(["--oidn", "/nonexistent/libOpenImageDenoise.so.2"])
        .env_remove("OIDN_DYLIB_PATH")
        .env("GDRECON_VENV", dir.path().join("no-venv"))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        text.contains("prior: the frame's 'prior' layer (given by the caller)"),
        "{text}"
    );
}

/// A plan for frames that bring their own prior (`MethodConfig::given_prior`, what the CLI
/// plans for such a bundle) is held to the limit without OIDN's scratch: `l1 --preset prior`
/// runs the bundle with a `prior` layer under a limit that refuses it for the bundle without
/// one, and a plan made that way refuses a frame without the layer instead of running OIDN.
#[test]
fn a_plan_for_given_priors_is_held_to_less_and_refuses_frames_without_one() {
    const MIB: u64 = 1 << 20;
    let dir = tempfile::tempdir().unwrap();
    let sample = root().join("examples/data/sample.exr");
    let frame = io::read_bundle(&sample, Policy::Replace).unwrap();
    let (w, h) = frame.size();
    let with_prior = common::with_prior(frame.clone(), frame.reference().unwrap().clone());
    let bundle = dir.path().join("with-prior.exr");
    io::write_bundle(&bundle, &with_prior).unwrap();
    let l1 = MethodConfig::PoissonL1(PoissonL1Config::prior());
    let computed = l1.fitted_to(w, h, 0).memory_estimate(w, h).div_ceil(MIB);
    let given = l1.given_prior().memory_estimate(w, h).div_ceil(MIB);
    assert!(given + 2 < computed, "{given} {computed}");
    let limit = (given + 1).to_string();
    let cli = |input: &Path| {
        gdrecon()
            .args(["reconstruct", "--method", "l1", "--preset", "prior", "-o"])
            .arg(dir.path().join("x.exr"))
            .arg(input)
            .args(["--max-memory-mb", &limit])
            .output()
            .unwrap()
    };
    let ok = cli(&bundle);
    let said = String::from_utf8_lossy(&ok.stdout);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    assert!(said.contains("prior: the frame's 'prior' layer"), "{said}");
    let refused = cli(&sample);
    let why = String::from_utf8_lossy(&refused.stderr);
    assert!(
        !refused.status.success() && why.contains("needs about"),
        "{why}"
    );

    let context = Context::new(ContextOptions::with_threads(Some(2))).unwrap();
    let mut plan = Plan::new(&context, &l1.given_prior(), w, h).unwrap();
    let (out, _) = plan.execute(&with_prior, &Progress::none()).unwrap();
    let (same, _) = run(&with_prior, &l1);
    assert_eq!(out.as_slice(), same.as_slice());
    let e = plan
        .execute(&frame, &Progress::none())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("bring their own prior") && e.contains("has none"),
        "{e}"
    );
}

/// Under `max_memory_mb` OIDN gets less scratch (`maxMemoryMB` 512 instead of 1024 here) and
/// denoises in tiles: the same image, bit for bit.
#[test]
fn a_memory_limit_tiles_oidn_to_the_same_image() {
    let (w, h) = (1280, 768); // 580 B a pixel of scratch: 544 MiB, over 512
    let frame = gdrecon::synth::synthetic_frame(w, h, 8.0, 7);
    let config = MethodConfig::default_for(Method::Prior);
    let least = config.fitted_to(w, h, 0).memory_estimate(w, h);
    assert!(least < config.memory_estimate(w, h));
    let options = ContextOptions::with_threads(Some(2)).with_max_memory_mb(least.div_ceil(1 << 20));
    let context = Context::new(options).unwrap();
    let mut plan = Plan::new(&context, &config, w, h).unwrap();
    let (tiled, report) = plan.execute(&frame, &Progress::none()).unwrap();
    let (whole, free) = run(&frame, &config);
    assert_eq!(tiled.as_slice(), whole.as_slice());
    let scratch = |report: &Report| {
        report
            .notes
            .iter()
            .find_map(|n| n.split(", ").find(|p| p.starts_with("scratch")))
            .unwrap()
            .to_owned()
    };
    assert_eq!(
        scratch(&report),
        "scratch 512 MiB (lowered to fit the memory limit)"
    );
    assert_eq!(scratch(&free), "scratch 1024 MiB");
}

/// A frame that brings its own prior never allocates OIDN's scratch: under a limit that leaves
/// the combiner out for frames OIDN must denoise (their scratch counted: 580 B a pixel, 127 MiB
/// at 640 x 360), a frame with a `prior` layer still takes it, and the same frame without the
/// layer does not. The combiner then runs in tiles fitted without the scratch.
#[test]
fn a_frame_with_its_own_prior_is_held_to_the_combiner_without_oidn() {
    if !cfg!(feature = "gradnet") {
        return;
    }
    const MIB: u64 = 1 << 20;
    let (w, h) = (640, 360);
    let least = MethodConfig::Combiner(AutoConfig::default().combiner)
        .fitted_to(w, h, 0)
        .memory_estimate(w, h)
        .div_ceil(MIB);
    let options = ContextOptions::with_threads(Some(2)).with_max_memory_mb(least - 60);
    let context = Context::new(options).unwrap();
    let auto = MethodConfig::Auto(AutoConfig::default());
    let mut plan = Plan::new(&context, &auto, w, h).unwrap();
    let frame = gdrecon::synth::synthetic_frame(w, h, 16.0, 7);
    let given = common::with_prior(frame.clone(), frame.color().clone());
    let (out, report) = plan.execute(&given, &Progress::none()).unwrap();
    assert!(out.all_finite());
    assert_eq!(report.method, "auto -> combiner", "{:?}", report.notes);
    // In tiles fitted without the scratch: larger than the least (96 x 96) that the fit with
    // it comes down to.
    let tiles = report
        .notes
        .iter()
        .find_map(|n| n.split("tile(s) of ").nth(1));
    let side = |s: &str| s.trim().parse::<usize>().unwrap();
    let pixels = tiles
        .and_then(|t| t.split_once(" x "))
        .map(|(a, b)| side(a) * side(b));
    assert!(pixels > Some(2 * 96 * 96), "{:?}", report.notes);
    let (out, report) = plan.execute(&frame, &Progress::none()).unwrap();
    assert!(out.all_finite());
    // The combiner with OIDN's scratch is what the limit left out.
    assert_eq!(report.method, "auto -> l1 (prior)", "{:?}", report.notes);
    let why = format!("no combiner (needs about {least} MiB");
    assert!(report.notes[0].contains(&why), "{:?}", report.notes);
}
