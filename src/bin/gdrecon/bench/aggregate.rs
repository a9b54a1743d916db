//! Per-spp aggregates over scenes and the Pareto front, shared by the summary and the plot.

use super::measure::Row;

/// One variant at one spp, over the scenes.
#[derive(Clone, Debug)]
pub struct Point {
    /// Variant label.
    pub variant: String,
    /// Method name (for colours).
    pub method: String,
    /// Geometric mean of relMSE over the frames.
    pub rel_mse: f64,
    /// Median over the frames of each frame's median seconds.
    pub seconds: f64,
    /// Frames (scenes) averaged.
    pub frames: usize,
    /// The largest relMSE over the frames, and its frame.
    pub worst: (f64, String),
    /// Not a variant of ours (`bench --baselines`): never marked Pareto, never plotted.
    pub baseline: bool,
    /// Median over the frames of this variant's time over OIDN's on the same frame (variant
    /// [`OIDN`] in the same run), when it was timed.
    pub times_oidn: Option<f64>,
    /// No other variant is at least as good in both and better in one.
    pub pareto: bool,
}

/// All variants at one spp, sorted by relMSE.
#[derive(Clone, Debug)]
pub struct Panel {
    /// Samples per pixel.
    pub spp: f32,
    /// The variants.
    pub points: Vec<Point>,
}

/// The variant that is Open Image Denoise alone (`bench --against-oidn` times it first).
pub const OIDN: &str = "prior";

/// The median over `of`'s frames (and scales) of its seconds over OIDN's on the same frame
/// and scale: OIDN's runs interleaved with the row's (`Row::oidn_s`) when there are any, else
/// OIDN's own row in `all`; `None` when OIDN was not timed on any of them, or `of` is a
/// baseline.
pub fn times_oidn(of: &[&Row], all: &[Row]) -> Option<f64> {
    let mut ratios: Vec<f64> = of
        .iter()
        .filter(|r| r.method != super::baseline::METHOD)
        .filter_map(|r| {
            let oidn = r.oidn_s.or_else(|| {
                all.iter()
                    .find(|o| o.variant == OIDN && o.frame == r.frame && o.scale == r.scale)
                    .map(|o| o.median_s)
            })?;
            (oidn > 0.0).then(|| r.median_s / oidn)
        })
        .collect();
    ratios.sort_by(f64::total_cmp);
    (!ratios.is_empty()).then(|| middle(&ratios))
}

/// Groups the original-size rows with a relMSE and a known spp by spp (ascending).
pub fn panels(rows: &[Row]) -> Vec<Panel> {
    let usable: Vec<&Row> = rows
        .iter()
        .filter(|r| r.scale == 1.0 && r.rel_mse.is_some() && r.spp.is_some())
        .collect();
    let mut spps: Vec<f32> = usable.iter().filter_map(|r| r.spp).collect();
    spps.sort_by(f32::total_cmp);
    spps.dedup();
    spps.into_iter()
        .map(|spp| {
            let at_spp: Vec<&Row> = usable
                .iter()
                .copied()
                .filter(|r| r.spp == Some(spp))
                .collect();
            Panel {
                spp,
                points: points(&at_spp, rows),
            }
        })
        .collect()
}

/// One point per variant (in first-seen order), marked and sorted by relMSE; `all` holds the
/// OIDN rows their times are compared with.
fn points(rows: &[&Row], all: &[Row]) -> Vec<Point> {
    let mut variants: Vec<&str> = Vec::new();
    for r in rows {
        if !variants.contains(&r.variant.as_str()) {
            variants.push(&r.variant);
        }
    }
    let mut points: Vec<Point> = variants
        .into_iter()
        .map(|v| {
            let of: Vec<&Row> = rows.iter().copied().filter(|r| r.variant == v).collect();
            let errors: Vec<f64> = of.iter().filter_map(|r| r.rel_mse).collect();
            let worst = of
                .iter()
                .filter_map(|r| Some((r.rel_mse?, r.frame.clone())))
                .max_by(|a, b| a.0.total_cmp(&b.0))
                .unwrap_or((f64::NAN, String::new()));
            let mut secs: Vec<f64> = of.iter().map(|r| r.median_s).collect();
            secs.sort_by(f64::total_cmp);
            Point {
                variant: v.to_owned(),
                method: of[0].method.clone(),
                rel_mse: geometric_mean(&errors),
                seconds: middle(&secs),
                frames: of.len(),
                worst,
                baseline: of[0].method == super::baseline::METHOD,
                times_oidn: times_oidn(&of, all),
                pareto: false,
            }
        })
        .collect();
    mark_pareto(&mut points);
    points.sort_by(|a, b| a.rel_mse.total_cmp(&b.rel_mse));
    points
}

/// Geometric mean of positive values (0 if any is 0).
pub fn geometric_mean(values: &[f64]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    (values.iter().map(|v| v.ln()).sum::<f64>() / values.len() as f64).exp()
}

/// The median of sorted values (mean of the two middle ones for an even count).
pub fn middle(sorted: &[f64]) -> f64 {
    let n = sorted.len();
    if n == 0 {
        f64::NAN
    } else if n % 2 == 1 {
        sorted[n / 2]
    } else {
        0.5 * (sorted[n / 2 - 1] + sorted[n / 2])
    }
}

/// Marks the variants that no other variant dominates (lower or equal error and time, one
/// lower); baselines take no part.
pub fn mark_pareto(points: &mut [Point]) {
    let dominated: Vec<bool> = points
        .iter()
        .map(|p| {
            p.baseline
                || points.iter().filter(|q| !q.baseline).any(|q| {
                    q.rel_mse <= p.rel_mse
                        && q.seconds <= p.seconds
                        && (q.rel_mse < p.rel_mse || q.seconds < p.seconds)
                })
        })
        .collect();
    for (p, d) in points.iter_mut().zip(dominated) {
        p.pareto = !d;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(name: &str, rel_mse: f64, seconds: f64) -> Point {
        Point {
            variant: name.into(),
            method: name.into(),
            rel_mse,
            seconds,
            frames: 1,
            worst: (rel_mse, name.into()),
            baseline: false,
            times_oidn: None,
            pareto: false,
        }
    }

    #[test]
    fn pareto_front_keeps_the_undominated() {
        let mut p = vec![
            point("fast", 3.0, 0.1),
            point("good", 1.0, 5.0),
            point("slow-bad", 3.0, 6.0),
            point("middle", 2.0, 1.0),
            point("tie-worse", 2.0, 1.5),
        ];
        mark_pareto(&mut p);
        let front: Vec<&str> = p
            .iter()
            .filter(|p| p.pareto)
            .map(|p| p.variant.as_str())
            .collect();
        assert_eq!(front, ["fast", "good", "middle"]);
    }

    #[test]
    fn means() {
        assert!((geometric_mean(&[1e-2, 1e-4]) - 1e-3).abs() < 1e-12);
        assert_eq!(middle(&[1.0, 2.0, 4.0, 8.0]), 3.0);
    }
}
