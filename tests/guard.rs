//! Never worse than doing nothing: on the guard frames (`tests/data/guard/`: small renders of
//! validation and test families, an HDR-emitter frame and a dim one among them, with 4096 spp
//! references) a reconstruction must have a lower relMSE than the base image it was given.
//!
//! Every method meets it on every guard frame, in every build (the core alone included, where
//! `auto` runs FRGR). The last exceptions, listed as known worse until then: GradNet on
//! `lamps_16spp` and `thin_16spp` (ended by the GPU-trained model, nineteenth session), `auto`
//! where ONNX Runtime can run (twenty-first session: the combiner), `frgr` on `lamps_16spp`
//! (33x its base before edge trimming, thirty-second session; 1.21x after; 0.39x since the
//! feature prefilter runs below 16 spp only, thirty-third session) and with it `auto` in the
//! core alone, and L1 on OIDN's prior there (`auto` without ONNX Runtime: 8.4x; 0.53x since its
//! noise band beside the bulbs' edges, thirty-third session). The tests below the list of
//! methods hold both sides of each of those fixes.

use std::path::{Path, PathBuf};

use gdrecon::{
    io, metrics, Context, ContextOptions, Frame, Method, MethodConfig, Plan, Policy, Progress,
};

/// The methods held to the bar.
const METHODS: [Method; 4] = [
    Method::PoissonL1,
    Method::Frgr,
    Method::GradNet,
    Method::Auto,
];

/// The 16 spp guard frames, then the 64 spp ones (`tests/data/guard/64spp/`: at 64 spp the
/// noise band is trimmed of emitters, `recon/band.rs`; the other suites that read the guard
/// frames keep to the 16 spp ones, whose fixtures they have).
fn guard_frames() -> Vec<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/guard");
    let mut files = Vec::new();
    for dir in [root.clone(), root.join("64spp")] {
        let mut found: Vec<PathBuf> = std::fs::read_dir(&dir)
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|x| x == "exr"))
            .collect();
        found.sort();
        files.extend(found);
    }
    files
}

/// relMSE of `config`'s output on `frame` (which has a reference); the output must be finite.
fn error_of(context: &Context, config: &MethodConfig, frame: &Frame) -> f64 {
    let mut plan = Plan::new(context, config, frame.width(), frame.height()).unwrap();
    let (out, _) = plan.execute(frame, &Progress::none()).unwrap();
    assert!(out.all_finite(), "{config:?}: output is not finite");
    metrics::compare(&out, frame.reference().unwrap())
        .unwrap()
        .rel_mse
}

/// Holds both sides of a fix on guard frame `file`: `config`'s relMSE is under `on_max` times
/// the base's, and with `off` assigned (the fix undone) over `off_min` times it, so that the
/// frame keeps testing the fix.
fn holds_both_sides(config: MethodConfig, file: &str, off: &str, on_max: f64, off_min: f64) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/guard")
        .join(file);
    let context = Context::new(ContextOptions::with_threads(Some(2))).unwrap();
    let mut without = config.clone();
    without.set_assignment(off).unwrap();
    let frame = io::read_bundle(&path, Policy::Replace).unwrap();
    let base = metrics::compare(frame.color(), frame.reference().unwrap())
        .unwrap()
        .rel_mse;
    let (error, undone) = (
        error_of(&context, &config, &frame),
        error_of(&context, &without, &frame),
    );
    let method = config.method();
    eprintln!("{file}: {method} {error:.4e}, {off} {undone:.4e}, base {base:.4e}");
    assert!(
        error < on_max * base,
        "{file}: {method} {error:.4e} against base {base:.4e} (bar {on_max}x)"
    );
    assert!(
        undone > off_min * base,
        "{file}: {method} with {off} {undone:.4e} against base {base:.4e} (bar {off_min}x): \
         the frame no longer needs the fix, so it no longer tests it"
    );
}

