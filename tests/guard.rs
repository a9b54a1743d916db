//! Never worse than doing nothing: on the guard frames (`tests/data/guard/`: small renders of
//! validation and test families, an HDR-emitter frame and a dim one among them, with 4096 spp
//! references) a reconstruction must have a lower relMSE than the base image it was given.
//!
//! Not every method meets that yet. The pairs that do not are listed in [`KNOWN_WORSE`], and
//! the test holds both sides: every other pair must beat the base, and every listed pair must
//! still fail (so a fix has to strike it from the list, and the list cannot go stale).

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

/// (frame, method) pairs measured worse than their input (relMSE at the time of writing, base
/// in brackets). Bulbs in view break FRGR, whose published pre-processing assumes radiance in
/// [0, 1]. Issue "Accurate on scenes it was never tuned on" tracks it.
/// GradNet's two failures ended with the GPU-trained model (fp32, the default): `lamps_16spp`
/// 0.0795 against the base's 0.0996 (0.372 before; 0.177 with `precision=int8`), `thin_16spp`
/// (sub-pixel wires) 0.0080 against 0.0181 (0.0334 before). `auto`'s ended where ONNX Runtime
/// can run (twenty-first session): with OIDN it takes the combiner, `lamps_16spp` 0.0858, and
/// without OIDN GradNet (0.0795); see [`KNOWN_WORSE_CORE_ALONE`].
const KNOWN_WORSE: &[(&str, &str)] = &[
    // 0.121 (0.0996); 3.31 without trimming the bulbs' edges, 3.39 without the noise band
    ("lamps_16spp.exr", "frgr"),
];

/// The same for a build with neither ONNX Runtime nor OIDN (cargo features `gradnet` and
/// `oidn` off: the core alone), where `auto` has no prior and no GradNet and takes FRGR, whose
/// entry is above. With OIDN and without ONNX Runtime it takes L1 on the prior, which beats
/// the base since the noise band holds the bulbs' dark ring (thirty-third session: 0.0528;
/// 0.833 before).
const KNOWN_WORSE_CORE_ALONE: &[(&str, &str)] = &[("lamps_16spp.exr", "auto")];

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

/// `config`'s relMSE on guard frame `file`, with `off` assigned, and the base's.
fn with_and_without(config: MethodConfig, file: &str, off: &str) -> (f64, f64, f64) {
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
    let (error, error_off) = (
        error_of(&context, &config, &frame),
        error_of(&context, &without, &frame),
    );
    eprintln!(
        "{file}: {} {error:.4e}, {off} {error_off:.4e}, base {base:.4e}",
        config.method()
    );
    (error, error_off, base)
}

/// FRGR's relMSE on guard frame `file` at its defaults, with `off` assigned, and the base's.
fn frgr_with_and_without(file: &str, off: &str) -> (f64, f64, f64) {
    with_and_without(MethodConfig::default_for(Method::Frgr), file, off)
}

/// The 64 spp `lamps` frame is one the band's trimming saves: FRGR with the band untrimmed
/// spreads the bulbs into the dark wood beside them (1.95x the base's relMSE when written),
/// trimmed it is 0.27x. Both sides are held, so the frame keeps testing the trimming.
#[test]
fn the_trimmed_band_keeps_frgr_under_its_base_beside_bulbs() {
    let (error, untrimmed, base) = frgr_with_and_without("64spp/lamps_64spp.exr", "band_trim=0");
    assert!(
        error < 0.5 * base,
        "trimmed: {error:.4e} against base {base:.4e}"
    );
    assert!(
        untrimmed > base,
        "untrimmed: {untrimmed:.4e} against base {base:.4e}: the frame no longer needs \
         the trimming, so it no longer tests it"
    );
}

/// At 16 spp the band is trimmed only of the bulbs' edge pixels that the gradients confirm
/// (`recon/emitters.rs`): on the `lamps` frame that takes FRGR from 33x the base's relMSE to
/// 1.21x when written (still over it: [`KNOWN_WORSE`]). Both sides are held.
#[test]
fn trimming_the_bulbs_edges_cuts_frgr_error_at_16_spp() {
    let (error, untrimmed, base) = frgr_with_and_without("lamps_16spp.exr", "band_emitters=false");
    assert!(
        error < 2.0 * base,
        "edges trimmed: {error:.4e} against base {base:.4e}"
    );
    assert!(
        untrimmed > 10.0 * base,
        "edges kept: {untrimmed:.4e} against base {base:.4e}: the frame no longer needs \
         the edge trimming, so it no longer tests it"
    );
}

/// L1 on OIDN's prior (preset `prior`, `auto`'s path with OIDN and without ONNX Runtime):
/// OIDN spreads the bulbs of the 16 spp `lamps` frame into their dark ring, and the noise band
/// beside the bulbs' edges holds those pixels to the base (0.0528 against the base's 0.0996
/// when written; 0.833 without the band). Both sides are held.
#[cfg(feature = "oidn")]
#[test]
fn the_band_beside_edges_keeps_the_prior_path_under_its_base_beside_bulbs() {
    let prior = MethodConfig::preset(Method::PoissonL1, "prior").unwrap();
    let (error, off, base) = with_and_without(prior, "lamps_16spp.exr", "noise_band=0");
    assert!(
        error < 0.7 * base,
        "band beside edges: {error:.4e} against base {base:.4e}"
    );
    assert!(
        off > 5.0 * base,
        "no band: {off:.4e} against base {base:.4e}: the frame no longer needs the band, so \
         it no longer tests it"
    );
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
            let pair = (name.as_str(), method.name());
            let known = KNOWN_WORSE.contains(&pair)
                || (!cfg!(feature = "gradnet")
                    && !cfg!(feature = "oidn")
                    && KNOWN_WORSE_CORE_ALONE.contains(&pair));
            match (error < base, known) {
                (false, false) => wrong.push(format!("{name}: {method} {error:.4e} >= base {base:.4e}")),
                (true, true) => wrong.push(format!(
                    "{name}: {method} {error:.4e} now beats base {base:.4e}: strike it from KNOWN_WORSE"
                )),
                _ => {}
            }
        }
    }
    assert!(
        hdr,
        "no guard frame has reference pixels above 10 (an HDR emitter)"
    );
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}
