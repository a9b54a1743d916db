//! The C ABI tested from Rust through the exported functions themselves (as rav1e does):
//! results equal the Rust API's bit for bit, strided layouts equal packed ones, every error
//! case has its code, panics and cancellation come back as statuses.
//!
//! `write_reference_for_c` (ignored) writes the inputs and Rust-API outputs that the C tests in
//! `tests/c/` compare with: `GDR_CAPI_REF_DIR=dir cargo test --test capi -- --ignored`.

mod common;

use std::ffi::{c_char, c_void, CStr, CString};
use std::ptr::{null, null_mut};
use std::time::{Duration, Instant};

use gdrecon::capi::gdr_error::*;
use gdrecon::capi::*;
use gdrecon::{
    synth, Context, ContextOptions, Frame, Image, Layer, Method, MethodConfig, Plan, Progress,
};

const W: usize = 97;
const H: usize = 61;
const INPUTS: [Layer; 7] = [
    Layer::Color,
    Layer::Dx,
    Layer::Dy,
    Layer::Variance,
    Layer::Albedo,
    Layer::Normal,
    Layer::Depth,
];

fn frame() -> Frame {
    synth::synthetic_frame(W, H, 8.0, 7)
}

fn last_error() -> (gdr_error, String) {
    let mut msg: *const c_char = null();
    let code = unsafe { gdr_get_error(&mut msg) };
    let text = unsafe { CStr::from_ptr(msg) }
        .to_string_lossy()
        .into_owned();
    (code, text)
}

#[track_caller]
fn ok(code: gdr_error) {
    if code != GDR_ERROR_NONE {
        panic!("status {code:?}: {}", last_error().1);
    }
}

/// Asserts a status and returns the thread's message for it.
#[track_caller]
fn fails(code: gdr_error, expected: gdr_error) -> String {
    assert_eq!(code, expected, "message: {}", last_error().1);
    let (c, m) = last_error();
    assert_eq!(c, expected);
    assert_eq!(
        last_error().0,
        GDR_ERROR_NONE,
        "gdr_get_error clears the error"
    );
    m
}

fn cs(s: &str) -> CString {
    CString::new(s).unwrap()
}

fn context() -> *mut gdr_context {
    let mut ctx = null_mut();
    unsafe {
        ok(gdr_context_new(&mut ctx));
        ok(gdr_context_set_int(ctx, cs("threads").as_ptr(), 2));
        ok(gdr_context_commit(ctx));
    }
    ctx
}

fn filter(ctx: *mut gdr_context, method: &str) -> *mut gdr_filter {
    let mut f = null_mut();
    unsafe { ok(gdr_filter_new(ctx, cs(method).as_ptr(), &mut f)) };
    f
}

/// The Rust API's output for `config`, interleaved RGB.
fn rust_output(frame: &Frame, config: &MethodConfig) -> Vec<f32> {
    let ctx = Context::new(ContextOptions::with_threads(Some(2))).unwrap();
    let mut plan = Plan::new(&ctx, config, frame.width(), frame.height()).unwrap();
    let (image, _) = plan.execute(frame, &Progress::none()).unwrap();
    image.to_interleaved()
}

fn interleaved(frame: &Frame, layer: Layer) -> Vec<f32> {
    frame.layer(layer).unwrap().to_interleaved()
}

/// Sets every input layer packed-interleaved from `bufs` (kept alive by the caller).
unsafe fn set_packed(f: *mut gdr_filter, bufs: &[(Layer, Vec<f32>)]) {
    for (layer, buf) in bufs {
        let name = cs(layer.name());
        ok(gdr_filter_set_image(
            f,
            name.as_ptr(),
            buf.as_ptr(),
            W,
            H,
            layer.channels(),
            0,
            0,
        ));
    }
}

fn packed_inputs(frame: &Frame) -> Vec<(Layer, Vec<f32>)> {
    INPUTS.iter().map(|&l| (l, interleaved(frame, l))).collect()
}

unsafe fn run(f: *mut gdr_filter, out: &mut [f32]) {
    ok(gdr_filter_set_image(
        f,
        c"output".as_ptr(),
        out.as_mut_ptr(),
        W,
        H,
        3,
        0,
        0,
    ));
    ok(gdr_filter_commit(f));
    ok(gdr_filter_execute(f));
}

fn same_bits(a: &[f32], b: &[f32]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
}

#[test]
fn packed_results_equal_the_rust_api_bit_for_bit() {
    let frame = frame();
    let bufs = packed_inputs(&frame);
    let ctx = context();
    for method in Method::ALL.into_iter().filter(|m| m.is_built()) {
        let expected = rust_output(&frame, &MethodConfig::default_for(method));
        let mut f = filter(ctx, method.name());
        let mut out = vec![0f32; W * H * 3];
        unsafe {
            ok(gdr_filter_set_float(
                f,
                c"spp".as_ptr(),
                frame.spp().unwrap(),
            ));
            set_packed(f, &bufs);
            run(f, &mut out);
            assert!(same_bits(&out, &expected), "method {method}");
            // Executing again gives the same result.
            out.fill(-1.0);
            ok(gdr_filter_execute(f));
            assert!(same_bits(&out, &expected), "method {method}, second run");
            let mut report = null();
            ok(gdr_filter_get_report(f, &mut report));
            assert!(CStr::from_ptr(report)
                .to_str()
                .unwrap()
                .contains(method.name()));
            ok(gdr_filter_release(&mut f));
        }
        assert!(f.is_null());
    }
    unsafe { ok(gdr_context_release(&mut { ctx })) };
}

