//! Numerical stress: hostile frames through every method. For each case and method: no
//! panic, no NaN or Inf out, and the output stays within the bound that holds for the L2
//! solve, `max|I_b| + 4 max|g| / alpha^2` (the screened operator's inverse has infinity norm
//! at most `1 / alpha^2`, and `|D^T g| <= 4 max|g|`), checked for L1 and the filter too;
//! GradNet, which has no such operator, is held to `max(I_b) + (W + H) max|g|` (what any image
//! with the frame's gradients reaches along a path from its brightest base pixel), to which it
//! clamps. The combiner, a convex combination of the prior and two L1 solves on it, is held to
//! the L2 bound; these frames lack the layers it reads, so it gets plain ones ([`frame_for`]).

mod common;

use common::*;
use gdrecon::{
    recon::reconstruct, Frame, FrameBuilder, Image, Layer, Method, MethodConfig, Policy,
};

struct Case {
    name: &'static str,
    color: Image,
    dx: Image,
    dy: Image,
    spp: Option<f32>,
}

/// The frame `builder` makes for `method`: for the combiner with the layers it reads and these
/// frames lack (a variance of 0.01, a grey albedo, normals facing the camera).
fn frame_for(
    method: Method,
    builder: &FrameBuilder,
    size: (usize, usize),
) -> gdrecon::Result<Frame> {
    let builder = builder.clone();
    let builder = if method == Method::Combiner {
        let (w, h) = size;
        builder
            .image(Layer::Variance, filled(w, h, |_| 0.01))
            .image(Layer::Albedo, filled(w, h, |_| 0.5))
            .image(
                Layer::Normal,
                filled(w, h, |(c, _, _)| (c == 2) as u8 as f32),
            )
    } else {
        builder
    };
    builder.build(Policy::Replace)
}

fn filled(w: usize, h: usize, f: impl FnMut((usize, usize, usize)) -> f32) -> Image {
    Image::from_fn(3, w, h, f)
}

fn cases() -> Vec<Case> {
    let mut v = Vec::new();
    let mut add = |name, color: Image, dx: Image, dy: Image, spp| {
        v.push(Case {
            name,
            color,
            dx,
            dy,
            spp,
        })
    };
    let z = |w, h| Image::zeros(3, w, h);
    for (w, h) in [
        (1, 1),
        (1, 9),
        (9, 1),
        (2, 2),
        (13, 7),
        (33, 17),
        (8192, 8),
        (8, 300),
    ] {
        let img = test_image(w, h);
        let (dx, dy) = exact_gradients(&img);
        add("sizes", img, dx, dy, Some(4.0));
    }
    add("all zero", z(16, 16), z(16, 16), z(16, 16), None);
    add(
        "constant",
        filled(16, 16, |_| 3.5),
        z(16, 16),
        z(16, 16),
        Some(1.0),
    );
    let mut rng = Lcg(1);
    let nanny = filled(24, 24, |_| match (rng.uniform() * 10.0) as u32 {
        0 => f32::NAN,
        1 => f32::INFINITY,
        2 => f32::NEG_INFINITY,
        3 => -5.0,
        _ => 0.5,
    });
    add(
        "nan inf negative color",
        nanny.clone(),
        nanny.clone(),
        nanny,
        None,
    );
    let mut rng = Lcg(2);
    let fireflies = filled(32, 32, |_| if rng.uniform() < 0.01 { 1e6 } else { 0.2 });
    add(
        "1e6 fireflies in color",
        fireflies,
        z(32, 32),
        z(32, 32),
        Some(4.0),
    );
    let mut rng = Lcg(3);
    let gf = filled(32, 32, |_| {
        if rng.uniform() < 0.01 {
            1e6 * rng.signed() as f32
        } else {
            0.0
        }
    });
    add(
        "1e6 fireflies in gradients",
        filled(32, 32, |_| 0.2),
        gf.clone(),
        gf,
        Some(4.0),
    );
    let denormal = f32::MIN_POSITIVE / 8.0;
    add(
        "denormals",
        filled(16, 16, |_| denormal),
        filled(16, 16, |_| denormal),
        filled(16, 16, |_| -denormal),
        Some(2.0),
    );
    let img = test_image(20, 20);
    let (dx, dy) = exact_gradients(&img);
    let scale = |g: &Image, s: f32| filled(20, 20, |(c, x, y)| g.at(c, x, y) * s);
    add(
        "gradients 1e4 x too large",
        img.clone(),
        scale(&dx, 1e4),
        scale(&dy, 1e4),
        Some(16.0),
    );
    add(
        "gradients inconsistent in sign",
        img.clone(),
        scale(&dx, -1.0),
        scale(&dy, 1e-4),
        Some(16.0),
    );
    add(
        "huge finite values",
        filled(8, 8, |_| 1e30),
        filled(8, 8, |_| 1e30),
        filled(8, 8, |_| -1e30),
        Some(1.0),
    );
    v
}

