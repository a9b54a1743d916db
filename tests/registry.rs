//! A method registered once reaches every interface: the `testing` feature registers `copy`
//! (`src/recon/copy.rs`, one line in `registry!`), and nothing else in the crate names it.
//! Here it is found, with its parameter and preset, in `gdrecon params`, `reconstruct`,
//! `bench` and the C API. Run with `cargo test --features testing --test registry`.
#![cfg(feature = "testing")]

use std::ffi::{CStr, CString};
use std::ptr::null_mut;

use assert_cmd::Command;
use gdrecon::capi::gdr_error::*;
use gdrecon::capi::*;
use gdrecon::recon::Value;
use gdrecon::{io, synth, Method, MethodConfig, Policy};

fn gdrecon() -> Command {
    Command::cargo_bin("gdrecon").unwrap()
}

fn stdout(cmd: &mut Command) -> String {
    String::from_utf8(cmd.assert().success().get_output().stdout.clone()).unwrap()
}

#[test]
fn the_registered_method_is_in_the_rust_api() {
    let copy: Method = "copy".parse().unwrap();
    assert!(Method::ALL.contains(&copy));
    let params = copy.params();
    assert_eq!(params.len(), 1);
    assert_eq!(
        (params[0].name.as_str(), params[0].default),
        ("gain", Value::Float(1.0))
    );
    let mut config = MethodConfig::preset(copy, "double").unwrap();
    assert_eq!(config.get("gain").unwrap(), Value::Float(2.0));
    config.set_text("gain", "3").unwrap();
    let e = config.set_text("gain", "101").unwrap_err().to_string();
    assert!(
        e.contains("gain is 101, expected a float in [0, 100]"),
        "{e}"
    );
    let frame = synth::synthetic_frame(16, 9, 4.0, 1);
    let (image, report) = gdrecon::recon::reconstruct(&frame, &config).unwrap();
    assert_eq!(report.method, "copy");
    for (o, b) in image.as_slice().iter().zip(frame.color().as_slice()) {
        assert_eq!(*o, 3.0 * b);
    }
}

#[test]
fn the_registered_method_is_in_the_cli() {
    let listing = stdout(gdrecon().args(["params", "copy"]));
    assert!(
        listing.contains("copy:") && listing.contains("gain") && listing.contains("preset double"),
        "{listing}"
    );
    let dir = tempfile::tempdir().unwrap();
    let bundle = dir.path().join("f.exr");
    let frame = synth::synthetic_frame(24, 16, 4.0, 2);
    io::write_bundle(&bundle, &frame).unwrap();
    let result = dir.path().join("out.exr");
    stdout(
        gdrecon()
            .arg("reconstruct")
            .arg(&bundle)
            .args([
                "--method", "copy", "--preset", "double", "-p", "gain=0.5", "-o",
            ])
            .arg(&result),
    );
    let read = io::read_bundle(&bundle, Policy::Replace).unwrap();
    let image = io::read_rgb(&result).unwrap();
    for (o, b) in image.as_slice().iter().zip(read.color().as_slice()) {
        assert_eq!(*o, 0.5 * b);
    }
    let bad = gdrecon()
        .arg("reconstruct")
        .arg(&bundle)
        .args(["--method", "copy", "-p", "alpha=1", "-o"])
        .arg(&result)
        .assert()
        .code(1);
    let err = String::from_utf8(bad.get_output().stderr.clone()).unwrap();
    assert!(
        err.contains("unknown parameter 'alpha' for method 'copy'") && err.contains("gain (float)"),
        "{err}"
    );
}

#[test]
fn the_registered_method_is_in_bench() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("t.csv");
    stdout(
        gdrecon()
            .args([
                "bench",
                "--synthetic",
                "32x24",
                "--methods",
                "copy",
                "--sweep",
            ])
            .args(["--runs", "1", "--warmup", "0", "--csv"])
            .arg(&csv),
    );
    let text = std::fs::read_to_string(&csv).unwrap();
    let variants: Vec<String> = text
        .lines()
        .skip(1)
        .map(|l| l.split(',').nth(1).unwrap().to_owned())
        .collect();
    assert_eq!(variants, ["copy", "copy:gain=0.5"], "{text}");
    let help = stdout(gdrecon().args(["bench", "--help"]));
    assert!(help.contains("copy: copy, copy:gain=0.5"), "{help}");
}

#[test]
fn the_registered_method_is_in_the_c_api() {
    let names: Vec<String> = (0..)
        .map(|i| gdr_method_name(i))
        .take_while(|p| !p.is_null())
        .map(|p| unsafe { CStr::from_ptr(p) }.to_str().unwrap().to_owned())
        .collect();
    assert!(names.contains(&"copy".to_owned()), "{names:?}");
    let method = CString::new("copy").unwrap();
    unsafe {
        let mut count = 0;
        assert_eq!(
            gdr_method_param_count(method.as_ptr(), &mut count),
            GDR_ERROR_NONE
        );
        assert_eq!(count, 3, "gain, spp, strict");
        let mut ctx = null_mut();
        assert_eq!(gdr_context_new(&mut ctx), GDR_ERROR_NONE);
        assert_eq!(gdr_context_commit(ctx), GDR_ERROR_NONE);
        let mut f = null_mut();
        assert_eq!(gdr_filter_new(ctx, method.as_ptr(), &mut f), GDR_ERROR_NONE);
        assert_eq!(
            gdr_filter_set_float(f, c"gain".as_ptr(), 4.0),
            GDR_ERROR_NONE
        );
        let mut gain = 0.0;
        assert_eq!(
            gdr_filter_get_float(f, c"gain".as_ptr(), &mut gain),
            GDR_ERROR_NONE
        );
        assert_eq!(gain, 4.0);
        let frame = synth::synthetic_frame(8, 4, 4.0, 3);
        let inputs: Vec<Vec<f32>> = [frame.color(), frame.dx(), frame.dy()]
            .iter()
            .map(|i| i.to_interleaved())
            .collect();
        for (name, data) in [c"color", c"dx", c"dy"].iter().zip(&inputs) {
            let s = gdr_filter_set_image(f, name.as_ptr(), data.as_ptr(), 8, 4, 3, 0, 0);
            assert_eq!(s, GDR_ERROR_NONE);
        }
        let mut out = vec![0f32; 8 * 4 * 3];
        let s = gdr_filter_set_image(f, c"output".as_ptr(), out.as_mut_ptr(), 8, 4, 3, 0, 0);
        assert_eq!(s, GDR_ERROR_NONE);
        assert_eq!(gdr_filter_commit(f), GDR_ERROR_NONE);
        assert_eq!(gdr_filter_execute(f), GDR_ERROR_NONE);
        for (o, b) in out.iter().zip(&inputs[0]) {
            assert_eq!(*o, 4.0 * b);
        }
        gdr_filter_release(&mut f);
        gdr_context_release(&mut ctx);
    }
}
