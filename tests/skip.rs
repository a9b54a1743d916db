//! Work a frame does not need is skipped, and skipping never changes the answer: empty regions
//! (zero colour, gradients and variance) cost the filter's QP and GradNet's network nothing and
//! come out black; frames without features run the reduced paths (see tests/gradnet.rs).

use std::path::Path;

use gdrecon::recon::FrgrConfig;
#[cfg(all(feature = "gradnet", feature = "embed-model"))]
use gdrecon::recon::GradNetConfig;
use gdrecon::{
    io, Context, ContextOptions, Frame, FrameBuilder, Image, Layer, MethodConfig, Plan, Policy,
    Progress, Report,
};

/// The bundled sample frame.
fn sample() -> Frame {
    io::read_bundle(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/data/sample.exr"),
        Policy::Replace,
    )
    .unwrap()
}

/// The bundled sample placed at the right of a frame `pad` pixels wider, left part empty.
fn half_empty(pad: usize) -> Frame {
    let sample = sample();
    let (w, h) = sample.size();
    let widen = |img: &Image| {
        Image::from_fn(img.channels(), w + pad, h, |(c, x, y)| {
            if x >= pad {
                img.at(c, x - pad, y)
            } else {
                0.0
            }
        })
    };
    let mut b = FrameBuilder::new().spp(sample.spp());
    for layer in [Layer::Color, Layer::Dx, Layer::Dy, Layer::Variance] {
        b = b.image(layer, widen(sample.layer(layer).unwrap()));
    }
    b.build(Policy::Replace).unwrap()
}

fn run(frame: &Frame, config: MethodConfig) -> (Image, Report) {
    let ctx = Context::new(ContextOptions::with_threads(Some(2))).unwrap();
    Plan::new(&ctx, &config, frame.width(), frame.height())
        .unwrap()
        .execute(frame, &Progress::none())
        .unwrap()
}

fn left_is_black(out: &Image, upto: usize) -> bool {
    (0..3).all(|c| (0..out.height()).all(|y| (0..upto).all(|x| out.at(c, x, y) == 0.0)))
}

/// The report's skip line containing `needle` (the test fails if there is none).
fn skipped<'a>(report: &'a Report, needle: &str) -> &'a str {
    report
        .skipped
        .iter()
        .find(|s| s.contains(needle))
        .unwrap_or_else(|| panic!("no skip line with '{needle}': {:?}", report.skipped))
}

fn stage(report: &Report, prefix: &str) -> f64 {
    report
        .stages
        .iter()
        .filter(|s| s.name.starts_with(prefix))
        .map(|s| s.time.as_secs_f64())
        .sum()
}

#[test]
fn filter_skips_empty_windows_in_the_qp() {
    let frame = half_empty(320);
    let (out, report) = run(&frame, MethodConfig::Frgr(FrgrConfig::default()));
    let skipped: Vec<&String> = report
        .skipped
        .iter()
        .filter(|s| s.contains("empty pixels"))
        .collect();
    assert!(!skipped.is_empty(), "{:?}", report.skipped);
    // The 9 x 9 window of the 4 columns next to the content reaches it; further left is empty.
    assert!(left_is_black(&out, 300));
    println!(
        "frgr on 640 x 180, left half empty: qp {:.3} s; {:?}",
        stage(&report, "qp"),
        skipped
    );
}

/// The sample with its samples per pixel set to `spp` (every layer unchanged).
fn sample_at(spp: f32) -> Frame {
    let sample = sample();
    let mut b = FrameBuilder::new().spp(Some(spp));
    for layer in Layer::ALL {
        if let Some(img) = sample.layer(layer) {
            b = b.image(layer, img.clone());
        }
    }
    b.build(Policy::Replace).unwrap()
}

#[test]
fn filter_drops_qp_terms_whose_weight_vanishes_at_very_high_spp() {
    let config = MethodConfig::Frgr(FrgrConfig::default());
    let (_, report) = run(&sample_at(16.0), config.clone());
    assert!(
        !report.skipped.iter().any(|s| s.contains("vanishes")),
        "{:?}",
        report.skipped
    );
    // At 1e12 spp the albedo, normal and coarser-level terms weigh under 1e-4 of the
    // objective (measured on this frame: they start to from about 1e10 spp, the normal term
    // first).
    let (out, report) = run(&sample_at(1e12), config);
    let note = skipped(&report, "vanishes");
    assert!(note.contains("normal"), "{note}");
    assert!(out.as_slice().iter().all(|v| v.is_finite()));
    println!("{note}; qp {:.3} s", stage(&report, "qp"));
}

#[test]
fn filter_without_features_skips_their_terms_and_prefilter() {
    // The sample has 16 spp, where the prefilter runs only when asked to.
    let mut frgr = FrgrConfig::default();
    frgr.prefilter_below = 1e9;
    let config = MethodConfig::Frgr(frgr);
    let (_, with) = run(&sample(), config.clone());
    assert!(stage(&with, "feature prefilter") > 0.0, "{:?}", with.stages);
    assert!(!with.skipped.iter().any(|s| s.contains("prefilter")));
    let sample = sample();
    let mut b = FrameBuilder::new().spp(sample.spp());
    for layer in [Layer::Color, Layer::Dx, Layer::Dy, Layer::Variance] {
        b = b.image(layer, sample.layer(layer).unwrap().clone());
    }
    let (out, without) = run(&b.build(Policy::Replace).unwrap(), config);
    let note = skipped(&without, "no albedo or normal");
    assert!(note.contains("prefilter"), "{note}");
    assert_eq!(stage(&without, "feature prefilter"), 0.0);
    assert!(out.as_slice().iter().all(|v| v.is_finite()));
}

