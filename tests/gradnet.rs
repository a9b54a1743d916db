//! GradNet through the public API and the CLI: the whole pipeline against the Python reference
//! (`onnx/gdrecon_py/pipeline.py` with the torch model; fixtures from `onnx/gdrecon_py/make_fixtures.py`), tiling
//! against the untiled run, and each failure a distinct, clear error.
//!
//! Needs ONNX Runtime 1.31 (found by the library's discovery: `bash onnx/setup.sh` installs
//! it). Tolerances: the pipeline matches Python to 1e-4 relative (|a - b| <= 1e-4 (|b| + 1e-3)),
//! in fp32 against the torch model, in int8 (the default precision) against onnxruntime in
//! Python running `onnx/gradnet_int8_nhwc.onnx` (the same kernels, so the same bound holds);
//! tiled matches untiled to the same bound.
#![cfg(all(feature = "gradnet", feature = "embed-model"))]

use std::path::{Path, PathBuf};

use assert_cmd::Command;
use gdrecon::recon::{GradNetConfig, GradNetPrecision};
use gdrecon::{
    io, Context, ContextOptions, Error, Frame, Image, Layer, MethodConfig, Plan, Policy, Progress,
};
use ndarray::{Array3, ArrayD};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/gradnet")
        .join(name)
}

fn expected(name: &str) -> Image {
    let a: ArrayD<f32> = ndarray_npy::read_npy(fixture(name)).unwrap();
    let a: Array3<f32> = a.into_dimensionality().unwrap();
    Image::from_hwc(a.view())
}

fn context() -> Context {
    Context::new(ContextOptions::with_threads(Some(2))).unwrap()
}

fn run(frame: &Frame, config: GradNetConfig) -> gdrecon::Result<Image> {
    let mut plan = Plan::new(
        &context(),
        &MethodConfig::GradNet(config),
        frame.width(),
        frame.height(),
    )?;
    Ok(plan.execute(frame, &Progress::none())?.0)
}

fn assert_close(got: &Image, want: &Image, what: &str) {
    assert_eq!(got.size(), want.size(), "{what}");
    let mut worst = 0.0f32;
    for (g, w) in got.as_slice().iter().zip(want.as_slice()) {
        worst = worst.max((g - w).abs() / (w.abs() + 1e-3));
    }
    println!("{what}: worst relative difference {worst:e}");
    assert!(worst <= 1e-4, "{what}: worst relative difference {worst:e}");
}

/// The defaults without the noise band: the library's post-process around every method
/// (`recon/band.rs`, tested there), not a step of the Python pipeline these tests hold it to.
fn pipeline() -> GradNetConfig {
    let mut c = GradNetConfig::default();
    c.noise_band = 0.0;
    c
}

/// The fp32 graph, which the torch fixtures hold (the default, named where a test relies on it).
fn fp32() -> GradNetConfig {
    let mut c = pipeline();
    c.precision = GradNetPrecision::Fp32;
    c
}

/// The int8 graph (`precision=int8`).
fn int8() -> GradNetConfig {
    let mut c = pipeline();
    c.precision = GradNetPrecision::Int8;
    c
}

fn crop(name: &str) -> Frame {
    io::read_bundle(fixture(&format!("{name}.exr")), Policy::Replace).unwrap()
}

fn sample() -> Frame {
    io::read_bundle(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/data/sample.exr"),
        Policy::Replace,
    )
    .unwrap()
}

fn without_features(frame: Frame) -> Frame {
    frame
        .into_builder()
        .without(Layer::Albedo)
        .without(Layer::Normal)
        .without(Layer::Depth)
        .build(Policy::Replace)
        .unwrap()
}

