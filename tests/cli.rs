//! The `gdrecon` binary end to end: a synthetic bundle on disk, each subcommand, exit codes.

use assert_cmd::Command;

fn gdrecon() -> Command {
    Command::cargo_bin("gdrecon").unwrap()
}

fn out(cmd: &mut Command) -> String {
    let o = cmd.assert().success().get_output().stdout.clone();
    String::from_utf8(o).unwrap()
}

#[test]
fn demo_reconstruct_eval_info() {
    let dir = tempfile::tempdir().unwrap();
    let bundle = dir.path().join("demo.exr");
    out(gdrecon()
        .args([
            "demo", "--width", "64", "--height", "40", "--spp", "8", "-o",
        ])
        .arg(&bundle));
    let info = out(gdrecon().arg("info").arg(&bundle));
    assert!(
        info.contains("64 x 40") && info.contains("spp: 8") && info.contains("reference"),
        "{info}"
    );
    for method in ["l2", "l1"] {
        let result = dir.path().join(format!("{method}.exr"));
        let png = dir.path().join(format!("{method}.png"));
        let text = out(gdrecon()
            .arg("reconstruct")
            .arg(&bundle)
            .args(["--method", method, "--threads", "2", "-o"])
            .arg(&result)
            .arg("--png")
            .arg(&png));
        assert!(
            text.contains(&format!("method {method}")) && text.contains("relMSE"),
            "{text}"
        );
        let reference = gdrecon::io::read_bundle(&bundle, gdrecon::Policy::Replace).unwrap();
        let img = gdrecon::io::read_rgb(&result).unwrap();
        assert_eq!(img.size(), (64, 40));
        let m = gdrecon::metrics::compare(&img, reference.reference().unwrap()).unwrap();
        let base =
            gdrecon::metrics::compare(reference.color(), reference.reference().unwrap()).unwrap();
        assert!(
            m.rel_mse < base.rel_mse,
            "{method}: {} vs base {}",
            m.rel_mse,
            base.rel_mse
        );
        assert!(png.exists());
        let eval = out(gdrecon()
            .arg("eval")
            .arg(&result)
            .arg("--reference")
            .arg(&bundle));
        assert!(
            eval.contains(&format!("relMSE {:.5e}", m.rel_mse)),
            "{eval} vs {}",
            m.rel_mse
        );
    }
    let quiet = out(gdrecon()
        .arg("reconstruct")
        .arg(&bundle)
        .arg("-q")
        .arg("-o")
        .arg(dir.path().join("q.exr")));
    assert!(quiet.is_empty(), "{quiet}");
}

/// `eval BUNDLE` scores the bundle's colour (its base image), not its reference; a reference
/// holding NaN is refused, never scored as "relMSE NaN".
#[test]
fn eval_scores_a_bundles_colour_and_refuses_a_nan_reference() {
    let dir = tempfile::tempdir().unwrap();
    let bundle = dir.path().join("demo.exr");
    let frame = gdrecon::synth::synthetic_frame(24, 16, 4.0, 5);
    gdrecon::io::write_bundle(&bundle, &frame).unwrap();
    let base = gdrecon::metrics::compare(frame.color(), frame.reference().unwrap()).unwrap();
    assert!(base.rel_mse > 1e-4);
    let eval = out(gdrecon().arg("eval").arg(&bundle).arg("-r").arg(&bundle));
    assert!(
        eval.contains(&format!("relMSE {:.5e}", base.rel_mse)),
        "{eval}"
    );

    let mut reference = frame.reference().unwrap().clone();
    reference.plane_mut(1)[[2, 3]] = f32::NAN;
    let nan = dir.path().join("nan_reference.exr");
    gdrecon::io::write_rgb(&nan, &reference).unwrap();
    let o = gdrecon()
        .arg("eval")
        .arg(&bundle)
        .arg("-r")
        .arg(&nan)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("reference holds 1 non-finite"), "{stderr}");
    assert_eq!(stderr.trim_end().lines().count(), 1, "{stderr}");
}

