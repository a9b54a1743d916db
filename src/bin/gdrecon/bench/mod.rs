//! `gdrecon bench`: run time against error, per method variant and frame.
//!
//! Planning (DCT plans, buffers, ONNX sessions) is done once per variant and frame size and not
//! timed, as a renderer would commit once and execute per frame. Times are medians over
//! `--runs` executions after `--warmup` untimed ones; relMSE is against the frame's reference;
//! peak memory is the resident high-water mark (VmHWM), reset when each variant starts.
//!
//! Variants are methods at named settings (`l1:reweight_steps=5`, see [`variant`]); `--sweep`
//! times each
//! method's speed/quality variants, `--scales` times resized copies of the frames, and
//! `--out-dir` writes the report: `results.csv`, `results.json`, `summary.md` and the Pareto
//! plots `pareto.png` / `pareto.svg`.

mod aggregate;
mod baseline;
mod cpu;
mod frames;
mod measure;
mod plot;
mod report;
mod summary;
mod variant;

use std::path::{Path, PathBuf};

use clap::Args;

use gdrecon::Context;

use self::frames::BenchFrame;
use self::measure::{Row, Schedule};
use self::variant::Variant;
use crate::RuntimeArgs;

/// Arguments of `gdrecon bench`.
#[derive(Args)]
pub struct BenchArgs {
    /// Frame bundles to time (any number); `<scene>_<N>spp.exr` names give scene and spp.
    inputs: Vec<PathBuf>,
    /// Also time a synthetic frame of this size, e.g. 1280x720.
    #[arg(long)]
    synthetic: Option<String>,
    /// Comma-separated methods (each at its default settings, or its variants with --sweep).
    #[arg(long, default_value = "l2,l1")]
    methods: String,
    /// Time each method's speed/quality variants (each method declares its own: the release's
    /// schedule and the ablations; `gdrecon bench --help` lists them).
    #[arg(long, long_help = sweep_help())]
    sweep: bool,
    /// Comma-separated variants METHOD[:PRESET][:NAME=VALUE...] instead of --methods, e.g.
    /// `l2,l1:reweight_steps=5:cg_tolerance=0,frgr:guide=l1,gradnet:use_features=false`;
    /// `gdrecon params` lists every method's parameters and presets.
    #[arg(long, conflicts_with_all = ["sweep", "methods"])]
    settings: Option<String>,
    /// A parameter NAME=VALUE for every variant whose method has it (a variant's own options
    /// override it); repeat for several.
    #[arg(long = "param", short = 'p', value_name = "NAME=VALUE")]
    params: Vec<String>,
    /// Also time every frame resized by these factors, e.g. 0.5,1,2 (nearest-neighbour; 1 is
    /// the frame as read; the synthetic frame is rendered anew at each size). relMSE is
    /// reported at factor 1 only.
    #[arg(long)]
    scales: Option<String>,
    /// Timed runs per variant and frame (the median is reported).
    #[arg(long, default_value_t = 7)]
    runs: usize,
    /// Untimed runs first.
    #[arg(long, default_value_t = 1)]
    warmup: usize,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Keep each plan within this many MiB beyond its frame, as `reconstruct --max-memory-mb`
    /// does (smaller tiles for GradNet, the combiner and OIDN; 0: no limit): to time what a
    /// memory budget costs.
    #[arg(long, default_value_t = 0)]
    max_memory_mb: u64,
    /// Write the table as CSV here too (one line per frame and variant).
    #[arg(long)]
    csv: Option<PathBuf>,
    /// Write the report here: results.csv, results.json, summary.md, pareto.png, pareto.svg.
    #[arg(long)]
    out_dir: Option<PathBuf>,
    /// Also report, per frame with a reference, the base image itself (`base`) and Intel OIDN
    /// on the base image (`oidn`) and on a 2x-spp primal render (`oidn:equal-time`), read from
    /// `<folder>/oidn/` and `<folder>/oidn-equal-time/` beside each bundle (written by
    /// `python -m gdrecon_py.oidn <folder>`); their seconds are OIDN's own, not timed here.
    #[arg(long)]
    baselines: bool,
    /// Also time Intel Open Image Denoise on every frame in this run (the variant `prior`: the
    /// library's own OIDN, or the frame's prior layer), alone first, then once before each
    /// run of every other variant, and report every variant's time as a multiple of OIDN's
    /// runs interleaved with its own ("x OIDN": per frame, then the median; column `oidn_s`),
    /// so that speed is quoted against the denoiser under the same load. Peaks then include
    /// OIDN's plan.
    #[arg(long)]
    against_oidn: bool,
    /// Heading of summary.md.
    #[arg(long, default_value = "gdrecon bench")]
    title: String,
    #[command(flatten)]
    runtime: RuntimeArgs,
}