#[test]
fn parameters_reach_the_method() {
    let frame = frame();
    let bufs = packed_inputs(&frame);
    let ctx = context();
    let mut config = gdrecon::recon::PoissonL1Config::default();
    config.alpha = 0.5;
    config.reweight_steps = 6;
    config.cg_iterations = 5;
    config.preconditioned = false;
    let expected = rust_output(&frame, &MethodConfig::PoissonL1(config));
    let f = filter(ctx, "l1");
    let mut out = vec![0f32; W * H * 3];
    unsafe {
        ok(gdr_filter_set_float(f, c"alpha".as_ptr(), 0.5));
        ok(gdr_filter_set_int(f, c"reweight_steps".as_ptr(), 6));
        ok(gdr_filter_set_int(f, c"cg_iterations".as_ptr(), 5));
        ok(gdr_filter_set_bool(f, c"preconditioned".as_ptr(), false));
        let (mut a, mut n, mut b) = (0f32, 0i32, true);
        ok(gdr_filter_get_float(f, c"alpha".as_ptr(), &mut a));
        ok(gdr_filter_get_int(f, c"cg_iterations".as_ptr(), &mut n));
        ok(gdr_filter_get_bool(f, c"preconditioned".as_ptr(), &mut b));
        assert_eq!((a, n, b), (0.5, 5, false));
        set_packed(f, &bufs);
        run(f, &mut out);
        gdr_filter_release(&mut { f });
        gdr_context_release(&mut { ctx });
    }
    assert!(same_bits(&out, &expected));
}

/// `frgr` without `spp` is refused at commit, in the C API's words, not at execute.
#[test]
fn frgr_without_spp_fails_at_commit() {
    let frame = frame();
    let bufs = packed_inputs(&frame);
    let ctx = context();
    let f = filter(ctx, "frgr");
    let mut out = vec![0f32; W * H * 3];
    unsafe {
        set_packed(f, &bufs);
        ok(gdr_filter_set_image(
            f,
            c"output".as_ptr(),
            out.as_mut_ptr(),
            W,
            H,
            3,
            0,
            0,
        ));
        let msg = fails(gdr_filter_commit(f), GDR_ERROR_INVALID_OPERATION);
        assert!(
            msg.contains("\"spp\"")
                && msg.contains("gdr_filter_set_float")
                && !msg.contains("--spp"),
            "{msg}"
        );
        ok(gdr_filter_set_float(f, c"spp".as_ptr(), 4.0));
        ok(gdr_filter_commit(f));
        ok(gdr_filter_execute(f));
        ok(gdr_filter_release(&mut { f }));
        ok(gdr_context_release(&mut { ctx }));
    }
}

#[test]
fn filter_parameters_reach_the_method() {
    // The ablation settings through the C API equal the Rust API's, and a bad guide is named.
    let frame = frame();
    let bufs = packed_inputs(&frame);
    let ctx = context();
    let mut config = gdrecon::recon::FrgrConfig::default();
    config.radius = 4;
    config.levels = 1;
    config.enhance_iterations = 0;
    config.guide = gdrecon::recon::FrgrGuide::Colour;
    config.prefilter = true;
    let expected = rust_output(&frame, &MethodConfig::Frgr(config));
    let f = filter(ctx, "frgr");
    let mut out = vec![0f32; W * H * 3];
    unsafe {
        ok(gdr_filter_set_float(
            f,
            c"spp".as_ptr(),
            frame.spp().unwrap(),
        ));
        ok(gdr_filter_set_int(f, c"radius".as_ptr(), 4));
        ok(gdr_filter_set_int(f, c"levels".as_ptr(), 1));
        ok(gdr_filter_set_int(f, c"enhance_iterations".as_ptr(), 0));
        let msg = fails(
            gdr_filter_set_int(f, c"guide".as_ptr(), 7),
            GDR_ERROR_INVALID_ARGUMENT,
        );
        assert!(
            msg.contains("one of rdfc, l1, none, prior") && msg.contains("index, 0 to 3"),
            "{msg}"
        );
        ok(gdr_filter_set_int(
            f,
            c"guide".as_ptr(),
            GDR_FRGR_GUIDE_NONE,
        ));
        let (mut r, mut l, mut e, mut g) = (0i32, 0i32, -1i32, 0i32);
        ok(gdr_filter_get_int(f, c"radius".as_ptr(), &mut r));
        ok(gdr_filter_get_int(f, c"levels".as_ptr(), &mut l));
        ok(gdr_filter_get_int(
            f,
            c"enhance_iterations".as_ptr(),
            &mut e,
        ));
        ok(gdr_filter_get_int(f, c"guide".as_ptr(), &mut g));
        assert_eq!((r, l, e, g), (4, 1, 0, GDR_FRGR_GUIDE_NONE));
        set_packed(f, &bufs);
        run(f, &mut out);
        gdr_filter_release(&mut { f });
        gdr_context_release(&mut { ctx });
    }
    assert!(same_bits(&out, &expected));
}

