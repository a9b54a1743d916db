//! `summary.md`: per-spp geometric means with the Pareto front, every row, and the scaling.

use std::fmt::Write as _;

use super::aggregate::Panel;
use super::cpu;
use super::measure::Row;

/// What the summary says about how it was made.
pub struct Header {
    /// The heading.
    pub title: String,
    /// The command line, frames abbreviated.
    pub command: String,
    /// Worker threads.
    pub threads: usize,
    /// Timed runs per variant and frame.
    pub runs: usize,
    /// Untimed runs first.
    pub warmup: usize,
    /// The machine's load average when timing started (other processes share the cores).
    pub load_before: Option<String>,
    /// The load average when timing ended.
    pub load_after: Option<String>,
}

/// The whole `summary.md`.
pub fn markdown(header: &Header, rows: &[Row], panels: &[Panel]) -> String {
    let mut out = String::new();
    intro(&mut out, header);
    for panel in panels {
        panel_table(&mut out, panel);
    }
    family_tables(&mut out, rows, panels);
    frame_table(&mut out, rows);
    scaling_table(&mut out, rows);
    out
}

/// Title and how the numbers were taken.
fn intro(out: &mut String, h: &Header) {
    let _ = writeln!(out, "# {}\n", h.title);
    let _ = writeln!(out, "```\n{}\n```\n", h.command);
    let _ = writeln!(
        out,
        "{} UTC, {}, {} worker threads. Each variant is planned once per frame size (not \
         timed), then run {} time(s) untimed and {} time(s) timed per frame; seconds are the \
         median run. relMSE is against the frame's reference. Peak MiB is the process's \
         resident high-water mark since the variant started (it includes every frame loaded). \
         Load average (1, 5, 15 min) before: {}, after: {}.\n",
        utc_now(),
        cpu::describe(),
        h.threads,
        h.warmup,
        h.runs,
        h.load_before.as_deref().unwrap_or("unknown"),
        h.load_after.as_deref().unwrap_or("unknown")
    );
}

/// One spp: geometric means over the scenes, best first.
fn panel_table(out: &mut String, panel: &Panel) {
    let frames = panel.points.iter().map(|p| p.frames).max().unwrap_or(0);
    let _ = writeln!(
        out,
        "## {} spp: geometric mean over {frames} frame(s)\n",
        panel.spp
    );
    let against_oidn = panel.points.iter().any(|p| p.times_oidn.is_some());
    let _ = writeln!(
        out,
        "| variant | relMSE (geo. mean) | worst frame | median s |{} Pareto |\n\
         | --- | --- | --- | --- |{} --- |",
        if against_oidn {
            " x OIDN (this run) |"
        } else {
            ""
        },
        if against_oidn { " --- |" } else { "" }
    );
    for p in &panel.points {
        let mark = if p.pareto { "**yes**" } else { "" };
        // Baselines in italics: not ours, timed elsewhere (or not at all).
        let name = if p.baseline {
            format!("_{}_", p.variant)
        } else {
            format!("`{}`", p.variant)
        };
        let ratio = match (against_oidn, p.times_oidn) {
            (false, _) => String::new(),
            (true, Some(x)) => format!(" {x:.3} |"),
            (true, None) => " - |".to_owned(),
        };
        let _ = writeln!(
            out,
            "| {name} | {:.4e} | {:.4e} ({}) | {} |{ratio} {mark} |",
            p.rel_mse,
            p.worst.0,
            p.worst.1,
            if p.seconds.is_nan() {
                "-".to_owned()
            } else {
                seconds(p.seconds)
            }
        );
    }
    out.push('\n');
}

/// One table per spp: relMSE per family (scene) and variant, variants in the panel's order.
fn family_tables(out: &mut String, rows: &[Row], panels: &[Panel]) {
    for panel in panels {
        let at: Vec<&Row> = rows
            .iter()
            .filter(|r| r.scale == 1.0 && r.spp == Some(panel.spp) && r.rel_mse.is_some())
            .collect();
        let mut scenes: Vec<&str> = Vec::new();
        for r in &at {
            if !scenes.contains(&r.scene.as_str()) {
                scenes.push(&r.scene);
            }
        }
        if scenes.len() < 2 {
            continue;
        }
        let _ = writeln!(
            out,
            "## {} spp per family (relMSE)\n\n| variant | {} |\n|{}",
            panel.spp,
            scenes.join(" | "),
            " --- |".repeat(scenes.len() + 1)
        );
        for p in &panel.points {
            let cells: Vec<String> = scenes
                .iter()
                .map(|s| {
                    let errors: Vec<f64> = at
                        .iter()
                        .filter(|r| r.variant == p.variant && r.scene == *s)
                        .filter_map(|r| r.rel_mse)
                        .collect();
                    if errors.is_empty() {
                        "-".to_owned()
                    } else {
                        format!("{:.3e}", super::aggregate::geometric_mean(&errors))
                    }
                })
                .collect();
            let _ = writeln!(out, "| `{}` | {} |", p.variant, cells.join(" | "));
        }
        out.push('\n');
    }
}

