//! The bad-input policy of docs/CONVENTIONS.md, one test per case.

mod common;

use common::*;
use gdrecon::{Error, FrameBuilder, Image, Layer, Policy};
use ndarray::ShapeBuilder;

fn base(w: usize, h: usize) -> FrameBuilder {
    let img = test_image(w, h);
    let (dx, dy) = exact_gradients(&img);
    FrameBuilder::new()
        .image(Layer::Color, img)
        .image(Layer::Dx, dx)
        .image(Layer::Dy, dy)
}

fn input_error(r: gdrecon::Result<gdrecon::Frame>) -> String {
    match r {
        Err(Error::InvalidInput(m)) => m,
        other => panic!("expected InvalidInput, got {other:?}"),
    }
}

#[test]
fn missing_required_layer_is_named() {
    for layer in [Layer::Color, Layer::Dx, Layer::Dy] {
        let m = input_error(base(4, 3).without(layer).build(Policy::Replace));
        assert!(
            m.contains(&format!("'{layer}'")) && m.contains("missing"),
            "{m}"
        );
    }
}

#[test]
fn sizes_that_disagree_are_named() {
    let m = input_error(
        base(4, 3)
            .image(Layer::Albedo, Image::zeros(3, 5, 3))
            .build(Policy::Replace),
    );
    assert!(
        m.contains("'albedo' is 5 x 3") && m.contains("4 x 3"),
        "{m}"
    );
}

#[test]
fn wrong_channel_count_is_named() {
    let m = input_error(
        base(4, 3)
            .image(Layer::Depth, Image::zeros(3, 4, 3))
            .build(Policy::Replace),
    );
    assert!(m.contains("'depth' has 3 channels, expected 1"), "{m}");
}

#[test]
fn zero_sized_image_is_refused() {
    let m = input_error(
        FrameBuilder::new()
            .image(Layer::Color, Image::zeros(3, 4, 0))
            .image(Layer::Dx, Image::zeros(3, 4, 0))
            .image(Layer::Dy, Image::zeros(3, 4, 0))
            .build(Policy::Replace),
    );
    assert!(m.contains("4 x 0"), "{m}");
}

#[test]
fn bad_spp_is_refused() {
    for spp in [0.0, -4.0, f32::NAN, f32::INFINITY] {
        let m = input_error(base(4, 3).spp(Some(spp)).build(Policy::Replace));
        assert!(m.contains("spp"), "{m}");
    }
    assert_eq!(
        base(4, 3).spp(None).build(Policy::Replace).unwrap().spp(),
        None
    );
    // Setting it on a built frame checks it the same way and keeps what was replaced.
    let mut color = test_image(4, 3);
    color.as_mut_slice()[2] = f32::NAN;
    let frame = base(4, 3)
        .image(Layer::Color, color)
        .build(Policy::Replace)
        .unwrap();
    for spp in [0.0, -4.0, f32::NAN, f32::INFINITY] {
        let m = input_error(frame.clone().with_spp(Some(spp)));
        assert!(m.contains("spp"), "{m}");
    }
    let frame = frame.with_spp(Some(8.0)).unwrap();
    assert_eq!(frame.spp(), Some(8.0));
    assert_eq!(frame.sanitized().layer(Layer::Color).non_finite, 1);
}

#[test]
fn non_finite_values_are_replaced_and_counted_in_every_layer() {
    let (w, h) = (5, 4);
    let mut b = base(w, h)
        .image(Layer::Variance, Image::zeros(3, w, h))
        .image(Layer::Albedo, Image::zeros(3, w, h))
        .image(Layer::Normal, Image::zeros(3, w, h))
        .image(Layer::Depth, Image::zeros(1, w, h))
        .image(Layer::Reference, Image::zeros(3, w, h));
    for (k, layer) in Layer::ALL.into_iter().enumerate() {
        let mut img = Image::zeros(layer.channels(), w, h);
        img.as_mut_slice()[k] = f32::NAN;
        img.as_mut_slice()[k + 1] = f32::INFINITY;
        img.as_mut_slice()[k + 2] = f32::NEG_INFINITY;
        b = b.image(layer, img);
    }
    let frame = b.build(Policy::Replace).unwrap();
    for layer in Layer::ALL {
        assert_eq!(frame.sanitized().layer(layer).non_finite, 3, "{layer}");
        assert!(frame.layer(layer).unwrap().all_finite());
    }
    assert_eq!(frame.sanitized().total(), 3 * Layer::ALL.len() as u64);
}

#[test]
fn negative_colour_and_variance_are_replaced_but_gradients_and_normals_kept() {
    let (w, h) = (5, 4);
    let mut color = test_image(w, h);
    color.as_mut_slice()[3] = -2.0;
    let mut var = Image::zeros(3, w, h);
    var.as_mut_slice()[0] = -1.0;
    let mut dx = Image::zeros(3, w, h);
    dx.as_mut_slice()[0] = -1.0;
    let mut normal = Image::zeros(3, w, h);
    normal.as_mut_slice()[0] = -1.0;
    let frame = base(w, h)
        .image(Layer::Color, color)
        .image(Layer::Variance, var)
        .image(Layer::Dx, dx)
        .image(Layer::Normal, normal)
        .build(Policy::Replace)
        .unwrap();
    assert_eq!(frame.sanitized().layer(Layer::Color).negative, 1);
    assert_eq!(frame.sanitized().layer(Layer::Variance).negative, 1);
    assert_eq!(frame.color().as_slice()[3], 0.0);
    assert_eq!(frame.dx().as_slice()[0], -1.0);
    assert_eq!(frame.normal().unwrap().as_slice()[0], -1.0);
    assert!(frame.sanitized().to_string().contains("color: 1 negative"));
}