#[test]
fn strided_planar_and_in_place_layouts_equal_packed() {
    let frame = frame();
    let expected = rust_output(&frame, &MethodConfig::default_for(Method::PoissonL2));
    let ctx = context();
    let f = filter(ctx, "l2");
    unsafe {
        // RGBA with padded rows (row stride 97 * 16 + 32 bytes), output in place over color.
        let row = W * 4 + 8;
        let mut rgba: Vec<Vec<f32>> = Vec::new();
        for &l in &INPUTS[..3] {
            let src = interleaved(&frame, l);
            let mut buf = vec![f32::NAN; row * H];
            for y in 0..H {
                for x in 0..W {
                    for c in 0..3 {
                        buf[y * row + x * 4 + c] = src[(y * W + x) * 3 + c];
                    }
                }
            }
            rgba.push(buf);
        }
        for (l, buf) in INPUTS[..3].iter().zip(&mut rgba) {
            let name = cs(l.name());
            ok(gdr_filter_set_image(
                f,
                name.as_ptr(),
                buf.as_mut_ptr(),
                W,
                H,
                3,
                16,
                row * 4,
            ));
        }
        let in_place = rgba[0].as_mut_ptr();
        ok(gdr_filter_set_image(
            f,
            c"color".as_ptr(),
            in_place,
            W,
            H,
            3,
            16,
            row * 4,
        ));
        ok(gdr_filter_set_image(
            f,
            c"output".as_ptr(),
            in_place,
            W,
            H,
            3,
            16,
            row * 4,
        ));
        ok(gdr_filter_commit(f));
        ok(gdr_filter_execute(f));
        let mut got = Vec::with_capacity(W * H * 3);
        for y in 0..H {
            for x in 0..W {
                got.extend_from_slice(&rgba[0][y * row + x * 4..y * row + x * 4 + 3]);
                assert!(rgba[0][y * row + x * 4 + 3].is_nan(), "alpha untouched");
            }
        }
        assert!(same_bits(&got, &expected), "RGBA, padded rows, in place");

        // Planar, packed.
        let planes: Vec<Vec<f32>> = INPUTS[..3]
            .iter()
            .map(|&l| frame.layer(l).unwrap().as_slice().to_vec())
            .collect();
        for (l, buf) in INPUTS[..3].iter().zip(&planes) {
            let name = cs(l.name());
            ok(gdr_filter_set_image_planar(
                f,
                name.as_ptr(),
                buf.as_ptr(),
                W,
                H,
                3,
                0,
                0,
            ));
        }
        let mut out = vec![0f32; 3 * W * H];
        ok(gdr_filter_set_image_planar(
            f,
            c"output".as_ptr(),
            out.as_mut_ptr(),
            W,
            H,
            3,
            0,
            0,
        ));
        ok(gdr_filter_commit(f));
        ok(gdr_filter_execute(f));
        let img =
            gdrecon::Image::from_planes(ndarray::Array3::from_shape_vec((3, H, W), out).unwrap());
        assert!(same_bits(&img.to_interleaved(), &expected), "planar");

        // All passes interleaved in one buffer (9 floats per pixel: color, dx, dy), output in
        // a 4th slot of a 12-float pixel: views interleave without sharing elements.
        let stride = 12;
        let mut big = vec![0f32; W * H * stride];
        for (i, &l) in INPUTS[..3].iter().enumerate() {
            let src = interleaved(&frame, l);
            for p in 0..W * H {
                big[p * stride + 3 * i..p * stride + 3 * i + 3]
                    .copy_from_slice(&src[p * 3..p * 3 + 3]);
            }
        }
        let base = big.as_mut_ptr();
        for (i, &l) in INPUTS[..3].iter().enumerate() {
            let name = cs(l.name());
            ok(gdr_filter_set_image(
                f,
                name.as_ptr(),
                base.add(3 * i),
                W,
                H,
                3,
                48,
                0,
            ));
        }
        ok(gdr_filter_set_image(
            f,
            c"output".as_ptr(),
            base.add(9),
            W,
            H,
            3,
            48,
            0,
        ));
        ok(gdr_filter_commit(f));
        ok(gdr_filter_execute(f));
        let got: Vec<f32> = (0..W * H)
            .flat_map(|p| big[p * stride + 9..p * stride + 12].to_vec())
            .collect();
        assert!(same_bits(&got, &expected), "one interleaved render buffer");
        gdr_filter_release(&mut { f });
        gdr_context_release(&mut { ctx });
    }
}