/// Values replaced while reading are reported, with and without `--spp` (which once rebuilt
/// the frame, sanitising its clean layers again and reporting nothing replaced).
#[test]
fn replaced_values_are_reported_whatever_the_spp() {
    use exr::prelude::{self as x, WritableImage};
    let dir = tempfile::tempdir().unwrap();
    let bundle = dir.path().join("nan.exr");
    let (w, h) = (24, 16);
    let channels = ["color", "dx", "dy"].into_iter().flat_map(|layer| {
        ["R", "G", "B"].map(|c| {
            let mut v = vec![0.25f32; w * h];
            if layer == "color" && c == "G" {
                (v[5], v[40]) = (f32::NAN, -1.0);
            }
            let name = x::Text::from(format!("{layer}.{c}").as_str());
            x::AnyChannel::new(name, x::FlatSamples::F32(v))
        })
    });
    let layer = x::Layer::new(
        (w, h),
        x::LayerAttributes::default(),
        x::Encoding::FAST_LOSSLESS,
        x::AnyChannels::sort(channels.collect()),
    );
    x::Image::from_layer(layer)
        .write()
        .to_file(&bundle)
        .unwrap();
    for spp in [None, Some("8")] {
        let mut cmd = gdrecon();
        cmd.arg("reconstruct")
            .arg(&bundle)
            .arg("-o")
            .arg(dir.path().join("o.exr"));
        if let Some(s) = spp {
            cmd.args(["--spp", s]);
        }
        let said = out(&mut cmd);
        assert!(
            said.contains("replaced by 0: color: 1 non-finite 1 negative"),
            "--spp {spp:?}: {said}"
        );
    }
}

#[test]
fn errors_are_one_line_with_nonzero_exit() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing.exr");
    let a = gdrecon()
        .arg("reconstruct")
        .arg(&missing)
        .arg("-o")
        .arg(dir.path().join("o.exr"))
        .assert()
        .code(1);
    let err = String::from_utf8(a.get_output().stderr.clone()).unwrap();
    assert!(
        err.starts_with("gdrecon: error:")
            && err.contains("missing.exr")
            && err.lines().count() == 1,
        "{err}"
    );

    let junk = dir.path().join("junk.exr");
    std::fs::write(&junk, "hello").unwrap();
    let a = gdrecon().arg("info").arg(&junk).assert().code(1);
    let err = String::from_utf8(a.get_output().stderr.clone()).unwrap();
    assert!(err.contains("junk.exr"), "{err}");

    let bundle = dir.path().join("d.exr");
    out(gdrecon()
        .args(["demo", "--width", "8", "--height", "8", "-o"])
        .arg(&bundle));
    let a = gdrecon()
        .arg("reconstruct")
        .arg(&bundle)
        .args(["-m", "nope", "-o"])
        .arg(dir.path().join("o.exr"))
        .assert()
        .code(1);
    let err = String::from_utf8(a.get_output().stderr.clone()).unwrap();
    assert!(
        err.contains("unknown method 'nope'") && err.contains("l2, l1"),
        "{err}"
    );
    let a = gdrecon()
        .arg("reconstruct")
        .arg(&bundle)
        .args(["--param", "alpha=-1", "-o"])
        .arg(dir.path().join("o.exr"))
        .assert()
        .code(1);
    assert!(String::from_utf8(a.get_output().stderr.clone())
        .unwrap()
        .contains("alpha is -1"));
    gdrecon().arg("reconstruct").assert().code(2);
}

/// Out-of-range sizes and counts from the command line are refused at once, in one line: no
/// abort (a 100000 x 100000 demo), no overflow panic (bench --synthetic), no 83 s of thread
/// spawning (--threads 100000), no usage page for a negative number or a usage error.
#[test]
fn absurd_arguments_get_one_line_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let bundle = dir.path().join("d.exr");
    out(gdrecon()
        .args(["demo", "--width", "8", "--height", "8", "-o"])
        .arg(&bundle));
    let o = dir.path().join("o.exr");
    let cases: Vec<(Vec<std::ffi::OsString>, i32, &str)> = vec![
        (
            vec![
                "demo".into(),
                "--width".into(),
                "100000".into(),
                "--height".into(),
                "100000".into(),
                "-o".into(),
                o.clone().into(),
            ],
            1,
            "at most 67108864 pixels",
        ),
        (
            vec![
                "bench".into(),
                "--synthetic".into(),
                "99999999999x99999999999".into(),
            ],
            1,
            "at most 67108864 pixels",
        ),
        (
            vec![
                "reconstruct".into(),
                bundle.clone().into(),
                "--threads".into(),
                "100000".into(),
                "-o".into(),
                o.clone().into(),
            ],
            1,
            "at most 1024",
        ),
        (
            vec![
                "reconstruct".into(),
                bundle.clone().into(),
                "--spp".into(),
                "-1".into(),
                "-o".into(),
                o.clone().into(),
            ],
            1,
            "spp is -1",
        ),
        (
            vec![
                "reconstruct".into(),
                bundle.clone().into(),
                "--bogus".into(),
            ],
            2,
            "unexpected argument '--bogus'",
        ),
    ];
    for (args, code, says) in cases {
        let t = std::time::Instant::now();
        let a = gdrecon().args(&args).assert().code(code);
        let err = String::from_utf8(a.get_output().stderr.clone()).unwrap();
        assert!(
            err.starts_with("gdrecon: error:") && err.contains(says) && err.lines().count() == 1,
            "{args:?}: {err}"
        );
        // Generous: a refusal does no work (the thread count took 83 s before).
        assert!(
            t.elapsed().as_secs() < 10,
            "{args:?} took {:?}",
            t.elapsed()
        );
    }
}

