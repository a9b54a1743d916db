//! `gdrecon bench --sweep --out-dir`: the report files on a tiny synthetic frame.

mod common;

use std::path::Path;

use assert_cmd::Command;

/// The CLI under test.
fn gdrecon() -> Command {
    Command::cargo_bin("gdrecon").unwrap()
}

#[test]
fn sweep_writes_every_report_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("report");
    bench(
        ["--synthetic", "48x32", "--methods", "l2,l1", "--sweep"],
        &out,
    );
    for file in [
        "results.csv",
        "results.json",
        "summary.md",
        "pareto.png",
        "pareto.svg",
    ] {
        let meta = std::fs::metadata(out.join(file)).unwrap_or_else(|e| panic!("{file}: {e}"));
        assert!(meta.len() > 0, "{file} is empty");
    }
    let csv = std::fs::read_to_string(out.join("results.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(
        lines.next().unwrap(),
        "scene,spp,method,setting,scale,width,height,pixels,threads,runs,median_s,min_s,max_s,\
         rel_mse,peak_rss_mib,stages,oidn_s"
    );
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    let variants: Vec<(&str, &str)> = rows.iter().map(|r| (r[2], r[3])).collect();
    // The prior variants are swept when OIDN can be loaded (cargo feature `oidn`).
    let prior = cfg!(feature = "oidn");
    let expected: Vec<(&str, &str)> = [
        ("l2", "default", true),
        ("l2", "data=prior", prior),
        ("l1", "default", true),
        ("l1", "step_change=0", true),
        ("l1", "fast", true),
        ("l1", "reweight_steps=5", true),
        ("l1", "published", true),
        ("l1", "prior", prior),
    ]
    .into_iter()
    .filter(|v| v.2)
    .map(|(m, s, _)| (m, s))
    .collect();
    assert_eq!(variants, expected);
    for r in &rows {
        assert_eq!(r.len(), 17, "{r:?}");
        assert_eq!(r[16], "", "OIDN was not timed alongside: {r:?}");
        // Stage medians: l2 times its right-hand side and its DCT solve.
        if r[2] == "l2" && r[3] == "default" {
            assert!(
                r[15].starts_with("rhs=") && r[15].contains(";dct solve="),
                "{r:?}"
            );
        }
        assert_eq!((r[0], r[1], r[5], r[6]), ("synthetic", "16", "48", "32"));
        let rel: f64 = r[13].parse().unwrap();
        assert!(rel > 0.0 && rel < 1.0, "{r:?}");
    }
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(summary.contains("## 16 spp"), "{summary}");
    assert!(summary.contains("**yes**"), "{summary}");
    let png = std::fs::read(out.join("pareto.png")).unwrap();
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    let svg = std::fs::read_to_string(out.join("pareto.svg")).unwrap();
    assert!(svg.contains("<svg") && svg.contains("l1:published"));
}