/// Every measured row.
fn frame_table(out: &mut String, rows: &[Row]) {
    let _ = writeln!(out, "## Per frame\n");
    let _ = writeln!(
        out,
        "| frame | variant | size | median s | min s | max s | relMSE | peak MiB |\n\
         | --- | --- | --- | --- | --- | --- | --- | --- |"
    );
    for r in rows {
        let _ = writeln!(
            out,
            "| {} | `{}` | {} x {} | {} | {} | {} | {} | {} |",
            r.frame,
            r.variant,
            r.width,
            r.height,
            seconds(r.median_s),
            seconds(r.min_s),
            seconds(r.max_s),
            r.rel_mse
                .map_or_else(|| "-".to_owned(), |v| format!("{v:.4e}")),
            r.peak_rss_mib
                .map_or_else(|| "-".to_owned(), |v| format!("{v:.0}"))
        );
    }
    out.push('\n');
}

/// Median seconds of each variant and frame at each scale, with the fitted exponent of
/// `seconds ~ pixels^k`; nothing when only one scale was timed.
fn scaling_table(out: &mut String, rows: &[Row]) {
    let mut scales: Vec<f64> = rows.iter().map(|r| r.scale).collect();
    scales.sort_by(f64::total_cmp);
    scales.dedup();
    if scales.len() < 2 {
        return;
    }
    let _ = writeln!(
        out,
        "## Resolution scaling\n\nFrames resized nearest-neighbour (gradients re-derived from \
         the source gradients, noise kept; the synthetic frame is rendered anew at each size); \
         cells: median seconds (nanoseconds per pixel), and with `--against-oidn` the time as \
         a multiple of OIDN's runs interleaved with it (OIDN itself is the variant `prior`). \
         `k` fits seconds ~ pixels^k over the scales timed; `scaling.png` plots the same.\n"
    );
    let head: Vec<String> = scales.iter().map(|s| format!("{s}x")).collect();
    let _ = writeln!(
        out,
        "| variant | frame | {} | k |\n|{}",
        head.join(" | "),
        " --- |".repeat(scales.len() + 3)
    );
    for (variant, frame) in groups(rows) {
        let of: Vec<&Row> = rows
            .iter()
            .filter(|r| r.variant == variant && r.frame == frame)
            .collect();
        let cells: Vec<String> = scales
            .iter()
            .map(|s| match of.iter().find(|r| r.scale == *s) {
                Some(r) => format!(
                    "{} x {}: {} ({:.0}){}",
                    r.width,
                    r.height,
                    seconds(r.median_s),
                    r.median_s * 1e9 / r.pixels() as f64,
                    r.oidn_s
                        .filter(|o| *o > 0.0)
                        .map_or_else(String::new, |o| format!(", {:.2}x OIDN", r.median_s / o))
                ),
                None => "-".to_owned(),
            })
            .collect();
        let k = exponent(&of).map_or_else(|| "-".to_owned(), |k| format!("{k:.2}"));
        let _ = writeln!(
            out,
            "| `{variant}` | {frame} | {} | {k} |",
            cells.join(" | ")
        );
    }
    out.push('\n');
}

/// Distinct (variant, frame) pairs in first-seen order.
pub fn groups(rows: &[Row]) -> Vec<(String, String)> {
    let mut seen: Vec<(String, String)> = Vec::new();
    for r in rows {
        let key = (r.variant.clone(), r.frame.clone());
        if !seen.contains(&key) {
            seen.push(key);
        }
    }
    seen
}

/// Least-squares slope of log seconds against log pixels (needs two sizes).
fn exponent(rows: &[&Row]) -> Option<f64> {
    let pts: Vec<(f64, f64)> = rows
        .iter()
        .map(|r| ((r.pixels() as f64).ln(), r.median_s.ln()))
        .collect();
    let n = pts.len() as f64;
    let mx = pts.iter().map(|p| p.0).sum::<f64>() / n;
    let my = pts.iter().map(|p| p.1).sum::<f64>() / n;
    let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    (pts.len() >= 2 && sxx > 0.0).then(|| sxy / sxx)
}

/// Seconds with 3 significant digits (at least 4 decimals below 0.1 s).
pub fn seconds(s: f64) -> String {
    if s >= 10.0 {
        format!("{s:.1}")
    } else if s >= 0.1 {
        format!("{s:.3}")
    } else {
        format!("{s:.4}")
    }
}

/// The 1, 5 and 15 minute load averages (Linux), e.g. `1.02 0.87 0.55`.
pub fn load_average() -> Option<String> {
    let text = std::fs::read_to_string("/proc/loadavg").ok()?;
    let fields: Vec<&str> = text.split_whitespace().take(3).collect();
    (fields.len() == 3).then(|| fields.join(" "))
}

/// The current UTC date and time, `YYYY-MM-DD HH:MM`.
fn utc_now() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let (days, rest) = ((secs / 86_400) as i64, secs % 86_400);
    let (y, m, d) = civil_from_days(days);
    format!(
        "{y:04}-{m:02}-{d:02} {:02}:{:02}",
        rest / 3600,
        (rest % 3600) / 60
    )
}

/// Proleptic Gregorian date of a day count since 1970-01-01 (H. Hinnant's algorithm).
fn civil_from_days(z: i64) -> (i64, u32, u32) {
    let z = z + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    let y = yoe + era * 400 + i64::from(m <= 2);
    (y, m, d)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dates() {
        assert_eq!(civil_from_days(0), (1970, 1, 1));
        assert_eq!(civil_from_days(19_782), (2024, 2, 29));
    }
}