#[test]
fn every_error_has_its_code_and_message() {
    let frame = frame();
    let bufs = packed_inputs(&frame);
    let ctx = context();
    let mut out = vec![0f32; W * H * 3];
    unsafe {
        // Null pointers.
        fails(gdr_context_new(null_mut()), GDR_ERROR_NULL_POINTER);
        fails(gdr_context_commit(null_mut()), GDR_ERROR_NULL_POINTER);
        fails(gdr_filter_commit(null_mut()), GDR_ERROR_NULL_POINTER);
        fails(gdr_filter_execute(null_mut()), GDR_ERROR_NULL_POINTER);
        fails(gdr_filter_release(null_mut()), GDR_ERROR_NULL_POINTER);
        let mut none: *mut gdr_filter = null_mut();
        ok(gdr_filter_release(&mut none));
        let mut f: *mut gdr_filter = std::ptr::dangling_mut();
        let m = fails(gdr_filter_new(ctx, null(), &mut f), GDR_ERROR_NULL_POINTER);
        assert!(f.is_null() && m.contains("method"), "{m}");

        // Unknown method, lists the valid ones.
        let m = fails(
            gdr_filter_new(ctx, c"gradnot".as_ptr(), &mut f),
            GDR_ERROR_INVALID_ARGUMENT,
        );
        assert!(m.contains("l2") && m.contains("l1"), "{m}");

        // A filter needs a committed context; a committed context is frozen.
        let mut raw = null_mut();
        ok(gdr_context_new(&mut raw));
        fails(
            gdr_filter_new(raw, c"l2".as_ptr(), &mut f),
            GDR_ERROR_INVALID_OPERATION,
        );
        fails(
            gdr_context_set_int(raw, c"threads".as_ptr(), -1),
            GDR_ERROR_INVALID_ARGUMENT,
        );
        fails(
            gdr_context_set_int(raw, c"thread".as_ptr(), 1),
            GDR_ERROR_INVALID_ARGUMENT,
        );
        ok(gdr_context_commit(raw));
        fails(gdr_context_commit(raw), GDR_ERROR_INVALID_OPERATION);
        fails(
            gdr_context_set_int(raw, c"threads".as_ptr(), 1),
            GDR_ERROR_INVALID_OPERATION,
        );
        ok(gdr_context_set_int(raw, c"log_level".as_ptr(), 0));
        ok(gdr_context_release(&mut raw));
        assert!(raw.is_null());

        let f = filter(ctx, "l1");
        // Unknown parameter (lists valid names), wrong type, out of range.
        let m = fails(
            gdr_filter_set_float(f, c"alfa".as_ptr(), 0.1),
            GDR_ERROR_INVALID_ARGUMENT,
        );
        assert!(m.contains("alpha") && m.contains("reweight_steps"), "{m}");
        let m = fails(
            gdr_filter_set_int(f, c"alpha".as_ptr(), 1),
            GDR_ERROR_INVALID_ARGUMENT,
        );
        assert!(m.contains("gdr_filter_set_float"), "{m}");
        fails(
            gdr_filter_set_int(f, c"cg_iterations".as_ptr(), -3),
            GDR_ERROR_INVALID_ARGUMENT,
        );
        fails(
            gdr_filter_set_float(f, c"spp".as_ptr(), f32::NAN),
            GDR_ERROR_INVALID_ARGUMENT,
        );

        // Wrong order: execute before commit; commit without required images.
        fails(gdr_filter_execute(f), GDR_ERROR_INVALID_OPERATION);
        let m = fails(gdr_filter_commit(f), GDR_ERROR_INVALID_OPERATION);
        assert!(m.contains("'color'"), "{m}");

        // Image views: unknown name, NULL, wrong channels, misaligned, bad strides, sizes.
        let p = bufs[0].1.as_ptr();
        fails(
            gdr_filter_set_image(f, c"colour".as_ptr(), p, W, H, 3, 0, 0),
            GDR_ERROR_INVALID_ARGUMENT,
        );
        let m = fails(
            gdr_filter_set_image(f, c"color".as_ptr(), null(), W, H, 3, 0, 0),
            GDR_ERROR_NULL_POINTER,
        );
        assert!(m.contains("'color'"), "{m}");
        let m = fails(
            gdr_filter_set_image(f, c"color".as_ptr(), p, W, H, 4, 0, 0),
            GDR_ERROR_INVALID_IMAGE,
        );
        assert!(m.contains("'color'") && m.contains("RGBA"), "{m}");
        fails(
            gdr_filter_set_image(f, c"depth".as_ptr(), p, W, H, 3, 0, 0),
            GDR_ERROR_INVALID_IMAGE,
        );
        fails(
            gdr_filter_set_image(
                f,
                c"color".as_ptr(),
                p.cast::<u8>().add(2).cast(),
                W,
                H,
                3,
                0,
                0,
            ),
            GDR_ERROR_INVALID_IMAGE,
        );
        fails(
            gdr_filter_set_image(f, c"color".as_ptr(), p, W, H, 3, 14, 0),
            GDR_ERROR_INVALID_IMAGE,
        );
        let m = fails(
            gdr_filter_set_image(f, c"color".as_ptr(), p, W, H, 3, 8, 0),
            GDR_ERROR_INVALID_IMAGE,
        );
        assert!(m.contains("overlap"), "{m}");
        fails(
            gdr_filter_set_image(f, c"color".as_ptr(), p, W, H, 3, 12, 12 * (W - 1)),
            GDR_ERROR_INVALID_IMAGE,
        );
        fails(
            gdr_filter_set_image(f, c"color".as_ptr(), p, 0, H, 3, 0, 0),
            GDR_ERROR_INVALID_IMAGE,
        );
        fails(
            gdr_filter_set_image(f, c"color".as_ptr(), p, usize::MAX / 8, H, 3, 0, 0),
            GDR_ERROR_INVALID_IMAGE,
        );
        set_packed(f, &bufs);
        ok(gdr_filter_set_image(
            f,
            c"output".as_ptr(),
            out.as_mut_ptr(),
            W - 1,
            H,
            3,
            0,
            0,
        ));
        let m = fails(gdr_filter_commit(f), GDR_ERROR_INVALID_IMAGE);
        assert!(
            m.contains("'output'") && m.contains(&format!("{W} x {H}")),
            "{m}"
        );

        // Output overlapping an input partially (shifted by one pixel) is an error; exactly
        // the same view (in place) is fine.
        let mut dx_buf = bufs[1].1.clone();
        let dx = dx_buf.as_mut_ptr();
        ok(gdr_filter_set_image(
            f,
            c"output".as_ptr(),
            dx.add(3),
            W,
            H - 1,
            3,
            0,
            0,
        ));
        ok(gdr_filter_set_image(
            f,
            c"dx".as_ptr(),
            dx,
            W,
            H - 1,
            3,
            0,
            0,
        ));
        ok(gdr_filter_set_image(
            f,
            c"color".as_ptr(),
            bufs[0].1.as_ptr(),
            W,
            H - 1,
            3,
            0,
            0,
        ));
        ok(gdr_filter_set_image(
            f,
            c"dy".as_ptr(),
            bufs[2].1.as_ptr(),
            W,
            H - 1,
            3,
            0,
            0,
        ));
        for l in &INPUTS[3..] {
            ok(gdr_filter_unset_image(f, cs(l.name()).as_ptr()));
        }
        let m = fails(gdr_filter_commit(f), GDR_ERROR_OVERLAP);
        assert!(m.contains("'dx'"), "{m}");
        ok(gdr_filter_set_image(
            f,
            c"output".as_ptr(),
            dx,
            W,
            H - 1,
            3,
            0,
            0,
        ));
        ok(gdr_filter_commit(f));

        // Parameters out of range are refused when set, with the table's range; the filter
        // keeps its value.
        let m = fails(
            gdr_filter_set_float(f, c"alpha".as_ptr(), -1.0),
            GDR_ERROR_INVALID_ARGUMENT,
        );
        assert!(
            m.contains("alpha is -1, expected a float in (0, 10000]"),
            "{m}"
        );
        let mut alpha = 0.0;
        ok(gdr_filter_get_float(f, c"alpha".as_ptr(), &mut alpha));
        assert_eq!(alpha, 0.2);
        ok(gdr_filter_set_float(f, c"alpha".as_ptr(), 0.2));

        // Strict mode refuses NaN (default: replaced and counted).
        set_packed(f, &bufs);
        let mut color = bufs[0].1.clone();
        color[5] = f32::NAN;
        ok(gdr_filter_set_image(
            f,
            c"color".as_ptr(),
            color.as_ptr(),
            W,
            H,
            3,
            0,
            0,
        ));
        ok(gdr_filter_set_image(
            f,
            c"output".as_ptr(),
            out.as_mut_ptr(),
            W,
            H,
            3,
            0,
            0,
        ));
        ok(gdr_filter_commit(f));
        ok(gdr_filter_execute(f));
        assert!(out.iter().all(|v| v.is_finite()));
        ok(gdr_filter_set_bool(f, c"strict".as_ptr(), true));
        ok(gdr_filter_commit(f));
        let m = fails(gdr_filter_execute(f), GDR_ERROR_INVALID_INPUT);
        assert!(m.contains("color"), "{m}");

        // Files.
        let mut fr = null_mut();
        fails(
            gdr_frame_read(c"/nonexistent/frame.exr".as_ptr(), &mut fr),
            GDR_ERROR_IO,
        );
        assert!(fr.is_null());
        gdr_filter_release(&mut { f });
        gdr_context_release(&mut { ctx });
    }
    assert!(last_error().0 == GDR_ERROR_NONE);
    assert_eq!(
        unsafe { CStr::from_ptr(gdr_error_name(GDR_ERROR_OVERLAP as u32)) },
        c"GDR_ERROR_OVERLAP"
    );
}