#[test]
fn pipeline_matches_the_python_reference() {
    for name in ["crop_a", "crop_b"] {
        let frame = crop(name);
        let full = run(&frame, fp32()).unwrap();
        assert_close(&full, &expected(&format!("{name}_out.npy")), name);

        let mut no_bias = fp32();
        no_bias.bias_correction = false;
        let raw = run(&frame, no_bias).unwrap();
        assert_close(&raw, &expected(&format!("{name}_out_nobias.npy")), name);

        // A frame without features runs the no-feature model, and so does use_features off.
        let nofeat_want = expected(&format!("{name}_nofeat_out.npy"));
        let bare = run(&without_features(frame.clone()), pipeline()).unwrap();
        assert_close(&bare, &nofeat_want, &format!("{name} without features"));
        let mut off = pipeline();
        off.use_features = false;
        assert_close(&run(&frame, off).unwrap(), &nofeat_want, name);
    }
}

/// `precision=int8` against `pipeline.reconstruct` with onnxruntime running
/// `onnx/gradnet_int8_nhwc.onnx` in Python (`make_fixtures --int8`); and how far int8 is from the
/// fp32 pipeline on these crops (printed; docs/gradnet.md, "Reduced precision").
#[test]
fn int8_pipeline_matches_onnxruntime_in_python() {
    for name in ["crop_a", "crop_b"] {
        let frame = crop(name);
        let int8 = run(&frame, int8()).unwrap();
        assert_close(&int8, &expected(&format!("{name}_int8_out.npy")), name);
        let fp = run(&frame, fp32()).unwrap();
        let d = gdrecon::metrics::compare(&int8, &fp).unwrap().rel_mse;
        println!("{name}: relMSE of int8 against fp32 {d:e}");
        assert!(d < 1e-3, "{name}: int8 strays from fp32: relMSE {d:e}");
    }
}

/// The emitter rules (`range_limit`, the pipeline's step 6b, and `bias_limit`, its step 7) on a
/// frame with bulbs in view (the `lamps` guard frame; fixture from `make_fixtures --emitter`,
/// onnxruntime): the same pixels keep their base colour before the bias correction and the same
/// ones stay out of its gain, so the output matches the Python reference; without the rules it
/// does not, and its error is larger (the bar of 1.5x dates from the emitter rule alone: 2.2x
/// with the model trained on HDR frames, nineteenth session); without the bias limit alone, 10x.
#[test]
fn emitter_rule_matches_the_python_reference() {
    let frame = crop("emitter");
    let want = expected("emitter_out.npy");
    let ours = run(&frame, fp32()).unwrap();
    assert_close(&ours, &want, "emitter");
    let mut release = fp32();
    release.range_limit = 0.0;
    release.bias_limit = 0.0;
    let without = run(&frame, release).unwrap();
    let reference = frame.reference().unwrap();
    let (with_rule, no_rule) = (
        gdrecon::metrics::compare(&ours, reference).unwrap().rel_mse,
        gdrecon::metrics::compare(&without, reference)
            .unwrap()
            .rel_mse,
    );
    assert!(
        no_rule > 1.5 * with_rule,
        "release {no_rule:e}, rule {with_rule:e}"
    );
    // The bias limit alone: the bulbs' noisy edges, which the network cannot output, raised
    // the gain over the whole room (8.7e-2 against 8.9e-3 with it).
    let mut unlimited = fp32();
    unlimited.bias_limit = 0.0;
    let spread = run(&frame, unlimited).unwrap();
    let spread = gdrecon::metrics::compare(&spread, reference)
        .unwrap()
        .rel_mse;
    assert!(
        spread > 3.0 * with_rule,
        "bias_limit=0 {spread:e}, default {with_rule:e}"
    );
}

#[test]
fn tiles_match_the_untiled_run() {
    let frame = sample();
    let mut whole = GradNetConfig::default();
    whole.tile_pixels = 0;
    let mut tiled = GradNetConfig::default();
    tiled.whole_pixels = 0;
    tiled.tile_pixels = 232 * 184; // 320 x 184 padded: 4 tiles of 224 x 184
    let mut plan = Plan::new(&context(), &MethodConfig::GradNet(tiled), 320, 180).unwrap();
    let (got, report) = plan.execute(&frame, &Progress::none()).unwrap();
    assert!(
        report.notes.iter().any(|n| n.contains("4 tile(s)")),
        "{:?}",
        report.notes
    );
    assert_close(&got, &run(&frame, whole).unwrap(), "tiled");
}