#[test]
fn every_method_survives_every_case_within_the_bound() {
    let mut count = 0;
    for case in cases() {
        let (w, h) = case.color.size();
        let builder = FrameBuilder::new()
            .image(Layer::Color, case.color)
            .image(Layer::Dx, case.dx)
            .image(Layer::Dy, case.dy)
            .spp(case.spp);
        let frame = builder.clone().build(Policy::Replace).unwrap();
        let maxabs = |img: &Image| {
            img.as_slice()
                .iter()
                .fold(0.0f64, |m, &v| m.max(f64::from(v.abs())))
        };
        // Ignore the last column of dx / last row of dy: they carry no information.
        let gmax = (0..3)
            .flat_map(|c| (0..h).flat_map(move |y| (0..w).map(move |x| (c, x, y))))
            .map(|(c, x, y)| {
                let gx = if x + 1 < w {
                    frame.dx().at(c, x, y).abs()
                } else {
                    0.0
                };
                let gy = if y + 1 < h {
                    frame.dy().at(c, x, y).abs()
                } else {
                    0.0
                };
                f64::from(gx.max(gy))
            })
            .fold(0.0, f64::max);
        for method in Method::ALL.into_iter().filter(|m| m.is_built()) {
            let config = MethodConfig::default_for(method);
            if method == Method::Frgr && frame.spp().is_none() {
                // The filter's weights depend on the sample count: it must ask for it.
                let e = reconstruct(&frame, &config).unwrap_err();
                assert!(
                    e.to_string().contains("spp"),
                    "{} / {method}: {e}",
                    case.name
                );
                count += 1;
                continue;
            }
            let input = frame_for(method, &builder, (w, h)).unwrap();
            let (out, report) = reconstruct(&input, &config)
                .unwrap_or_else(|e| panic!("{} / {method}: {e}", case.name));
            assert!(
                out.all_finite(),
                "{} / {method}: non-finite output",
                case.name
            );
            assert_eq!(report.output_repaired, 0, "{} / {method}", case.name);
            let negative = out.as_slice().iter().filter(|v| **v < 0.0).count();
            assert_eq!(negative, 0, "{} / {method}: negative output", case.name);
            // Screened Poisson (alpha 0.2) and the filter: max|I_b| + 4 max|g| / alpha^2.
            // GradNet clamps to max(I_b) + (W + H) max|g| (any path from the brightest pixel);
            // auto runs one of them.
            let (w, h) = frame.size();
            let poisson = maxabs(frame.color()) + 4.0 * gmax / 0.04;
            let path = maxabs(frame.color()) + (w + h) as f64 * gmax;
            let bound = match method {
                Method::GradNet => path,
                Method::Auto => poisson.max(path),
                _ => poisson,
            };
            let got = maxabs(&out);
            assert!(
                got <= bound * (1.0 + 1e-3) + 1e-6,
                "{} / {method}: |out| {got:e} > bound {bound:e}",
                case.name
            );
            count += 1;
        }
    }
    println!("{count} case x method runs");
    assert_eq!(
        count,
        cases().len() * Method::ALL.iter().filter(|m| m.is_built()).count()
    );
}