#[test]
#[cfg(feature = "testing")]
fn a_panic_becomes_a_status_and_the_filter_stays_usable() {
    let frame = frame();
    let bufs = packed_inputs(&frame);
    let ctx = context();
    let f = filter(ctx, "l2");
    let mut out = vec![0f32; W * H * 3];
    unsafe {
        let m = fails(
            gdr_filter_set_bool(f, c"internal_test_panic".as_ptr(), true),
            GDR_ERROR_UNKNOWN,
        );
        assert!(m.contains("panic"), "{m}");
        set_packed(f, &bufs);
        run(f, &mut out);
        gdr_filter_release(&mut { f });
        gdr_context_release(&mut { ctx });
    }
    let expected = rust_output(&frame, &MethodConfig::default_for(Method::PoissonL2));
    assert!(same_bits(&out, &expected));
}

/// The panic hook the first `gdr_context_new` installs keeps the library's panics (on the
/// calling thread and on pool threads) off stderr and hands every other panic to the hook
/// installed before it. Run in a child process of this test binary: hooks are process-wide.
#[test]
#[cfg(feature = "testing")]
fn library_panics_are_silent_and_the_host_hook_still_runs() {
    const NAME: &str = "library_panics_are_silent_and_the_host_hook_still_runs";
    if std::env::var_os("GDR_TEST_HOOK_CHILD").is_some() {
        return hook_child();
    }
    let out = std::process::Command::new(std::env::current_exe().unwrap())
        .args(["--exact", NAME, "--nocapture", "--test-threads=1"])
        .env("GDR_TEST_HOOK_CHILD", "1")
        .output()
        .unwrap();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(stdout.contains("host hook: 1 call"), "{stdout}");
    assert!(!stderr.contains("panicked"), "{stderr}");
}

#[cfg(feature = "testing")]
fn hook_child() {
    use std::sync::atomic::{AtomicUsize, Ordering};
    static CALLS: AtomicUsize = AtomicUsize::new(0);
    std::panic::set_hook(Box::new(|_| {
        CALLS.fetch_add(1, Ordering::SeqCst);
    }));
    let ctx = context(); // installs gdrecon's hook in front of the one above
    let f = filter(ctx, "l2");
    for name in [c"internal_test_panic", c"internal_test_panic_in_pool"] {
        let m = fails(
            unsafe { gdr_filter_set_bool(f, name.as_ptr(), true) },
            GDR_ERROR_UNKNOWN,
        );
        assert!(m.contains("deliberate panic"), "{m}");
    }
    assert_eq!(
        CALLS.load(Ordering::SeqCst),
        0,
        "library panics reach no hook"
    );
    let host = std::thread::spawn(|| panic!("a host panic")).join();
    assert!(host.is_err());
    assert_eq!(
        CALLS.load(Ordering::SeqCst),
        1,
        "a host panic reaches the host's hook"
    );
    println!("host hook: 1 call");
    unsafe {
        ok(gdr_filter_release(&mut { f }));
        ok(gdr_context_release(&mut { ctx }));
    }
}

struct CancelState {
    calls: u32,
    cancelled_at: Option<Instant>,
    filter: *mut gdr_filter,
    reentrant: Option<gdr_error>,
}

/// Packed colour/dx/dy buffers of a frame and an output buffer, for the 720p l1 runs.
fn l1_720p_buffers(frame: &Frame) -> (Vec<Vec<f32>>, Vec<f32>) {
    let bufs = INPUTS[..3].iter().map(|&l| interleaved(frame, l)).collect();
    (bufs, vec![0f32; frame.width() * frame.height() * 3])
}

/// Sets the packed colour/dx/dy views and the output, then commits.
unsafe fn set_views_and_commit(
    f: *mut gdr_filter,
    bufs: &[Vec<f32>],
    out: &mut [f32],
    w: usize,
    h: usize,
) {
    for (l, b) in INPUTS[..3].iter().zip(bufs) {
        ok(gdr_filter_set_image(
            f,
            cs(l.name()).as_ptr(),
            b.as_ptr(),
            w,
            h,
            3,
            0,
            0,
        ));
    }
    ok(gdr_filter_set_image(
        f,
        c"output".as_ptr(),
        out.as_mut_ptr(),
        w,
        h,
        3,
        0,
        0,
    ));
    ok(gdr_filter_commit(f));
}

unsafe extern "C" fn cancel_on_second_call(user: *mut c_void, _fraction: f64) -> bool {
    let s = &mut *user.cast::<CancelState>();
    s.calls += 1;
    if s.calls == 1 {
        // Calls on the same filter from its own callback fail instead of deadlocking.
        s.reentrant = Some(gdr_filter_set_float(s.filter, c"alpha".as_ptr(), 0.3));
        return true;
    }
    s.cancelled_at = Some(Instant::now());
    false
}