/// The int8 default lays tiles out for the int8 graph's budgets; a frame without features runs
/// the fp32 no-feature model, which takes 3x the memory a pixel, in tiles of half the budgets,
/// and the same plan goes back to the int8 tiles for a frame with features.
/// The tiles a GradNet run reports: "N tile(s) of W x H".
fn tiles(report: &gdrecon::Report) -> String {
    report
        .notes
        .iter()
        .find_map(|n| {
            n.split(", ")
                .find(|p| p.contains("tile(s)"))
                .map(str::to_owned)
        })
        .unwrap()
}

#[test]
fn an_fp32_graph_runs_in_tiles_of_half_the_budgets() {
    let frame = sample(); // 320 x 184 padded: 58880 pixels
    let featureless = without_features(frame.clone());
    let mut config = GradNetConfig::default();
    config.whole_pixels = 60_000;
    config.tile_pixels = 2 * 232 * 184; // fp32: 4 tiles of 224 x 184
    let ctx = context();
    let mut plan = Plan::new(&ctx, &MethodConfig::GradNet(config), 320, 180).unwrap();
    let (fp32, report) = plan.execute(&featureless, &Progress::none()).unwrap();
    assert_eq!(tiles(&report), "4 tile(s) of 224 x 184");
    let (int8, report) = plan.execute(&frame, &Progress::none()).unwrap();
    assert_eq!(tiles(&report), "1 tile(s) of 320 x 184");
    let mut whole = GradNetConfig::default();
    whole.tile_pixels = 0;
    assert_close(
        &fp32,
        &run(&featureless, whole.clone()).unwrap(),
        "fp32 tiled",
    );
    assert_eq!(int8.as_slice(), run(&frame, whole).unwrap().as_slice());
}

/// `max_memory_mb` tiles each graph by its own bytes a pixel: just under the estimate of the
/// default (the fp32 no-feature model's, run whole), a featureless frame runs the fp32 model
/// in tiles and a frame with features still runs the int8 graph whole; the images are those
/// of a plan without a limit. Under the least tiles' estimate the plan is refused. (A frame
/// larger than the least tile a limit lowers the budget to, 384 x 384: the sample is smaller,
/// and would be refused.)
#[test]
fn a_memory_limit_tiles_each_graph_by_its_own_bytes() {
    let frame = gdrecon::synth::synthetic_frame(512, 320, 16.0, 5);
    let featureless = without_features(frame.clone());
    let config = MethodConfig::GradNet(GradNetConfig::default());
    let (w, h) = (frame.width(), frame.height());
    let mib = |bytes: u64| bytes.div_ceil(1 << 20);
    let limited = |mb: u64| {
        let options = ContextOptions::with_threads(Some(2)).with_max_memory_mb(mb);
        Plan::new(&Context::new(options).unwrap(), &config, w, h)
    };
    let limit = mib(config.memory_estimate(w, h)) - 2;
    let mut plan = limited(limit).unwrap();
    let (fp32, report) = plan.execute(&featureless, &Progress::none()).unwrap();
    assert!(!tiles(&report).starts_with("1 tile(s)"), "{report:?}");
    let (int8, report) = plan.execute(&frame, &Progress::none()).unwrap();
    assert_eq!(tiles(&report), "1 tile(s) of 512 x 320");
    let free = GradNetConfig::default();
    assert_close(
        &fp32,
        &run(&featureless, free.clone()).unwrap(),
        "fp32 fitted",
    );
    assert_eq!(int8.as_slice(), run(&frame, free).unwrap().as_slice());
    let least = mib(config.fitted_to(w, h, 0).memory_estimate(w, h));
    limited(least).unwrap();
    let err = limited(least - 1).unwrap_err();
    assert!(
        matches!(err, gdrecon::Error::OutOfMemory(_)) && err.to_string().contains("gradnet"),
        "{err}"
    );
    // The sample (320 x 184 padded) is within one least tile: no limit under its estimate
    // tiles it, so none is planned.
    let (sw, sh) = (sample().width(), sample().height());
    let whole = config.memory_estimate(sw, sh);
    assert!(
        config
            .fitted_to(sw, sh, whole - (2 << 20))
            .memory_estimate(sw, sh)
            >= whole
    );
}