/// `--sweep`'s help: every method's sweep, from the registry.
fn sweep_help() -> String {
    let mut help =
        String::from("Time each method's speed/quality variants instead of its defaults alone:");
    for m in gdrecon::Method::ALL {
        let names = variant::names_for_methods(m.name(), true).unwrap_or_default();
        help += &format!("\n  {m}: {}", names.join(", "));
    }
    help
}

/// Runs `gdrecon bench`.
pub fn run(args: BenchArgs) -> gdrecon::Result<()> {
    if args.runs == 0 {
        return Err(gdrecon::Error::InvalidArgument(
            "--runs must be at least 1".into(),
        ));
    }
    let variants = variants(&args)?;
    let scales = match &args.scales {
        Some(list) => frames::parse_scales(list)?,
        None => vec![1.0],
    };
    let frames = load_frames(&args)?;
    let context = Context::new(
        args.runtime
            .context(args.threads)
            .with_max_memory_mb(args.max_memory_mb),
    )?;
    let schedule = Schedule {
        warmup: args.warmup,
        runs: args.runs,
    };
    let load_before = summary::load_average();
    say!(
        "{}, {} worker threads{}",
        cpu::describe(),
        context.threads(),
        match context.max_memory_mb() {
            0 => String::new(),
            mb => format!(", max_memory_mb {mb}"),
        }
    );
    print_header();
    let mut rows = time_all(
        &context,
        &variants,
        &frames,
        &scales,
        schedule,
        args.against_oidn,
    )?;
    if args.against_oidn {
        print_against_oidn(&rows);
        if frames.iter().any(|f| f.frame.prior().is_some()) {
            say!("(OIDN timed on each frame without its 'prior' layer; other variants given it)");
        }
    }
    if args.baselines {
        for row in baseline::rows(&frames, context.threads())? {
            print_row(&row);
            rows.push(row);
        }
    }
    if let Some(csv) = &args.csv {
        report::write(csv, &report::plain_csv(&rows))?;
    }
    if let Some(dir) = &args.out_dir {
        let header = summary::Header {
            title: args.title.clone(),
            command: command_line(&args.inputs),
            threads: context.threads(),
            runs: args.runs,
            warmup: args.warmup,
            load_before,
            load_after: summary::load_average(),
        };
        write_report(dir, &header, &rows)?;
    }
    Ok(())
}

/// The variants to time, checked before any frame is read.
fn variants(args: &BenchArgs) -> gdrecon::Result<Vec<Variant>> {
    let names = match &args.settings {
        Some(list) => variant::split_list(list).map(str::to_owned).collect(),
        None => variant::names_for_methods(&args.methods, args.sweep)?,
    };
    if names.is_empty() {
        return Err(gdrecon::Error::InvalidArgument(
            "no method to time: --methods / --settings is empty".into(),
        ));
    }
    let mut variants = names
        .iter()
        .map(|n| variant::parse(n, &args.params, &args.runtime))
        .collect::<gdrecon::Result<Vec<_>>>()?;
    if args.against_oidn {
        // OIDN first: the reference every later variant's time is divided by.
        variants.retain(|v| v.label() != aggregate::OIDN);
        variants.insert(
            0,
            variant::parse(aggregate::OIDN, &args.params, &args.runtime)?,
        );
    }
    variant::check_common(&args.params, &variants)?;
    Ok(variants)
}

/// The bundles named on the command line, then the synthetic frame.
fn load_frames(args: &BenchArgs) -> gdrecon::Result<Vec<BenchFrame>> {
    let mut frames = args
        .inputs
        .iter()
        .map(|p| frames::load(p))
        .collect::<gdrecon::Result<Vec<_>>>()?;
    if let Some(spec) = &args.synthetic {
        frames.push(frames::synthetic(spec)?);
    }
    if frames.is_empty() {
        return Err(gdrecon::Error::InvalidArgument(
            "nothing to time: give frame bundles or --synthetic WxH".into(),
        ));
    }
    Ok(frames)
}

/// Times every variant on every frame at every scale (resized copies made one scale at a time).
fn time_all(
    context: &Context,
    variants: &[Variant],
    frames: &[BenchFrame],
    scales: &[f64],
    schedule: Schedule,
    against_oidn: bool,
) -> gdrecon::Result<Vec<Row>> {
    let mut rows = Vec::new();
    for &scale in scales {
        let resized = if scale == 1.0 {
            None
        } else {
            Some(
                frames
                    .iter()
                    .map(|f| frames::resized(f, scale))
                    .collect::<gdrecon::Result<Vec<_>>>()?,
            )
        };
        let set = resized.as_deref().unwrap_or(frames);
        // With --against-oidn, OIDN is the first variant: timed alone, then alternately with
        // every other one.
        let oidn = variants
            .first()
            .filter(|v| against_oidn && v.label() == aggregate::OIDN);
        for v in variants {
            let against = match oidn {
                Some(o) if std::ptr::eq(o, v) => measure::Against::Itself,
                Some(o) => measure::Against::Beside(o),
                None => measure::Against::Nothing,
            };
            rows.extend(measure::time_variant(
                context,
                v,
                against,
                set,
                schedule,
                &mut print_row,
            )?);
        }
    }
    Ok(rows)
}

