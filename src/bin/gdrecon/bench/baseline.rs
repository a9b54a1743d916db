//! `--baselines`: rows for what a renderer would do without gdrecon, beside the variants.
//!
//! - `base`: the frame's own base image (doing nothing); time 0.
//! - `oidn`: Intel Open Image Denoise on the base image at the same spp.
//! - `oidn:equal-time`: OIDN on a plain path-traced render of the frame at 2x the spp (a
//!   gradient-domain sample costs about two primal samples), the equal-render-time yardstick.
//!
//! The OIDN images are computed beforehand by `python -m gdrecon_py.oidn <folder>` (OIDN
//! 2.5.1 through PyPI `pyoidn`: RT filter, hdr, quality high, albedo + normal), which writes
//! `<folder>/oidn/<stem>.exr`, `<folder>/oidn-equal-time/<stem>.exr` and the same-spp filter's
//! seconds in `<folder>/oidn/timings.json`; the equal-time row reuses that time (same image
//! size, same filter). relMSE is computed here, by the same metric as every other row.

use std::path::Path;

use gdrecon::{io, metrics, Image};

use super::frames::BenchFrame;
use super::measure::Row;

/// Method name of every baseline row (so no plot colour or Pareto mark is given to them).
pub const METHOD: &str = "baseline";

/// The baseline rows of the original-size frames that have a reference: `base` always,
/// the OIDN rows where their images exist. Missing OIDN images are said once per folder.
pub fn rows(frames: &[BenchFrame], threads: usize) -> gdrecon::Result<Vec<Row>> {
    let mut rows = Vec::new();
    let mut warned: Vec<std::path::PathBuf> = Vec::new();
    for f in frames.iter().filter(|f| f.scale == 1.0) {
        let Some(reference) = f.frame.reference() else {
            continue;
        };
        rows.push(row(f, "base", f.frame.color(), reference, 0.0, threads)?);
        let Some(path) = &f.path else { continue };
        let (dir, stem) = match (path.parent(), path.file_stem()) {
            (Some(d), Some(s)) => (d, s.to_string_lossy().into_owned()),
            _ => continue,
        };
        let seconds = timing(&dir.join("oidn").join("timings.json"), &stem).unwrap_or(f64::NAN);
        for (label, sub) in [("oidn", "oidn"), ("oidn:equal-time", "oidn-equal-time")] {
            let file = dir.join(sub).join(format!("{stem}.exr"));
            if !file.exists() {
                if !warned.iter().any(|d| d == dir) {
                    say!(
                        "bench: no {} (run: python -m gdrecon_py.oidn {})",
                        file.display(),
                        dir.display()
                    );
                    warned.push(dir.to_owned());
                }
                continue;
            }
            let image = io::exr::read_rgb(&file)?;
            rows.push(row(f, label, &image, reference, seconds, threads)?);
        }
    }
    Ok(rows)
}

/// One baseline row.
fn row(
    f: &BenchFrame,
    label: &str,
    image: &Image,
    reference: &Image,
    seconds: f64,
    threads: usize,
) -> gdrecon::Result<Row> {
    let rel_mse = metrics::compare(image, reference)
        .map_err(|e| gdrecon::Error::InvalidInput(format!("{label} of {}: {e}", f.name)))?
        .rel_mse;
    Ok(Row {
        frame: f.name.clone(),
        scene: f.scene.clone(),
        spp: f.spp,
        method: METHOD.to_owned(),
        setting: label.to_owned(),
        variant: label.to_owned(),
        scale: 1.0,
        width: f.frame.width(),
        height: f.frame.height(),
        threads,
        runs: 0,
        median_s: seconds,
        min_s: seconds,
        max_s: seconds,
        rel_mse: Some(rel_mse),
        peak_rss_mib: None,
        stages: Vec::new(),
        oidn_s: None,
    })
}

/// The seconds recorded for `stem` in a `timings.json` (`{"stem": seconds, ...}`).
fn timing(path: &Path, stem: &str) -> Option<f64> {
    let text = std::fs::read_to_string(path).ok()?;
    let key = format!("\"{stem}\"");
    let rest = &text[text.find(&key)? + key.len()..];
    let rest = rest.trim_start().strip_prefix(':')?.trim_start();
    let end = rest.find([',', '}', '\n']).unwrap_or(rest.len());
    rest[..end].trim().parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn timings_are_read_by_stem() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("timings.json");
        std::fs::write(&p, "{\n \"a_4spp\": 0.25,\n \"a_16spp\": 1.5\n}").unwrap();
        assert_eq!(timing(&p, "a_4spp"), Some(0.25));
        assert_eq!(timing(&p, "a_16spp"), Some(1.5));
        assert_eq!(timing(&p, "a_64spp"), None);
    }
}