#[cfg(all(feature = "gradnet", feature = "embed-model"))]
#[test]
fn gradnet_skips_empty_tiles() {
    let frame = half_empty(640);
    let mut config = GradNetConfig::default();
    config.whole_pixels = 0;
    config.tile_pixels = 256 * 184; // 12 tiles of 256 x 184
    let (out, report) = run(&frame, MethodConfig::GradNet(config));
    let note = skipped(&report, "no radiance and no gradient");
    println!(
        "gradnet on 960 x 180, 640 columns empty: network {:.3} s; {note}",
        stage(&report, "network")
    );
    assert!(left_is_black(&out, 500));
}

/// The sample with its right `w` columns replaced by the 4096 spp reference, declared
/// converged there (variance 0, gradients the reference's exact differences).
fn half_converged() -> Frame {
    let sample = sample();
    let (w, h) = sample.size();
    let reference = sample.reference().unwrap();
    let converged = |x: usize| x >= w;
    let colour = Image::from_fn(3, 2 * w, h, |(c, x, y)| {
        if converged(x) {
            reference.at(c, x - w, y)
        } else {
            sample.color().at(c, x, y)
        }
    });
    let (exact_dx, exact_dy) = colour.forward_differences();
    let pick = |layer: Layer, exact: &Image| {
        Image::from_fn(3, 2 * w, h, |(c, x, y)| {
            if x + 1 >= w {
                exact.at(c, x, y)
            } else {
                sample.layer(layer).unwrap().at(c, x, y)
            }
        })
    };
    let variance = Image::from_fn(3, 2 * w, h, |(c, x, y)| {
        if converged(x) {
            0.0
        } else {
            sample.variance().unwrap().at(c, x, y)
        }
    });
    FrameBuilder::new()
        .spp(sample.spp())
        .image(Layer::Dx, pick(Layer::Dx, &exact_dx))
        .image(Layer::Dy, pick(Layer::Dy, &exact_dy))
        .image(Layer::Color, colour)
        .image(Layer::Variance, variance)
        .build(Policy::Replace)
        .unwrap()
}

fn right_is_base(out: &Image, frame: &Frame, from: usize) -> bool {
    (0..3).all(|c| {
        (0..out.height()).all(|y| {
            (from..out.width()).all(|x| {
                let (o, b) = (out.at(c, x, y), frame.color().at(c, x, y));
                (o - b).abs() <= 1e-6 * b.abs()
            })
        })
    })
}

#[test]
fn filter_keeps_converged_pixels() {
    let frame = half_converged();
    let (out, report) = run(&frame, MethodConfig::Frgr(FrgrConfig::default()));
    let note = skipped(&report, "converged pixels");
    println!(
        "frgr on 640 x 180, right half converged: qp {:.3} s; {note}",
        stage(&report, "qp")
    );
    assert!(right_is_base(&out, &frame, 320));
}

#[cfg(all(feature = "gradnet", feature = "embed-model"))]
#[test]
fn gradnet_keeps_converged_tiles() {
    let frame = half_converged();
    let mut config = GradNetConfig::default();
    config.whole_pixels = 0;
    config.tile_pixels = 232 * 184; // 12 tiles of 232 x 184
    let (out, report) = run(&frame, MethodConfig::GradNet(config));
    let note = skipped(&report, "converged");
    println!("gradnet on 640 x 180, right half converged: {note}");
    assert!(right_is_base(&out, &frame, 560));
}

/// Writes the frames of this file as bundles for `gdrecon bench` (docs/skipping.md):
/// `GDR_SKIP_DIR=dir cargo test --release --test skip -- --ignored write_frames`.
#[test]
#[ignore]
fn write_frames() {
    let dir = std::path::PathBuf::from(std::env::var("GDR_SKIP_DIR").expect("GDR_SKIP_DIR"));
    std::fs::create_dir_all(&dir).unwrap();
    let sample = sample();
    // Control: the noisy sample twice, side by side (same size as the others).
    let (w, h) = sample.size();
    let twice =
        |img: &Image| Image::from_fn(img.channels(), 2 * w, h, |(c, x, y)| img.at(c, x % w, y));
    let mut b = FrameBuilder::new().spp(sample.spp());
    for layer in [Layer::Color, Layer::Dx, Layer::Dy, Layer::Variance] {
        b = b.image(layer, twice(sample.layer(layer).unwrap()));
    }
    let control = b.build(Policy::Replace).unwrap();
    for (name, frame) in [
        ("control", control),
        ("half_empty", half_empty(320)),
        ("half_converged", half_converged()),
    ] {
        io::write_bundle(dir.join(format!("{name}.exr")), &frame).unwrap();
    }
}