/// Every variant's time as a multiple of OIDN's (`--against-oidn`): per frame and scale, then
/// the median over them.
fn print_against_oidn(rows: &[Row]) {
    say!("\ntime against OIDN in this run (per frame, then the median; 1 = OIDN alone)");
    let mut seen: Vec<&str> = Vec::new();
    for r in rows {
        if !seen.contains(&r.variant.as_str()) {
            seen.push(&r.variant);
        }
    }
    for v in seen {
        let of: Vec<&Row> = rows.iter().filter(|r| r.variant == v).collect();
        if let Some(x) = aggregate::times_oidn(&of, rows) {
            say!("{v:<40} {x:>8.3}x OIDN");
        }
    }
}

/// The console table's header.
fn print_header() {
    say!(
        "{:<22} {:<18} {:>11} {:>9} {:>9} {:>9} {:>11} {:>8}",
        "frame",
        "variant",
        "size",
        "median s",
        "min s",
        "max s",
        "relMSE",
        "peak MiB"
    );
}

/// One console line.
fn print_row(r: &Row) {
    say!(
        "{:<22} {:<18} {:>11} {:>9.4} {:>9.4} {:>9.4} {:>11} {:>8}",
        r.frame,
        r.variant,
        format!("{}x{}", r.width, r.height),
        r.median_s,
        r.min_s,
        r.max_s,
        r.rel_mse
            .map_or_else(|| "-".to_owned(), |v| format!("{v:.5e}")),
        r.peak_rss_mib
            .map_or_else(|| "-".to_owned(), |p| format!("{p:.0}"))
    );
    if r.stages.len() > 1 {
        let stages: Vec<String> = r
            .stages
            .iter()
            .map(|(name, s)| format!("{name} {s:.3}"))
            .collect();
        say!("    stage medians (s): {}", stages.join(", "));
    }
}

/// Writes the five report files into `dir` (created if needed).
fn write_report(dir: &Path, header: &summary::Header, rows: &[Row]) -> gdrecon::Result<()> {
    std::fs::create_dir_all(dir).map_err(|source| gdrecon::Error::Io {
        path: dir.to_owned(),
        source,
    })?;
    let panels = aggregate::panels(rows);
    report::write(&dir.join("results.csv"), &report::csv(rows))?;
    report::write(&dir.join("results.json"), &report::json(rows))?;
    report::write(
        &dir.join("summary.md"),
        &summary::markdown(header, rows, &panels),
    )?;
    // The plot shows our variants only: baselines carry another program's time, or none.
    let ours: Vec<aggregate::Panel> = panels
        .iter()
        .map(|p| aggregate::Panel {
            spp: p.spp,
            points: p.points.iter().filter(|q| !q.baseline).cloned().collect(),
        })
        .collect();
    plot::write(&dir.join("pareto.png"), &dir.join("pareto.svg"), &ours)?;
    let timed: Vec<Row> = rows
        .iter()
        .filter(|r| r.method != baseline::METHOD)
        .cloned()
        .collect();
    let scaled = timed.iter().any(|r| r.scale != 1.0);
    if scaled {
        plot::write_scaling(&dir.join("scaling.png"), &dir.join("scaling.svg"), &timed)?;
    }
    say!(
        "wrote {}/{{results.csv, results.json, summary.md, pareto.png, pareto.svg{}}}",
        dir.display(),
        if scaled {
            ", scaling.png, scaling.svg"
        } else {
            ""
        }
    );
    Ok(())
}

/// This process's command line, with frame paths shortened to their file names and words
/// holding spaces quoted.
fn command_line(inputs: &[PathBuf]) -> String {
    let words: Vec<String> = std::env::args_os()
        .skip(1)
        .map(|a| {
            let word = if inputs.iter().any(|i| i.as_os_str() == a) {
                Path::new(&a)
                    .file_name()
                    .unwrap_or(&a)
                    .to_string_lossy()
                    .into_owned()
            } else {
                a.to_string_lossy().into_owned()
            };
            if word.contains(char::is_whitespace) {
                format!("'{word}'")
            } else {
                word
            }
        })
        .collect();
    format!("gdrecon {}", words.join(" "))
}