#[test]
fn strict_mode_refuses_and_names_layer_and_pixel() {
    let (w, h) = (5, 4);
    let mut dy = Image::zeros(3, w, h);
    dy.plane_mut(1)[[2, 3]] = f32::NAN;
    let m = input_error(base(w, h).image(Layer::Dy, dy).build(Policy::Strict));
    assert!(
        m.contains("'dy'") && m.contains("pixel (3, 2)") && m.contains("channel G"),
        "{m}"
    );
    let mut color = test_image(w, h);
    color.as_mut_slice()[0] = -1.0;
    let m = input_error(base(w, h).image(Layer::Color, color).build(Policy::Strict));
    assert!(m.contains("'color'") && m.contains("negative"), "{m}");
    assert!(base(w, h).build(Policy::Strict).is_ok());
}

#[test]
fn output_never_holds_nan_or_inf_whatever_the_input() {
    let (w, h) = (16, 12);
    let mut color = test_image(w, h);
    color.as_mut_slice()[5] = f32::NAN;
    color.as_mut_slice()[6] = f32::INFINITY;
    let mut dx = Image::zeros(3, w, h);
    dx.as_mut_slice()[7] = f32::NEG_INFINITY;
    dx.as_mut_slice()[8] = 1e30;
    let mut dy = Image::zeros(3, w, h);
    dy.as_mut_slice()[9] = -1e30;
    // Variance, albedo and normal too (clean): the combiner reads them.
    let frame = base(w, h)
        .image(Layer::Color, color)
        .image(Layer::Dx, dx)
        .image(Layer::Dy, dy)
        .image(Layer::Variance, Image::from_fn(3, w, h, |_| 0.01))
        .image(Layer::Albedo, Image::from_fn(3, w, h, |_| 0.5))
        .image(
            Layer::Normal,
            Image::from_fn(3, w, h, |(c, _, _)| (c == 2) as u8 as f32),
        )
        .spp(Some(4.0))
        .build(Policy::Replace)
        .unwrap();
    for m in gdrecon::Method::ALL.into_iter().filter(|m| m.is_built()) {
        let (out, report) =
            gdrecon::recon::reconstruct(&frame, &gdrecon::MethodConfig::default_for(m)).unwrap();
        assert!(out.all_finite(), "{m}");
        // 3 non-finite values, and the two 1e30 gradients are implausible.
        assert_eq!(report.sanitized.total(), 5, "{m}");
        let implausible = report.sanitized.layer(Layer::Dx).implausible
            + report.sanitized.layer(Layer::Dy).implausible;
        assert_eq!(implausible, 2, "{m}");
    }
}

#[test]
fn strided_views_equal_packed_images() {
    let (w, h) = (6, 4);
    let img = test_image(w, h);
    // RGBA interleaved buffer with 2 floats of row padding.
    let row = 4 * w + 2;
    let mut buf = vec![-9.0f32; row * h];
    for y in 0..h {
        for x in 0..w {
            for c in 0..3 {
                buf[y * row + 4 * x + c] = img.at(c, x, y);
            }
        }
    }
    let view = ndarray::ArrayView3::from_shape((h, w, 3).strides((row, 4, 1)), &buf).unwrap();
    assert_eq!(Image::from_hwc(view), img);
    let planar = img.as_slice().to_vec();
    let view = ndarray::ArrayView3::from_shape((h, w, 3).strides((w, 1, w * h)), &planar).unwrap();
    assert_eq!(Image::from_hwc(view), img);
}

#[test]
fn garbage_features_leave_the_filter_finite() {
    // Features are only "roughly in [0, 1]" by convention; huge values must not overflow the
    // prefilter, RDFC, GLU or the QP into a non-finite result.
    let (w, h) = (20, 18);
    let mut albedo = Image::from_fn(3, w, h, |(c, x, y)| ((x + 2 * y + c) % 7) as f32 * 0.1);
    albedo.as_mut_slice()[11] = 3e38;
    albedo.as_mut_slice()[40] = -3e38;
    let mut normal = Image::from_fn(3, w, h, |(c, _, _)| if c == 2 { 1.0 } else { 0.0 });
    normal.as_mut_slice()[100] = 1e30;
    let frame = base(w, h)
        .image(Layer::Albedo, albedo)
        .image(Layer::Normal, normal)
        .spp(Some(4.0))
        .build(Policy::Replace)
        .unwrap();
    let (out, report) = gdrecon::recon::reconstruct(
        &frame,
        &gdrecon::MethodConfig::default_for(gdrecon::Method::Frgr),
    )
    .unwrap();
    assert!(out.all_finite());
    assert_eq!(report.output_repaired, 0, "{report}");
}