#[test]
fn plans_reuse_the_context_session_and_report_what_ran() {
    let frame = crop("crop_a");
    let ctx = context();
    let config = MethodConfig::GradNet(GradNetConfig::default());
    let mut a = Plan::new(&ctx, &config, frame.width(), frame.height()).unwrap();
    let (first, report) = a.execute(&frame, &Progress::none()).unwrap();
    assert!(report.stages.iter().any(|s| s.name == "network"));
    assert!(report
        .notes
        .iter()
        .any(|n| n.contains("embedded gradnet_int8_nhwc.onnx")));
    let mut b = Plan::new(&ctx, &config, frame.width(), frame.height()).unwrap();
    let (second, _) = b.execute(&frame, &Progress::none()).unwrap();
    assert_eq!(
        first.as_slice(),
        second.as_slice(),
        "same session, same result"
    );
    // Albedo and normal without depth: the report names what is missing.
    let no_depth = frame
        .clone()
        .into_builder()
        .without(Layer::Depth)
        .build(Policy::Replace)
        .unwrap();
    let (_, report) = a.execute(&no_depth, &Progress::none()).unwrap();
    assert!(
        report
            .skipped
            .iter()
            .any(|s| s.contains("lacks depth (") && s.contains("no-feature model")),
        "{:?}",
        report.skipped
    );
    let bare = without_features(frame);
    let (_, report) = a.execute(&bare, &Progress::none()).unwrap();
    assert!(
        report
            .skipped
            .iter()
            .any(|s| s.contains("lacks albedo, normal, depth")),
        "{:?}",
        report.skipped
    );
}

#[test]
fn model_errors_are_distinct() {
    let dir = tempfile::tempdir().unwrap();
    let frame = crop("crop_a");
    let with_model = |path: PathBuf| {
        let mut c = GradNetConfig::default();
        c.model = Some(path);
        run(&frame, c).unwrap_err()
    };
    // Missing file: an I/O error naming it.
    let missing = with_model(dir.path().join("absent.onnx"));
    assert!(matches!(missing, Error::Io { .. }), "{missing}");
    assert!(missing.to_string().contains("absent.onnx"), "{missing}");

    // Wrong hash: the committed model with one byte changed.
    let mut bytes =
        std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("onnx/gradnet.onnx")).unwrap();
    let n = bytes.len();
    bytes[n / 2] ^= 1;
    let altered = dir.path().join("altered.onnx");
    std::fs::write(&altered, &bytes).unwrap();
    let wrong = with_model(altered.clone());
    assert!(matches!(wrong, Error::Model(_)), "{wrong}");
    assert!(
        wrong.to_string().contains("not that of an exported model"),
        "{wrong}"
    );
    std::fs::write(dir.path().join("altered.onnx.sha256"), "0".repeat(64)).unwrap();
    let mismatch = with_model(altered);
    assert!(
        mismatch.to_string().contains("recorded at export"),
        "{mismatch}"
    );

    // Corrupted: garbage whose recorded hash matches, so ONNX Runtime is what rejects it.
    let garbage = dir.path().join("garbage.onnx");
    std::fs::write(&garbage, b"this is not protobuf").unwrap();
    let digest = std::process::Command::new("sha256sum")
        .arg(&garbage)
        .output()
        .unwrap();
    std::fs::write(
        dir.path().join("garbage.onnx.sha256"),
        String::from_utf8(digest.stdout).unwrap(),
    )
    .unwrap();
    let corrupted = with_model(garbage);
    assert!(matches!(corrupted, Error::Model(_)), "{corrupted}");
    assert!(
        corrupted
            .to_string()
            .contains("ONNX Runtime cannot load it"),
        "{corrupted}"
    );

    // The full model on a frame without features.
    let mut c = GradNetConfig::default();
    c.model = Some(Path::new(env!("CARGO_MANIFEST_DIR")).join("onnx/gradnet.onnx"));
    let needs = run(&without_features(frame.clone()), c).unwrap_err();
    assert!(matches!(needs, Error::InvalidInput(_)), "{needs}");
    assert!(
        needs.to_string().contains("albedo, normal and depth"),
        "{needs}"
    );

    // A tile too small for the receptive field.
    let mut c = GradNetConfig::default();
    c.tile_pixels = 100 * 100;
    let small = run(&crop("crop_a"), c);
    assert!(small.is_ok(), "a frame within whole_pixels is one tile");
    let big = sample();
    let mut c = GradNetConfig::default();
    c.whole_pixels = 0;
    c.tile_pixels = 100 * 100;
    let err = run(&big, c).unwrap_err();
    assert!(matches!(err, Error::InvalidArgument(_)), "{err}");
    assert!(
        err.to_string().contains("tile_pixels 10000 is too small"),
        "{err}"
    );
}