#[test]
fn cancellation_returns_promptly_on_720p() {
    let (w, h) = (1280, 720);
    let frame = synth::synthetic_frame(w, h, 4.0, 3);
    let (bufs, mut out) = l1_720p_buffers(&frame);
    let ctx = context();
    let f = filter(ctx, "l1");
    let mut state = CancelState {
        calls: 0,
        cancelled_at: None,
        filter: f,
        reentrant: None,
    };
    unsafe {
        set_views_and_commit(f, &bufs, &mut out, w, h);
        ok(gdr_filter_set_progress_callback(
            f,
            Some(cancel_on_second_call),
            (&mut state as *mut CancelState).cast(),
        ));
        let status = gdr_filter_execute(f);
        let returned = Instant::now();
        fails(status, GDR_ERROR_CANCELLED);
        let latency = returned - state.cancelled_at.expect("callback asked to cancel");
        eprintln!(
            "cancellation latency on 1280x720 l1: {:.1} ms",
            latency.as_secs_f64() * 1e3
        );
        assert!(latency < Duration::from_millis(100), "{latency:?}");
        assert_eq!(state.reentrant, Some(GDR_ERROR_INVALID_OPERATION));
        assert!(
            out.iter().all(|&v| v == 0.0),
            "a cancelled execute leaves the output untouched"
        );
        gdr_filter_release(&mut { f });
        gdr_context_release(&mut { ctx });
    }
}

struct Gaps {
    last: Option<Instant>,
    max: Duration,
    calls: u32,
}

unsafe extern "C" fn record_gaps(user: *mut c_void, _fraction: f64) -> bool {
    let g = &mut *user.cast::<Gaps>();
    let now = Instant::now();
    if let Some(last) = g.last {
        g.max = g.max.max(now - last);
    }
    g.last = Some(now);
    g.calls += 1;
    true
}

#[test]
fn cancel_from_another_thread_on_720p() {
    let (w, h) = (1280, 720);
    let frame = synth::synthetic_frame(w, h, 4.0, 5);
    let (bufs, mut out) = l1_720p_buffers(&frame);
    let ctx = context();
    let f = filter(ctx, "l1");
    let mut gaps = Gaps {
        last: None,
        max: Duration::ZERO,
        calls: 0,
    };
    unsafe {
        set_views_and_commit(f, &bufs, &mut out, w, h);
        ok(gdr_filter_set_progress_callback(
            f,
            Some(record_gaps),
            (&mut gaps as *mut Gaps).cast(),
        ));
        let start = Instant::now();
        ok(gdr_filter_execute(f));
        eprintln!(
            "1280x720 l1: {:.0} ms, {} progress calls, largest gap {:.1} ms",
            start.elapsed().as_secs_f64() * 1e3,
            gaps.calls,
            gaps.max.as_secs_f64() * 1e3
        );
        for delay_ms in [50u64, 200, 450] {
            let handle = f as usize;
            let canceller = std::thread::spawn(move || {
                std::thread::sleep(Duration::from_millis(delay_ms));
                let at = Instant::now();
                ok(gdr_filter_cancel(handle as *mut gdr_filter));
                at
            });
            let status = gdr_filter_execute(f);
            let returned = Instant::now();
            let at = canceller.join().unwrap();
            if status == GDR_ERROR_CANCELLED {
                let latency = returned.saturating_duration_since(at);
                eprintln!(
                    "cancel from another thread after {delay_ms} ms: returned {:.1} ms later",
                    latency.as_secs_f64() * 1e3
                );
                // Bounded by the largest gap between the method's progress calls (the points
                // where it can stop), plus scheduling noise on a shared machine.
                let bound = gaps.max + Duration::from_millis(150);
                assert!(latency < bound, "{latency:?}, bound {bound:?}");
                last_error();
            } else {
                ok(status); // finished before the cancel arrived
            }
        }
        gdr_filter_release(&mut { f });
        gdr_context_release(&mut { ctx });
    }
}

#[test]
fn version_matches_the_crate() {
    let v = env!("CARGO_PKG_VERSION")
        .split('.')
        .map(|p| p.parse::<u32>().unwrap())
        .collect::<Vec<_>>();
    assert_eq!(gdr_version(), v[0] * 10000 + v[1] * 100 + v[2]);
    assert_eq!(GDR_VERSION, gdr_version());
    let names: Vec<&str> = (0..)
        .map(|i| gdr_method_name(i))
        .take_while(|p| !p.is_null())
        .map(|p| unsafe { CStr::from_ptr(p) }.to_str().unwrap())
        .collect();
    assert_eq!(names, Method::ALL.map(Method::name));
}

/// A `gdr_param_info` ready for `gdr_method_param`: zeroed, its size set.
fn blank_info() -> gdr_param_info {
    // SAFETY: all-zero bytes are a valid gdr_param_info (null pointers, kind 0, false, 0.0).
    let mut info: gdr_param_info = unsafe { std::mem::zeroed() };
    info.size = std::mem::size_of::<gdr_param_info>();
    info
}