#[test]
fn bench_prints_a_table_and_csv() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("b.csv");
    let text = out(gdrecon()
        .args(["bench", "--synthetic", "48x32", "--runs", "3", "--csv"])
        .arg(&csv));
    assert!(text.contains("l2") && text.contains("l1"), "{text}");
    let table = std::fs::read_to_string(&csv).unwrap();
    assert_eq!(table.lines().count(), 3, "{table}");
}

#[test]
#[cfg(not(feature = "testing"))]
fn parameters_doc_is_generated_from_the_tables() {
    // docs/PARAMETERS.md is what `gdrecon params --markdown` prints: regenerate it with
    // `cargo run --release -- params --markdown > docs/PARAMETERS.md` when a table changes.
    let generated = out(gdrecon().args(["params", "--markdown"]));
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/docs/PARAMETERS.md");
    let committed = std::fs::read_to_string(path).unwrap();
    assert_eq!(
        committed, generated,
        "docs/PARAMETERS.md is stale: regenerate it with `gdrecon params --markdown`"
    );
}

#[test]
fn parameters_are_set_by_name_and_checked_against_their_range() {
    let dir = tempfile::tempdir().unwrap();
    let bundle = dir.path().join("demo.exr");
    out(gdrecon()
        .args(["demo", "--width", "40", "--height", "24", "-o"])
        .arg(&bundle));
    let listing = out(gdrecon().args(["params", "l1"]));
    assert!(
        listing.contains("reweight_steps") && listing.contains("preset published"),
        "{listing}"
    );
    let run = |args: &[&str]| {
        let mut cmd = gdrecon();
        cmd.arg("reconstruct")
            .arg(&bundle)
            .args(args)
            .arg("-o")
            .arg(dir.path().join("o.exr"));
        cmd.assert()
    };
    run(&[
        "-m",
        "l1",
        "--preset",
        "published",
        "-p",
        "reweight_steps=3",
    ])
    .success();
    run(&["-m", "frgr", "-p", "guide=l1", "-p", "prefilter=false"]).success();
    run(&["-m", "auto", "-p", "l1.alpha=0.3", "-p", "frgr.levels=1"]).success();
    for (args, needle) in [
        (
            &["-m", "frgr", "-p", "alpha=0.3"][..],
            "unknown parameter 'alpha' for method 'frgr'",
        ),
        (
            &["-m", "frgr", "-p", "levels=9"][..],
            "levels is 9, expected an integer in [1, 4]",
        ),
        (
            &["-m", "frgr", "-p", "guide=oidn"][..],
            "expected one of rdfc, l1, none",
        ),
        (&["-m", "l1", "-p", "alpha"][..], "write NAME=VALUE"),
        (&["-m", "l2", "--preset", "published"][..], "unknown preset"),
    ] {
        let a = run(args).code(1);
        let err = String::from_utf8(a.get_output().stderr.clone()).unwrap();
        assert!(
            err.contains(needle) && err.lines().count() == 1,
            "{args:?}: {err}"
        );
    }
}

#[test]
fn max_memory_mb_refuses_in_one_line() {
    let dir = tempfile::tempdir().unwrap();
    let bundle = dir.path().join("d.exr");
    out(gdrecon()
        .args(["demo", "--width", "64", "--height", "40", "-o"])
        .arg(&bundle));
    let output = dir.path().join("o.exr");
    let a = gdrecon()
        .arg("reconstruct")
        .arg(&bundle)
        .args(["-m", "l1", "--max-memory-mb", "1", "-o"])
        .arg(&output)
        .assert()
        .code(1);
    let err = String::from_utf8(a.get_output().stderr.clone()).unwrap();
    assert!(
        err.starts_with("gdrecon: error: out of memory:")
            && err.contains("MiB")
            && err.contains("max_memory_mb = 1")
            && err.lines().count() == 1,
        "{err}"
    );
    assert!(!output.exists());
    // A limit the plan fits in runs.
    out(gdrecon()
        .arg("reconstruct")
        .arg(&bundle)
        .args(["-m", "l1", "--max-memory-mb", "64", "-o"])
        .arg(&output));
}
