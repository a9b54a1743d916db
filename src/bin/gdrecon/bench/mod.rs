//! `gdrecon bench`: median run time (and relMSE when a reference exists) per method and frame.
//!
//! Planning (DCT plans, buffers) is done once per method and size and not timed, as a renderer
//! would commit once and execute per frame. Times are medians over `--runs` executions after
//! `--warmup` untimed ones; peak memory is the process's resident high-water mark (VmHWM)
//! after the method ran, so run one method per process for per-method peaks.

use std::path::PathBuf;
use std::time::Instant;

use clap::Args;

use gdrecon::{metrics, synth, Context, ContextOptions, Frame, Plan, Policy, Progress};

use crate::MethodArgs;

#[derive(Args)]
pub struct BenchArgs {
    /// Frame bundles to time (any number).
    inputs: Vec<PathBuf>,
    /// Also time a synthetic frame of this size, e.g. 1280x720.
    #[arg(long)]
    synthetic: Option<String>,
    /// Comma-separated methods.
    #[arg(long, default_value = "l2,l1")]
    methods: String,
    /// Timed runs per method and frame (the median is reported).
    #[arg(long, default_value_t = 7)]
    runs: usize,
    /// Untimed runs first.
    #[arg(long, default_value_t = 1)]
    warmup: usize,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Write the table as CSV here too.
    #[arg(long)]
    csv: Option<PathBuf>,
    #[command(flatten)]
    method: MethodArgs,
}

fn parse_size(s: &str) -> gdrecon::Result<(usize, usize)> {
    let bad = || gdrecon::Error::InvalidArgument(format!("--synthetic '{s}': expected WxH"));
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    let (w, h) = (w.parse().map_err(|_| bad())?, h.parse().map_err(|_| bad())?);
    if w == 0 || h == 0 {
        return Err(bad());
    }
    Ok((w, h))
}

/// Peak resident memory of this process in MiB (Linux), if known.
pub fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

pub fn run(args: BenchArgs) -> gdrecon::Result<()> {
    if args.runs == 0 {
        return Err(gdrecon::Error::InvalidArgument(
            "--runs must be at least 1".into(),
        ));
    }
    let mut frames: Vec<(String, Frame)> = Vec::new();
    for p in &args.inputs {
        frames.push((
            p.display().to_string(),
            crate::load_frame(p, Policy::Replace, None)?,
        ));
    }
    if let Some(s) = &args.synthetic {
        let (w, h) = parse_size(s)?;
        frames.push((
            format!("synthetic {w}x{h}"),
            synth::synthetic_frame(w, h, 16.0, 1),
        ));
    }
    if frames.is_empty() {
        return Err(gdrecon::Error::InvalidArgument(
            "nothing to time: give frame bundles or --synthetic WxH".into(),
        ));
    }
    let context = Context::new(ContextOptions {
        threads: args.threads,
    })?;
    let mut rows = vec![
        "frame,method,width,height,threads,runs,median_s,min_s,max_s,rel_mse,peak_rss_mib"
            .to_owned(),
    ];
    say!(
        "{:<28} {:<6} {:>10} {:>10} {:>10} {:>12} {:>9}",
        "frame",
        "method",
        "median s",
        "min s",
        "max s",
        "relMSE",
        "peak MiB"
    );
    for (name, frame) in &frames {
        for m in args
            .methods
            .split(',')
            .map(str::trim)
            .filter(|m| !m.is_empty())
        {
            let mut margs = args.method.clone();
            margs.method = m.to_owned();
            let config = margs.config()?;
            let mut plan = Plan::new(&context, &config, frame.width(), frame.height())?;
            let mut out = gdrecon::Image::zeros(3, frame.height(), frame.width());
            for _ in 0..args.warmup {
                plan.execute_into(frame, &mut out, &Progress::none())?;
            }
            let mut times = Vec::with_capacity(args.runs);
            for _ in 0..args.runs {
                let t = Instant::now();
                plan.execute_into(frame, &mut out, &Progress::none())?;
                times.push(t.elapsed().as_secs_f64());
            }
            times.sort_by(f64::total_cmp);
            let median = times[times.len() / 2];
            let rel = match frame.reference() {
                Some(r) => format!("{:.5e}", metrics::compare(&out, r)?.rel_mse),
                None => "-".to_owned(),
            };
            let peak = peak_rss_mib().map_or_else(|| "-".to_owned(), |p| format!("{p:.0}"));
            say!(
                "{:<28} {:<6} {:>10.4} {:>10.4} {:>10.4} {:>12} {:>9}",
                name,
                m,
                median,
                times[0],
                times[times.len() - 1],
                rel,
                peak
            );
            rows.push(format!(
                "{name},{m},{},{},{},{},{median:.6},{:.6},{:.6},{rel},{peak}",
                frame.width(),
                frame.height(),
                context.threads(),
                args.runs,
                times[0],
                times[times.len() - 1]
            ));
        }
    }
    if let Some(csv) = &args.csv {
        std::fs::write(csv, rows.join("\n") + "\n").map_err(|source| gdrecon::Error::Io {
            path: csv.clone(),
            source,
        })?;
    }
    Ok(())
}