/// Every method's listing from C: what the Rust table says, each parameter settable to its
/// default and readable back, and both ends of each range enforced by the setters.
#[test]
fn parameters_are_listed_from_the_tables_and_every_one_is_settable() {
    let ctx = context();
    for method in Method::ALL {
        let name = CString::new(method.name()).unwrap();
        let mut count = 0usize;
        unsafe { ok(gdr_method_param_count(name.as_ptr(), &mut count)) };
        let table = method.params();
        assert_eq!(
            count,
            table.len() + 2,
            "{method}: its own, then spp and strict"
        );
        let f = filter(ctx, method.name());
        for index in 0..count {
            let mut info = blank_info();
            unsafe { ok(gdr_method_param(name.as_ptr(), index, &mut info)) };
            assert_eq!(info.size, std::mem::size_of::<gdr_param_info>());
            let pname = unsafe { CStr::from_ptr(info.name) }.to_str().unwrap();
            let doc = unsafe { CStr::from_ptr(info.doc) }.to_str().unwrap();
            assert!(!doc.is_empty(), "{method}.{pname} is documented");
            if let Some(row) = table.get(index) {
                assert_eq!(pname, row.name);
                assert_eq!((info.min, info.max), (row.range.min, row.range.max));
                let choices = unsafe { CStr::from_ptr(info.choices) }.to_str().unwrap();
                assert_eq!(choices, row.choices.join(","));
            } else {
                assert_eq!(pname, ["spp", "strict"][index - table.len()]);
            }
            let cname = CString::new(pname).unwrap();
            let p = cname.as_ptr();
            unsafe {
                match info.kind {
                    gdr_param_kind::GDR_PARAM_FLOAT => {
                        ok(gdr_filter_set_float(f, p, info.default_value as f32));
                        let mut v = f32::NAN;
                        ok(gdr_filter_get_float(f, p, &mut v));
                        assert_eq!(f64::from(v), info.default_value, "{method}.{pname}");
                        let below = if info.min_exclusive {
                            info.min
                        } else {
                            info.min - 1.0
                        };
                        fails(
                            gdr_filter_set_float(f, p, below as f32),
                            GDR_ERROR_INVALID_ARGUMENT,
                        );
                        fails(
                            gdr_filter_set_float(f, p, f32::NAN),
                            GDR_ERROR_INVALID_ARGUMENT,
                        );
                    }
                    gdr_param_kind::GDR_PARAM_INT | gdr_param_kind::GDR_PARAM_CHOICE => {
                        ok(gdr_filter_set_int(f, p, info.default_value as i32));
                        let mut v = -1;
                        ok(gdr_filter_get_int(f, p, &mut v));
                        assert_eq!(f64::from(v), info.default_value, "{method}.{pname}");
                        ok(gdr_filter_set_int(f, p, info.max as i32));
                        let m = fails(
                            gdr_filter_set_int(f, p, info.max as i32 + 1),
                            GDR_ERROR_INVALID_ARGUMENT,
                        );
                        assert!(m.contains(pname), "{m}");
                        ok(gdr_filter_set_int(f, p, info.default_value as i32));
                        fails(gdr_filter_set_float(f, p, 1.0), GDR_ERROR_INVALID_ARGUMENT);
                    }
                    gdr_param_kind::GDR_PARAM_BOOL => {
                        ok(gdr_filter_set_bool(f, p, info.default_value != 0.0));
                        let mut v = info.default_value == 0.0;
                        ok(gdr_filter_get_bool(f, p, &mut v));
                        assert_eq!(v, info.default_value != 0.0, "{method}.{pname}");
                        fails(gdr_filter_set_int(f, p, 1), GDR_ERROR_INVALID_ARGUMENT);
                    }
                }
            }
        }
        let mut info = blank_info();
        unsafe {
            let m = fails(
                gdr_method_param(name.as_ptr(), count, &mut info),
                GDR_ERROR_INVALID_ARGUMENT,
            );
            assert!(m.contains(&format!("has {count}")), "{m}");
            info.size = 8;
            let m = fails(
                gdr_method_param(name.as_ptr(), 0, &mut info),
                GDR_ERROR_INVALID_ARGUMENT,
            );
            assert!(m.contains("info->size is 8"), "{m}");
            gdr_filter_release(&mut { f });
        }
    }
    unsafe {
        let mut count = 0usize;
        fails(
            gdr_method_param_count(c"nope".as_ptr(), &mut count),
            GDR_ERROR_INVALID_ARGUMENT,
        );
        fails(
            gdr_method_param_count(c"l1".as_ptr(), null_mut()),
            GDR_ERROR_NULL_POINTER,
        );
        gdr_context_release(&mut { ctx });
    }
}

/// Writes the inputs and the Rust API's outputs for the C tests (see tests/c/run.sh).
#[test]
#[ignore]
fn write_reference_for_c() {
    let dir =
        std::path::PathBuf::from(std::env::var("GDR_CAPI_REF_DIR").expect("GDR_CAPI_REF_DIR"));
    std::fs::create_dir_all(&dir).unwrap();
    let frame = frame();
    let mut bytes: Vec<u8> = Vec::new();
    bytes.extend((W as u32).to_le_bytes());
    bytes.extend((H as u32).to_le_bytes());
    for l in INPUTS {
        bytes.extend(interleaved(&frame, l).iter().flat_map(|v| v.to_le_bytes()));
    }
    std::fs::write(dir.join("frame.bin"), bytes).unwrap();
    let mut custom = gdrecon::recon::PoissonL1Config::default();
    custom.alpha = 0.5;
    custom.reweight_steps = 6;
    custom.cg_iterations = 5;
    for (name, config) in [
        ("l2", MethodConfig::default_for(Method::PoissonL2)),
        ("l1", MethodConfig::default_for(Method::PoissonL1)),
        ("l1_custom", MethodConfig::PoissonL1(custom)),
    ] {
        let out = rust_output(&frame, &config);
        let bytes: Vec<u8> = out.iter().flat_map(|v| v.to_le_bytes()).collect();
        std::fs::write(dir.join(format!("ref_{name}.bin")), bytes).unwrap();
    }
}

/// The test frame, a caller's prior for it (any RGB image: here the reference, handed over as
/// image "prior"), and the frame with that prior as its layer.
fn frame_and_prior() -> (Frame, Image, Frame) {
    let frame = frame();
    let prior = frame.reference().unwrap().clone();
    let with_prior = common::with_prior(frame.clone(), prior.clone());
    (frame, prior, with_prior)
}