/// The 64 spp `lamps` frame is one the band's trimming saves: FRGR with the band untrimmed
/// spreads the bulbs into the dark wood beside them (1.95x the base's relMSE when written,
/// 1.84x since the prefilter stops at 16 spp), trimmed it is 0.27x (0.19x).
#[test]
fn the_trimmed_band_keeps_frgr_under_its_base_beside_bulbs() {
    let frgr = MethodConfig::default_for(Method::Frgr);
    holds_both_sides(frgr, "64spp/lamps_64spp.exr", "band_trim=0", 0.5, 1.0);
}

/// At 16 spp the band is trimmed only of the bulbs' edge pixels that the gradients confirm
/// (`recon/emitters.rs`): on the `lamps` frame that takes FRGR from 33x the base's relMSE to
/// 0.39x when written (1.21x with the feature prefilter).
#[test]
fn trimming_the_bulbs_edges_cuts_frgr_error_at_16_spp() {
    let frgr = MethodConfig::default_for(Method::Frgr);
    holds_both_sides(frgr, "lamps_16spp.exr", "band_emitters=false", 2.0, 10.0);
}

/// The feature prefilter runs below 16 spp only (`frgr`'s `prefilter_below`): on the 16 spp
/// `lamps` frame (a black sphere with small lamps: one albedo, normals that curve) its noise
/// bound blends the sphere's pixels, and FRGR spreads the lamps over it. 0.39x the base's
/// relMSE without it when written, 1.21x with it. Held at the release's 9 x 9 window
/// (`radius=4`), where it was needed: at the default 7 x 7 window (forty-sixth session) FRGR
/// spreads the lamps less, and with the prefilter the frame is at 0.9994x its base (0.40x
/// without), no longer a test of the fix.
#[test]
fn the_prefilter_stops_at_16_spp_and_keeps_frgr_under_its_base_beside_bulbs() {
    let mut frgr = MethodConfig::default_for(Method::Frgr);
    frgr.set_assignment("radius=4").unwrap();
    holds_both_sides(frgr, "lamps_16spp.exr", "prefilter_below=1e9", 0.6, 1.0);
}

/// L1 on OIDN's prior (preset `prior`, `auto`'s path with OIDN and without ONNX Runtime):
/// OIDN spreads the bulbs of the 16 spp `lamps` frame into their dark ring, and the noise band
/// beside the bulbs' edges holds those pixels to the base (0.0528 against the base's 0.0996
/// when written; 0.833 without the band).
#[cfg(feature = "oidn")]
#[test]
fn the_band_beside_edges_keeps_the_prior_path_under_its_base_beside_bulbs() {
    let prior = MethodConfig::preset(Method::PoissonL1, "prior").unwrap();
    holds_both_sides(prior, "lamps_16spp.exr", "noise_band=0", 0.7, 5.0);
}

#[test]
fn methods_beat_the_base_image_on_the_guard_frames() {
    let frames = guard_frames();
    assert!(
        frames.len() >= 5,
        "expected the guard frames, found {frames:?}"
    );
    let context = Context::new(ContextOptions::with_threads(Some(2))).unwrap();
    let mut wrong = Vec::new();
    let mut hdr = false;
    for path in &frames {
        let frame = io::read_bundle(path, Policy::Replace).unwrap();
        let reference = frame.reference().expect("guard frames have a reference");
        hdr |= reference.as_slice().iter().any(|&v| v > 10.0);
        let base = metrics::compare(frame.color(), reference).unwrap().rel_mse;
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        for method in METHODS.into_iter().filter(|m| m.is_built()) {
            let error = error_of(&context, &MethodConfig::default_for(method), &frame);
            eprintln!("{name}: {method} {error:.4e} (base {base:.4e})");
            if error >= base {
                wrong.push(format!("{name}: {method} {error:.4e} >= base {base:.4e}"));
            }
        }
    }
    assert!(
        hdr,
        "no guard frame has reference pixels above 10 (an HDR emitter)"
    );
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}
