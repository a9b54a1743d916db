//! Timing one planned variant on frames, and the process's peak memory.

use std::time::Instant;

use gdrecon::{metrics, Context, Frame, Image, Layer, Plan, Policy, Progress};

use super::frames::BenchFrame;
use super::variant::Variant;

/// One timed variant on one frame: a line of the report.
#[derive(Clone, Debug)]
pub struct Row {
    /// Display name of the frame.
    pub frame: String,
    /// Scene name.
    pub scene: String,
    /// Samples per pixel, when known.
    pub spp: Option<f32>,
    /// Method name.
    pub method: String,
    /// Variant setting (`default`, `reweight_steps=5`).
    pub setting: String,
    /// Variant label (`l1`, `l1:reweight_steps=5`).
    pub variant: String,
    /// Size factor against the frame as read.
    pub scale: f64,
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Worker threads.
    pub threads: usize,
    /// Timed runs.
    pub runs: usize,
    /// Median seconds per run.
    pub median_s: f64,
    /// Fastest run.
    pub min_s: f64,
    /// Slowest run.
    pub max_s: f64,
    /// relMSE against the frame's reference (original size only).
    pub rel_mse: Option<f64>,
    /// Peak resident memory since the variant started, MiB.
    pub peak_rss_mib: Option<f64>,
    /// Median seconds of each stage the method's report times, in execution order.
    pub stages: StageMedians,
    /// Median seconds of Open Image Denoise on the same frame, run alternately with this
    /// variant (`bench --against-oidn`), so that both medians saw the same load.
    pub oidn_s: Option<f64>,
}

/// `(stage name, median seconds)` in execution order.
pub type StageMedians = Vec<(String, f64)>;

impl Row {
    /// Pixels per frame.
    pub fn pixels(&self) -> usize {
        self.width * self.height
    }
}

/// How many runs to do.
#[derive(Clone, Copy, Debug)]
pub struct Schedule {
    /// Untimed runs first.
    pub warmup: usize,
    /// Timed runs.
    pub runs: usize,
}

/// How a variant's runs stand to Open Image Denoise's (`bench --against-oidn`).
#[derive(Clone, Copy)]
pub enum Against<'a> {
    /// No OIDN runs.
    Nothing,
    /// The variant is OIDN's own.
    Itself,
    /// A run of OIDN's variant before each run of the variant.
    Beside(&'a Variant),
}

/// Plans `variant` once per frame size (not timed) and times it on every frame. Beside Open
/// Image Denoise's variant (`against`), a plan of it runs before each run of `variant`, timed
/// too (`Row::oidn_s`); the row's peak memory then includes OIDN's plan. OIDN's runs, its own
/// variant's included, see each frame without a `prior` layer: given one, the `prior` method
/// returns it as is and OIDN would not be timed at all.
///
/// `on_row` receives each row as soon as it is measured (for live printing).
pub fn time_variant(
    context: &Context,
    variant: &Variant,
    against: Against,
    frames: &[BenchFrame],
    schedule: Schedule,
    on_row: &mut dyn FnMut(&Row),
) -> gdrecon::Result<Vec<Row>> {
    reset_peak_rss();
    let mut rows = Vec::with_capacity(frames.len());
    for size in distinct_sizes(frames) {
        let mut plan = Plan::new(context, &variant.config, size.0, size.1)?;
        let mut oidn = match against {
            Against::Beside(o) => Some(Plan::new(context, &o.config, size.0, size.1)?),
            _ => None,
        };
        let mut out = Image::zeros(3, size.0, size.1);
        for f in frames.iter().filter(|f| f.frame.size() == size) {
            let bare = match (f.frame.prior(), against) {
                (Some(_), Against::Itself | Against::Beside(_)) => Some(
                    f.frame
                        .clone()
                        .into_builder()
                        .without(Layer::Prior)
                        .build(Policy::Replace)?,
                ),
                _ => None,
            };
            let oidn_input = bare.as_ref().unwrap_or(&f.frame);
            let input = match against {
                Against::Itself => oidn_input,
                _ => &f.frame,
            };
            let oidn = oidn.as_mut().map(|plan| (plan, oidn_input));
            let (times, stages, oidn_s) = time_runs(&mut plan, oidn, input, &mut out, schedule)?;
            let rel_mse = match (f.frame.reference(), f.scale == 1.0) {
                (Some(r), true) => Some(metrics::compare(&out, r)?.rel_mse),
                _ => None,
            };
            let mut row = make_row(variant, f, context.threads(), &times, rel_mse);
            row.stages = stages;
            row.oidn_s = oidn_s;
            on_row(&row);
            rows.push(row);
        }
    }
    Ok(rows)
}