#[test]
fn the_prior_image_and_presets_reach_the_method() {
    let (frame, prior, with_prior) = frame_and_prior();
    let expected = rust_output(
        &with_prior,
        &MethodConfig::PoissonL1(gdrecon::recon::PoissonL1Config::prior()),
    );
    let mut bufs = packed_inputs(&frame);
    bufs.push((Layer::Prior, prior.to_interleaved()));
    let ctx = context();
    let l1 = filter(ctx, "l1");
    let alone = filter(ctx, "prior");
    let (mut out, mut out_alone) = (vec![0f32; W * H * 3], vec![0f32; W * H * 3]);
    unsafe {
        let msg = fails(
            gdr_filter_set_preset(l1, c"nope".as_ptr()),
            GDR_ERROR_INVALID_ARGUMENT,
        );
        assert!(
            msg.contains("unknown preset 'nope'") && msg.contains("fast, published, prior"),
            "{msg}"
        );
        ok(gdr_filter_set_preset(l1, c"prior".as_ptr()));
        let (mut data, mut weight) = (-1i32, 0f32);
        ok(gdr_filter_get_int(l1, c"data".as_ptr(), &mut data));
        ok(gdr_filter_get_float(
            l1,
            c"prior_alpha".as_ptr(),
            &mut weight,
        ));
        assert_eq!((data, weight), (GDR_DATA_PRIOR, 2.5));
        set_packed(l1, &bufs);
        run(l1, &mut out);
        set_packed(alone, &bufs);
        run(alone, &mut out_alone);
        let mut report = null();
        ok(gdr_filter_get_report(alone, &mut report));
        let report = CStr::from_ptr(report).to_str().unwrap().to_owned();
        assert!(report.contains("given by the caller"), "{report}");
        gdr_filter_release(&mut { l1 });
        gdr_filter_release(&mut { alone });
        gdr_context_release(&mut { ctx });
    }
    assert!(same_bits(&out, &expected));
    assert!(same_bits(&out_alone, &prior.to_interleaved()));
}

/// With image "prior" set, the commit plans for a given prior: under a memory limit between
/// the plan's needs with and without OIDN's scratch, `l1` with the prior preset commits and
/// runs (the Rust API's image), and the same filter without the prior image is refused.
#[test]
fn a_prior_image_is_planned_for_without_oidns_scratch() {
    let (frame, prior, with_prior) = frame_and_prior();
    let l1 = MethodConfig::PoissonL1(gdrecon::recon::PoissonL1Config::prior());
    let expected = rust_output(&with_prior, &l1);
    let mib = |b: u64| b.div_ceil(1 << 20);
    let computed = mib(l1.fitted_to(W, H, 0).memory_estimate(W, H));
    let given = mib(l1.given_prior().memory_estimate(W, H));
    assert!(given + 2 < computed, "{given} {computed}");
    let mut bufs = packed_inputs(&frame);
    bufs.push((Layer::Prior, prior.to_interleaved()));
    let mut out = vec![0f32; W * H * 3];
    unsafe {
        let mut ctx = null_mut();
        ok(gdr_context_new(&mut ctx));
        let limit = i32::try_from(given + 1).unwrap();
        ok(gdr_context_set_int(ctx, c"max_memory_mb".as_ptr(), limit));
        ok(gdr_context_commit(ctx));
        let f = filter(ctx, "l1");
        ok(gdr_filter_set_preset(f, c"prior".as_ptr()));
        set_packed(f, &bufs);
        run(f, &mut out);
        ok(gdr_filter_unset_image(f, c"prior".as_ptr()));
        let m = fails(gdr_filter_commit(f), GDR_ERROR_OUT_OF_MEMORY);
        assert!(m.contains(&format!("needs about {computed} MiB")), "{m}");
        ok(gdr_filter_release(&mut { f }));
        ok(gdr_context_release(&mut ctx));
    }
    assert!(same_bits(&out, &expected));
}

#[test]
fn the_context_takes_an_oidn_path() {
    let mut ctx = null_mut();
    unsafe {
        ok(gdr_context_new(&mut ctx));
        ok(gdr_context_set_string(
            ctx,
            c"oidn_path".as_ptr(),
            c"/opt/oidn/lib/libOpenImageDenoise.so.2".as_ptr(),
        ));
        let msg = fails(
            gdr_context_set_string(ctx, c"oidn".as_ptr(), c"x".as_ptr()),
            GDR_ERROR_INVALID_ARGUMENT,
        );
        assert!(
            msg.contains("onnxruntime_path, model_path, oidn_path"),
            "{msg}"
        );
        ok(gdr_context_commit(ctx));
        let msg = fails(
            gdr_context_set_string(ctx, c"oidn_path".as_ptr(), null()),
            GDR_ERROR_INVALID_OPERATION,
        );
        assert!(msg.contains("already committed"), "{msg}");
        ok(gdr_context_release(&mut ctx));
    }
}

#[test]
fn max_memory_mb_refuses_the_commit() {
    let frame = frame();
    let inputs = packed_inputs(&frame);
    let mut out = vec![0.0f32; 3 * W * H];
    unsafe {
        let mut ctx = null_mut();
        ok(gdr_context_new(&mut ctx));
        let name = cs("max_memory_mb");
        fails(
            gdr_context_set_int(ctx, name.as_ptr(), -1),
            GDR_ERROR_INVALID_ARGUMENT,
        );
        ok(gdr_context_set_int(ctx, name.as_ptr(), 1));
        let mut value = 0;
        ok(gdr_context_get_int(ctx, name.as_ptr(), &mut value));
        assert_eq!(value, 1);
        ok(gdr_context_commit(ctx));
        fails(
            gdr_context_set_int(ctx, name.as_ptr(), 2),
            GDR_ERROR_INVALID_OPERATION,
        );
        // l1 needs about 120 B a pixel and 1 MiB: over 1 MiB at any size.
        let f = filter(ctx, "l1");
        set_packed(f, &inputs);
        ok(gdr_filter_set_image(
            f,
            c"output".as_ptr(),
            out.as_mut_ptr(),
            W,
            H,
            3,
            0,
            0,
        ));
        let m = fails(gdr_filter_commit(f), GDR_ERROR_OUT_OF_MEMORY);
        assert!(
            m.contains("MiB") && m.contains("max_memory_mb = 1") && !m.contains('\n'),
            "{m}"
        );
        ok(gdr_filter_release(&mut { f }));
        ok(gdr_context_release(&mut ctx));
    }
}