fn gdrecon() -> Command {
    Command::cargo_bin("gdrecon").unwrap()
}

#[test]
fn cli_reconstructs_the_sample_and_reports_relmse() {
    let out = tempfile::tempdir().unwrap();
    let assert = gdrecon()
        .args([
            "reconstruct",
            "examples/data/sample.exr",
            "--method",
            "gradnet",
            "-o",
        ])
        .arg(out.path().join("g.exr"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .assert()
        .success();
    let text = String::from_utf8_lossy(&assert.get_output().stdout).to_string();
    let relmse = |label: &str| -> f64 {
        let line = text
            .lines()
            .find(|l| l.starts_with(label))
            .unwrap_or_else(|| panic!("no '{label}' line in:\n{text}"));
        line.split_whitespace().nth(2).unwrap().parse().unwrap()
    };
    assert!(relmse("gradnet") < 0.2 * relmse("base"), "{text}");
}

#[test]
fn missing_runtime_is_one_clear_error_and_other_methods_still_work() {
    let out = tempfile::tempdir().unwrap();
    let cmd = |method: &str| {
        let mut c = gdrecon();
        c.args([
            "reconstruct",
            "examples/data/sample.exr",
            "--method",
            method,
            "-o",
        ])
        .arg(out.path().join("x.exr"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .env_remove("ORT_DYLIB_PATH")
        .env("GDRECON_VENV", out.path().join("no-venv"));
        c
    };
    let failed = cmd("gradnet").assert().failure();
    let err = String::from_utf8_lossy(&failed.get_output().stderr).to_string();
    for part in [
        "GradNet and the combiner need ONNX Runtime",
        "1. explicit path",
        "2. ORT_DYLIB_PATH: not set",
        "3. next to the gdrecon library",
        "4. the project's Python environment",
        "onnx/setup.sh",
    ] {
        assert!(err.contains(part), "'{part}' missing from:\n{err}");
    }
    for method in ["l2", "l1"] {
        cmd(method).assert().success();
    }
    // An explicit path that does not exist is named.
    let failed = cmd("gradnet")
        .args(["--onnxruntime", "/nonexistent/libonnxruntime.so"])
        .assert()
        .failure();
    let err = String::from_utf8_lossy(&failed.get_output().stderr).to_string();
    assert!(
        err.contains("/nonexistent/libonnxruntime.so does not exist"),
        "{err}"
    );
}

#[test]
fn thread_count_changes_results_only_by_rounding() {
    // ONNX Runtime splits the convolutions by thread, so sums are reordered: results agree to
    // rounding (the native stages are bit-identical for any thread count, as everywhere).
    let frame = crop("crop_a");
    let config = MethodConfig::GradNet(GradNetConfig::default());
    let mut outs = Vec::new();
    for threads in [1, 2, 3] {
        let ctx = Context::new(ContextOptions::with_threads(Some(threads))).unwrap();
        let mut plan = Plan::new(&ctx, &config, frame.width(), frame.height()).unwrap();
        outs.push(plan.execute(&frame, &Progress::none()).unwrap().0);
    }
    assert_close(&outs[1], &outs[0], "2 vs 1 threads");
    assert_close(&outs[2], &outs[0], "3 vs 1 threads");
}