/// The frame sizes in first-seen order.
fn distinct_sizes(frames: &[BenchFrame]) -> Vec<(usize, usize)> {
    let mut sizes: Vec<(usize, usize)> = Vec::new();
    for f in frames {
        if !sizes.contains(&f.frame.size()) {
            sizes.push(f.frame.size());
        }
    }
    sizes
}

/// Warm-up runs, then the timed runs' seconds on `frame`, sorted, the median of each stage,
/// and the median of `oidn`'s runs (a plan and its input), one before each timed run.
fn time_runs(
    plan: &mut Plan,
    mut oidn: Option<(&mut Plan, &Frame)>,
    frame: &Frame,
    out: &mut Image,
    schedule: Schedule,
) -> gdrecon::Result<(Vec<f64>, StageMedians, Option<f64>)> {
    for _ in 0..schedule.warmup {
        if let Some((o, input)) = oidn.as_mut() {
            o.execute_into(input, out, &Progress::none())?;
        }
        plan.execute_into(frame, out, &Progress::none())?;
    }
    let mut times = Vec::with_capacity(schedule.runs);
    let mut oidn_times = Vec::with_capacity(schedule.runs);
    let mut stages: Vec<(String, Vec<f64>)> = Vec::new();
    for _ in 0..schedule.runs {
        if let Some((o, input)) = oidn.as_mut() {
            let t = Instant::now();
            o.execute_into(input, out, &Progress::none())?;
            oidn_times.push(t.elapsed().as_secs_f64());
        }
        let t = Instant::now();
        let report = plan.execute_into(frame, out, &Progress::none())?;
        times.push(t.elapsed().as_secs_f64());
        for stage in &report.stages {
            let secs = stage.time.as_secs_f64();
            match stages.iter_mut().find(|(name, _)| *name == stage.name) {
                Some((_, v)) => v.push(secs),
                None => stages.push((stage.name.clone(), vec![secs])),
            }
        }
    }
    times.sort_by(f64::total_cmp);
    oidn_times.sort_by(f64::total_cmp);
    let oidn_s = (!oidn_times.is_empty()).then(|| median(&oidn_times));
    let stages = stages
        .into_iter()
        .map(|(name, mut v)| {
            v.sort_by(f64::total_cmp);
            (name, median(&v))
        })
        .collect();
    Ok((times, stages, oidn_s))
}

/// A report row from sorted run times.
fn make_row(
    variant: &Variant,
    f: &BenchFrame,
    threads: usize,
    times: &[f64],
    rel_mse: Option<f64>,
) -> Row {
    Row {
        frame: f.name.clone(),
        scene: f.scene.clone(),
        spp: f.spp,
        method: variant.method.clone(),
        setting: variant.setting.clone(),
        variant: variant.label(),
        scale: f.scale,
        width: f.frame.width(),
        height: f.frame.height(),
        threads,
        runs: times.len(),
        median_s: median(times),
        min_s: times[0],
        max_s: times[times.len() - 1],
        rel_mse,
        peak_rss_mib: peak_rss_mib(),
        stages: Vec::new(),
        oidn_s: None,
    }
}

/// The median of sorted values (upper middle for an even count, as `bench` always reported).
pub fn median(sorted: &[f64]) -> f64 {
    sorted[sorted.len() / 2]
}

/// Peak resident memory of this process in MiB (Linux), if known.
pub fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// Resets the peak to the current resident size (Linux 4.0+: `5` to `/proc/self/clear_refs`),
/// so each variant's peak is its own, plus the frames already in memory. Where that fails the
/// peak stays the process's high-water mark.
pub fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}