#[test]
fn replaced_values_are_reported() {
    let nan = filled(4, 4, |(c, y, x)| {
        if (c, y, x) == (0, 1, 1) {
            f32::NAN
        } else {
            1.0
        }
    });
    let builder = FrameBuilder::new()
        .image(Layer::Color, nan)
        .image(Layer::Dx, Image::zeros(3, 4, 4))
        .image(Layer::Dy, Image::zeros(3, 4, 4))
        .spp(Some(4.0));
    for method in Method::ALL.into_iter().filter(|m| m.is_built()) {
        let frame = frame_for(method, &builder, (4, 4)).unwrap();
        let (_, report) = reconstruct(&frame, &MethodConfig::default_for(method)).unwrap();
        assert_eq!(report.sanitized.layer(Layer::Color).non_finite, 1);
        assert!(
            report.to_string().contains("color: 1 non-finite"),
            "{report}"
        );
    }
}

/// Absurd but finite gradients (1e30, f32::MAX, a million times the colour) are implausible:
/// replaced by 0, counted, reported; the output stays in the colour's range for every method
/// (they used to reach 1e30, or an all-zero image for GradNet). Strict mode refuses them.
#[test]
fn implausible_gradients_are_replaced_and_reported() {
    let (w, h) = (24, 20);
    let color = filled(w, h, |(c, x, y)| {
        0.1 + 0.9 * ((x + 2 * y + c) % 7) as f32 / 6.0
    });
    let (dx, dy) = exact_gradients(&color);
    let mut bad = 0;
    let mut poison = |g: &Image, values: &[f32]| {
        let mut g = g.clone();
        for (i, &v) in values.iter().enumerate() {
            g.plane_mut(i % 3)[[3 + 2 * i, 5 + i]] = v;
            bad += 1;
        }
        g
    };
    let dx = poison(&dx, &[1e30, -f32::MAX, 1e6, 2e6]);
    let dy = poison(&dy, &[f32::MAX, -1e30, 1e6]);
    let build = |policy| {
        FrameBuilder::new()
            .image(Layer::Color, color.clone())
            .image(Layer::Dx, dx.clone())
            .image(Layer::Dy, dy.clone())
            .spp(Some(4.0))
            .build(policy)
    };
    let e = build(Policy::Strict).unwrap_err().to_string();
    assert!(
        e.contains("layer 'dx' holds 4") && e.contains("implausible"),
        "{e}"
    );
    let frame = build(Policy::Replace).unwrap();
    let replaced = frame.sanitized().layer(Layer::Dx).implausible
        + frame.sanitized().layer(Layer::Dy).implausible;
    assert_eq!(replaced, bad);
    // Plausible gradients (up to 64 x the brightest colour) are kept.
    assert_eq!(
        frame.dx().at(0, 0, 0),
        exact_gradients(&color).0.at(0, 0, 0)
    );
    let builder = FrameBuilder::new()
        .image(Layer::Color, color.clone())
        .image(Layer::Dx, dx.clone())
        .image(Layer::Dy, dy.clone())
        .spp(Some(4.0));
    for method in Method::ALL.into_iter().filter(|m| m.is_built()) {
        let frame = frame_for(method, &builder, (w, h)).unwrap();
        let (out, report) = reconstruct(&frame, &MethodConfig::default_for(method)).unwrap();
        let top = out.as_slice().iter().fold(0.0f32, |m, v| m.max(v.abs()));
        assert!(out.all_finite() && top <= 1.5, "{method}: max |out| {top}");
        assert!(
            report.to_string().contains("implausible"),
            "{method}: {report}"
        );
    }
}