/// `gdrecon bench ARGS --runs 1 --warmup 0 --out-dir OUT`, which must succeed; returns what it
/// printed.
fn bench<I: AsRef<std::ffi::OsStr>>(args: impl IntoIterator<Item = I>, out: &Path) -> String {
    let output = gdrecon()
        .arg("bench")
        .args(args)
        .args(["--runs", "1", "--warmup", "0", "--out-dir"])
        .arg(out)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

#[test]
fn unknown_variant_is_named_in_the_error() {
    let output = gdrecon()
        .args(["bench", "--synthetic", "8x8", "--settings", "l2,l1:fastest"])
        .output()
        .unwrap();
    assert_eq!(output.status.code(), Some(1));
    let err = String::from_utf8_lossy(&output.stderr);
    assert!(
        err.contains("variant 'l1:fastest'")
            && err.contains("unknown preset 'fastest'")
            && err.contains("published"),
        "{err}"
    );
}

/// `--baselines`: the base image and the OIDN images found beside the bundle become rows with
/// their own relMSE, in italics in the summary, with the worst frame named, and never Pareto.
#[test]
fn baselines_are_read_beside_the_bundles() {
    let dir = tempfile::tempdir().unwrap();
    let sample = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/data/sample.exr");
    let bundle = dir.path().join("cornell_16spp.exr");
    std::fs::copy(&sample, &bundle).unwrap();
    let frame = gdrecon::io::read_bundle(&bundle, gdrecon::Policy::Replace).unwrap();
    // Stand-ins for OIDN's outputs: the reference itself (error 0 would not be positive, so a
    // slightly scaled one) and the base image.
    let reference = frame.reference().unwrap().clone();
    let near = gdrecon::Image::from_fn(3, frame.width(), frame.height(), |(c, x, y)| {
        reference.at(c, x, y) * 1.01
    });
    std::fs::create_dir_all(dir.path().join("oidn")).unwrap();
    std::fs::create_dir_all(dir.path().join("oidn-equal-time")).unwrap();
    gdrecon::io::exr::write_rgb(dir.path().join("oidn/cornell_16spp.exr"), &near).unwrap();
    gdrecon::io::exr::write_rgb(
        dir.path().join("oidn-equal-time/cornell_16spp.exr"),
        frame.color(),
    )
    .unwrap();
    std::fs::write(
        dir.path().join("oidn/timings.json"),
        "{\"cornell_16spp\": 0.5}",
    )
    .unwrap();
    let out = dir.path().join("report");
    let console = bench(
        [bundle.to_str().unwrap(), "--methods", "l2", "--baselines"],
        &out,
    );
    let csv = std::fs::read_to_string(out.join("results.csv")).unwrap();
    let rel = |setting: &str| -> f64 {
        let line = csv
            .lines()
            .find(|l| l.split(',').nth(3) == Some(setting))
            .unwrap_or_else(|| panic!("no {setting} row in\n{csv}\n{console}"));
        line.split(',').nth(13).unwrap().parse().unwrap()
    };
    let base = rel("base");
    assert!(
        (rel("oidn:equal-time") - base).abs() <= 1e-12 * base,
        "{csv}"
    );
    assert!(rel("oidn") < 1e-2 * base && rel("default") < base, "{csv}");
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(
        summary.contains("| _oidn_ |") && summary.contains("(cornell_16spp.exr)"),
        "{summary}"
    );
    let oidn_line = summary
        .lines()
        .find(|l| l.starts_with("| _oidn_ |"))
        .unwrap();
    assert!(
        oidn_line.contains("| 0.500 |") && !oidn_line.contains("**yes**"),
        "{oidn_line}"
    );
}

/// `--against-oidn` times OIDN (the `prior` variant) first, in the same run, and every
/// variant's time becomes a multiple of it, in the summary and on the console.
#[cfg(feature = "oidn")]
#[test]
fn against_oidn_reports_every_time_as_a_multiple_of_oidn() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("report");
    let console = bench(
        [
            "--synthetic",
            "64x48",
            "--methods",
            "l2,l1",
            "--against-oidn",
        ],
        &out,
    );
    let csv = std::fs::read_to_string(out.join("results.csv")).unwrap();
    let methods: Vec<&str> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').nth(2).unwrap())
        .collect();
    assert_eq!(methods, ["prior", "l2", "l1"], "OIDN is timed first");
    // Then once before each run of every other variant: its median is on that variant's row,
    // and the ratio divides by it.
    let rows: Vec<Vec<&str>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').collect())
        .collect();
    assert_eq!(rows[0][16], "", "OIDN's own row");
    for r in &rows[1..] {
        let oidn: f64 = r[16].parse().unwrap_or_else(|_| panic!("no oidn_s: {r:?}"));
        assert!(oidn > 0.0, "{r:?}");
    }
    assert!(
        console.contains("time against OIDN in this run"),
        "{console}"
    );
    let ratio = |v: &str| -> f64 {
        let line = console
            .lines()
            .find(|l| l.starts_with(v) && l.ends_with("x OIDN"))
            .unwrap_or_else(|| panic!("no ratio for {v}:\n{console}"));
        line.split_whitespace()
            .nth(1)
            .unwrap()
            .trim_end_matches('x')
            .parse()
            .unwrap()
    };
    assert_eq!(ratio("prior"), 1.0);
    let l1 = &rows[2];
    let expected = l1[10].parse::<f64>().unwrap() / l1[16].parse::<f64>().unwrap();
    assert!(
        (ratio("l1") - expected).abs() <= 5e-4 + 1e-3 * expected,
        "{expected}"
    );
    assert!(ratio("l2") > 0.0 && ratio("l2") < ratio("l1"));
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(summary.contains("| x OIDN (this run) |"), "{summary}");
    assert!(summary.contains("| `prior` |"), "{summary}");
}

/// A bundle that brings its own prior: OIDN's time is still OIDN's (its runs see the frame
/// without the layer, which the `prior` method would return as is). The layer here is the
/// reference itself, so OIDN's row has relMSE 0 exactly when OIDN did not run.
#[cfg(feature = "oidn")]
#[test]
fn against_oidn_times_oidn_on_a_bundle_with_a_prior() {
    let dir = tempfile::tempdir().unwrap();
    let frame = gdrecon::synth::synthetic_frame(64, 48, 16.0, 3);
    let reference = frame.reference().unwrap().clone();
    let frame = common::with_prior(frame, reference);
    let bundle = dir.path().join("synth_16spp.exr");
    gdrecon::io::write_bundle(&bundle, &frame).unwrap();
    let out = dir.path().join("report");
    let console = bench(
        [
            bundle.to_str().unwrap(),
            "--methods",
            "l2",
            "--against-oidn",
        ],
        &out,
    );
    assert!(console.contains("without its 'prior' layer"), "{console}");
    let csv = std::fs::read_to_string(out.join("results.csv")).unwrap();
    let oidn: Vec<&str> = csv.lines().nth(1).unwrap().split(',').collect();
    assert_eq!(oidn[2], "prior", "{csv}");
    let rel_mse: f64 = oidn[13].parse().unwrap();
    assert!(rel_mse > 1e-6, "OIDN's row is the given layer: {csv}");
}

/// `--scales` adds the scaling table (seconds per size, the exponent) and its plot.
#[test]
fn scales_write_the_scaling_table_and_plot() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("report");
    bench(
        [
            "--synthetic",
            "64x48",
            "--methods",
            "l2",
            "--scales",
            "0.5,1,2",
        ],
        &out,
    );
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    let row = summary
        .lines()
        .find(|l| l.starts_with("| `l2` | synthetic"))
        .unwrap_or_else(|| panic!("no scaling row:\n{summary}"));
    for size in ["32 x 24", "64 x 48", "128 x 96"] {
        assert!(row.contains(size), "{row}");
    }
    let png = std::fs::read(out.join("scaling.png")).unwrap();
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    let svg = std::fs::read_to_string(out.join("scaling.svg")).unwrap();
    assert!(svg.contains("<svg") && svg.contains("pixels per frame"));
}
