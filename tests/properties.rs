//! Property tests (proptest): random frames of random small sizes, values drawn from wide and
//! hostile ranges (huge, tiny, denormal, NaN, Inf, negative), through every method. Each case:
//! no panic, no NaN or Inf out, output within the method's stated bound (see tests/stress.rs),
//! and the same result for 1 and 3 threads (bit-identical for the native methods).

use gdrecon::recon::GradNetConfig;
use gdrecon::{
    Context, ContextOptions, Frame, FrameBuilder, Image, Layer, Method, MethodConfig, Plan, Policy,
    Progress,
};
use proptest::prelude::*;

/// A value from the ranges renderers and bugs produce.
fn value() -> impl Strategy<Value = f32> {
    prop_oneof![
        8 => 0.0f32..2.0,
        2 => -1.0f32..1.0,
        1 => Just(0.0f32),
        1 => 1e3f32..1e6,
        1 => prop_oneof![Just(f32::NAN), Just(f32::INFINITY), Just(f32::NEG_INFINITY)],
        1 => prop_oneof![Just(1e-40f32), Just(-1e-42f32), Just(f32::MIN_POSITIVE)],
    ]
}

fn image(w: usize, h: usize) -> impl Strategy<Value = Image> {
    prop::collection::vec(value(), 3 * w * h).prop_map(move |v| {
        Image::from_planes(ndarray::Array3::from_shape_vec((3, h, w), v).unwrap())
    })
}

fn frame() -> impl Strategy<Value = Frame> {
    (1usize..20, 1usize..20, prop::option::of(1.0f32..256.0))
        .prop_flat_map(|(w, h, spp)| (image(w, h), image(w, h), image(w, h), Just(spp)))
        .prop_map(|(color, dx, dy, spp)| {
            FrameBuilder::new()
                .image(Layer::Color, color)
                .image(Layer::Dx, dx)
                .image(Layer::Dy, dy)
                .spp(spp)
                .build(Policy::Replace)
                .expect("Replace accepts any values")
        })
}

fn max_abs(img: &Image) -> f64 {
    img.as_slice()
        .iter()
        .fold(0.0f64, |m, v| m.max(f64::from(v.abs())))
}

/// max |g| over the differences that exist (the last dx column and dy row are ignored).
fn max_gradient(frame: &Frame) -> f64 {
    let (w, h) = frame.size();
    let mut m = 0.0f64;
    for c in 0..3 {
        for y in 0..h {
            for x in 0..w {
                if x + 1 < w {
                    m = m.max(f64::from(frame.dx().at(c, x, y).abs()));
                }
                if y + 1 < h {
                    m = m.max(f64::from(frame.dy().at(c, x, y).abs()));
                }
            }
        }
    }
    m
}

fn run(frame: &Frame, config: &MethodConfig, threads: usize) -> Image {
    let ctx = Context::new(ContextOptions::with_threads(Some(threads))).unwrap();
    let mut plan = Plan::new(&ctx, config, frame.width(), frame.height()).unwrap();
    let (out, report) = plan.execute(frame, &Progress::none()).unwrap();
    assert_eq!(
        report.output_repaired, 0,
        "a method produced non-finite values"
    );
    out
}

fn check(frame: &Frame, method: Method) {
    let config = match method {
        // Small tiles are fine here: frames are at most 19 x 19 (one tile).
        Method::GradNet => MethodConfig::GradNet(GradNetConfig::default()),
        m => MethodConfig::default_for(m),
    };
    let out = run(frame, &config, 1);
    assert!(out.all_finite(), "{method}: non-finite output");
    let (w, h) = frame.size();
    let (colour, g) = (max_abs(frame.color()), max_gradient(frame));
    let bound = match method {
        Method::GradNet => colour + (w + h) as f64 * g,
        _ => colour + 4.0 * g / 0.04,
    };
    let got = max_abs(&out);
    assert!(
        got <= bound * (1.0 + 1e-3) + 1e-6,
        "{method}: |out| {got:e} > bound {bound:e}"
    );
    let again = run(frame, &config, 3);
    if method == Method::GradNet {
        for (a, b) in again.as_slice().iter().zip(out.as_slice()) {
            assert!(
                (a - b).abs() <= 1e-4 * (b.abs() + 1e-3),
                "{method}: threads"
            );
        }
    } else {
        assert_eq!(again.as_slice(), out.as_slice(), "{method}: thread count");
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    #[test]
    fn poisson_methods_hold_their_bound(frame in frame()) {
        check(&frame, Method::PoissonL2);
        check(&frame, Method::PoissonL1);
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    #[test]
    fn filter_holds_its_bound_or_asks_for_spp(frame in frame()) {
        if frame.spp().is_some() {
            check(&frame, Method::Frgr);
        } else {
            let e = gdrecon::recon::reconstruct(&frame, &MethodConfig::default_for(Method::Frgr));
            prop_assert!(e.unwrap_err().to_string().contains("spp"));
        }
    }

    #[cfg(all(feature = "gradnet", feature = "embed-model"))]
    #[test]
    fn gradnet_holds_its_bound(frame in frame()) {
        check(&frame, Method::GradNet);
    }
}
