//! `gdrecon`: the command-line front end (reconstruct, info, eval, demo, bench).
//!
//! The only place that prints or exits: library errors become one line on stderr and exit
//! code 1 (clap's usage errors exit with 2).

/// `println!` that ignores a closed stdout (`gdrecon info f.exr | head` must not panic).
macro_rules! say {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stdout(), $($arg)*);
    }};
}

mod bar;
mod bench;

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::{Args, Parser, Subcommand};

use gdrecon::recon::param::ParamInfo;
use gdrecon::{
    io, metrics, synth, Context, ContextOptions, Frame, Layer, Method, MethodConfig, Plan, Policy,
};

#[derive(Parser)]
#[command(
    name = "gdrecon",
    version,
    about = "Reconstruct gradient-domain renders"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Reconstruct a frame bundle into an RGB OpenEXR.
    // "--spp -1" is a value (refused with its range), "--exposure -2" a legal one: neither is
    // an unknown flag.
    #[command(allow_negative_numbers = true)]
    Reconstruct(ReconstructArgs),
    /// Describe a frame bundle: layers, size, spp, replaced values.
    Info {
        /// Frame bundle (multi-layer OpenEXR).
        input: PathBuf,
    },
    /// Compare an image with a reference: relMSE, MSE, PSNR.
    Eval {
        /// Image to evaluate (plain RGB EXR, or a bundle's color layer: the base image).
        image: PathBuf,
        /// Reference: a plain RGB EXR or a bundle with a `reference` layer.
        #[arg(long, short)]
        reference: PathBuf,
    },
    /// Write a synthetic frame bundle with a known reference (no renderer needed).
    #[command(allow_negative_numbers = true)]
    Demo {
        /// Output bundle.
        #[arg(long, short)]
        output: PathBuf,
        /// Width in pixels.
        #[arg(long, default_value_t = 320)]
        width: usize,
        /// Height in pixels.
        #[arg(long, default_value_t = 180)]
        height: usize,
        /// Samples per pixel the noise imitates.
        #[arg(long, default_value_t = 16.0)]
        spp: f32,
        /// Noise seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// Time methods on frames: median of several runs, relMSE when a reference is present.
    #[command(allow_negative_numbers = true)]
    Bench(bench::BenchArgs),
    /// List the methods' parameters: name, type, default, accepted values, meaning.
    Params {
        /// Only this method.
        method: Option<String>,
        /// Print the Markdown of docs/PARAMETERS.md.
        #[arg(long)]
        markdown: bool,
    },
}

/// Where GradNet's runtime and model, and the prior's denoiser, come from (shared by
/// `reconstruct` and `bench`).
#[derive(Args, Clone, Debug)]
pub(crate) struct RuntimeArgs {
    /// gradnet, combiner: ONNX Runtime library to load first (then ORT_DYLIB_PATH, a library
    /// next to gdrecon, the project's Python environment).
    #[arg(long)]
    onnxruntime: Option<PathBuf>,
    /// gradnet, combiner: model file instead of the embedded models (checked against its
    /// .sha256).
    #[arg(long)]
    model: Option<PathBuf>,
    /// The prior's Open Image Denoise library (libOpenImageDenoise.so.2), the only one tried
    /// when given (else OIDN_DYLIB_PATH, a library next to gdrecon, the project's Python
    /// environment).
    #[arg(long)]
    oidn: Option<PathBuf>,
}

impl RuntimeArgs {
    /// Points the configuration at the runtime (if it runs a network) and its model.
    pub(crate) fn apply(&self, config: &mut MethodConfig) {
        if let Some(runtime) = config.runtime_mut() {
            *runtime = self.onnxruntime.clone();
        }
        if let Some(c) = config.gradnet_mut() {
            c.model = self.model.clone();
        }
        if let MethodConfig::Combiner(c) = config {
            c.model = self.model.clone();
        }
    }

    /// The context options for `threads` worker threads and this OIDN library.
    pub(crate) fn context(&self, threads: Option<usize>) -> ContextOptions {
        let options = ContextOptions::with_threads(threads);
        match &self.oidn {
            Some(path) => options.with_oidn(path),
            None => options,
        }
    }
}

/// Method selection and settings of `reconstruct`.
#[derive(Args, Clone, Debug)]
pub(crate) struct MethodArgs {
    /// Reconstruction method: l2, l1, frgr, gradnet, prior, combiner or auto (`gdrecon params`
    /// lists each one; frgr needs spp, from the file or --spp; gradnet needs ONNX Runtime;
    /// prior, and the prior paths such as `--preset prior` for l1, need Open Image Denoise or
    /// the frame's 'prior' layer; combiner needs both, and variance, albedo and normal).
    #[arg(long, short, default_value = "l2")]
    method: String,
    /// Start from one of the method's presets (`gdrecon params METHOD` lists them), e.g.
    /// `published` for l1; --param settings apply on top.
    #[arg(long)]
    preset: Option<String>,
    /// Set a parameter of the method, NAME=VALUE; repeat for several (`gdrecon params
    /// METHOD` lists names, types, ranges and defaults), e.g. `-p alpha=0.3 -p reweight_steps=5`.
    #[arg(long = "param", short = 'p', value_name = "NAME=VALUE")]
    params: Vec<String>,
    #[command(flatten)]
    runtime: RuntimeArgs,
}

impl MethodArgs {
    pub(crate) fn config(&self) -> gdrecon::Result<MethodConfig> {
        let method: Method = self.method.parse()?;
        let mut config = match &self.preset {
            Some(name) => MethodConfig::preset(method, name)?,
            None => MethodConfig::default_for(method),
        };
        for assignment in &self.params {
            config.set_assignment(assignment)?;
        }
        self.runtime.apply(&mut config);
        Ok(config)
    }
}

#[derive(Args)]
struct ReconstructArgs {
    /// Frame bundle (multi-layer OpenEXR).
    input: PathBuf,
    /// Output RGB OpenEXR.
    #[arg(long, short)]
    output: PathBuf,
    #[command(flatten)]
    method: MethodArgs,
    /// Samples per pixel of the base image (overrides the file's `spp` attribute).
    #[arg(long)]
    spp: Option<f32>,
    /// Also write a tone-mapped PNG preview here.
    #[arg(long)]
    png: Option<PathBuf>,
    /// Exposure of the PNG preview, in stops.
    #[arg(long, default_value_t = 0.0)]
    exposure: f32,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Keep each plan's memory estimate, beyond the frame, within this many MiB (0: no limit):
    /// GradNet, the combiner and OIDN run in smaller tiles to fit (the same image up to rounding, slower); a
    /// plan that cannot fit is refused with an error instead of running out of memory.
    #[arg(long, default_value_t = 0)]
    max_memory_mb: u64,
    /// Refuse frames with NaN, Inf or negative colour instead of replacing them.
    #[arg(long)]
    strict: bool,
    /// Print nothing but errors.
    #[arg(long, short)]
    quiet: bool,
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => return usage_error(e),
    };
    let result = match cli.command {
        Command::Reconstruct(args) => reconstruct(args),
        Command::Info { input } => info(&input),
        Command::Eval { image, reference } => eval(&image, &reference),
        Command::Demo {
            output,
            width,
            height,
            spp,
            seed,
        } => demo(&output, width, height, spp, seed),
        Command::Bench(args) => bench::run(args),
        Command::Params { method, markdown } => params(method.as_deref(), markdown),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("gdrecon: error: {e}");
            ExitCode::FAILURE
        }
    }
}

/// Help and version go to stdout as clap writes them; a usage error is one line on stderr
/// (clap's own first line and a pointer to `--help`), exit code 2.
fn usage_error(e: clap::Error) -> ExitCode {
    use clap::error::ErrorKind;
    if matches!(e.kind(), ErrorKind::DisplayHelp | ErrorKind::DisplayVersion) {
        let _ = e.print();
        return ExitCode::SUCCESS;
    }
    let rendered = e.render().to_string();
    let first = rendered.lines().next().unwrap_or("invalid arguments");
    let first = first.strip_prefix("error: ").unwrap_or(first);
    eprintln!("gdrecon: error: {first} (see gdrecon --help)");
    ExitCode::from(2)
}

/// Reads a bundle and applies a `--spp` override.
pub(crate) fn load_frame(path: &Path, policy: Policy, spp: Option<f32>) -> gdrecon::Result<Frame> {
    let frame = io::read_bundle(path, policy)?;
    match spp {
        Some(s) => frame.with_spp(Some(s)),
        None => Ok(frame),
    }
}

fn reconstruct(args: ReconstructArgs) -> gdrecon::Result<()> {
    let policy = if args.strict {
        Policy::Strict
    } else {
        Policy::Replace
    };
    let config = args.method.config()?;
    let context = Context::new(
        args.method
            .runtime
            .context(args.threads)
            .with_max_memory_mb(args.max_memory_mb),
    )?;
    // Reading and writing decompress and compress blocks on the context's threads.
    let t0 = Instant::now();
    let frame = context.install(|| load_frame(&args.input, policy, args.spp))?;
    let read_time = t0.elapsed();
    // A frame with its own prior never runs OIDN: its scratch is not held against the limit.
    let config = match frame.prior() {
        Some(_) => config.given_prior(),
        None => config,
    };
    let mut plan = Plan::new(&context, &config, frame.width(), frame.height())?;
    let bar = bar::DelayedBar::new(args.quiet);
    let callback = |f: f64| bar.update(f);
    let (image, report) = plan.execute(&frame, &gdrecon::Progress::new(&callback))?;
    bar.finish();
    let t1 = Instant::now();
    context.install(|| io::write_rgb(&args.output, &image))?;
    let write_time = t1.elapsed();
    if let Some(png) = &args.png {
        io::write_png(png, &image, args.exposure)?;
    }
    if args.quiet {
        return Ok(());
    }
    say!(
        "{}: {} x {}, spp {}, read in {:.3} s",
        args.input.display(),
        frame.width(),
        frame.height(),
        frame
            .spp()
            .map_or_else(|| "unknown".to_owned(), |s| s.to_string()),
        read_time.as_secs_f64()
    );
    say!("{}", report.to_string().trim_end());
    if let Some(reference) = frame.reference() {
        // On the context's threads: outside it rayon would start its global pool for them.
        let (base, out) = context.install(|| {
            Ok::<_, gdrecon::Error>((
                metrics::compare(frame.color(), reference)?,
                metrics::compare(&image, reference)?,
            ))
        })?;
        say!("base     {base}");
        say!("{:<8} {out}", config.method().name());
    }
    say!(
        "wrote {} in {:.3} s",
        args.output.display(),
        write_time.as_secs_f64()
    );
    Ok(())
}

fn info(path: &Path) -> gdrecon::Result<()> {
    let raw = io::read_bundle_raw(path)?;
    say!("{}: {} x {}", path.display(), raw.size.0, raw.size.1);
    say!(
        "spp: {}",
        raw.spp
            .map_or_else(|| "unknown".to_owned(), |s| s.to_string())
    );
    for layer in Layer::ALL {
        match raw.sources.get(&layer) {
            Some(names) => say!("  {:<10} {}", layer.name(), names.join(", ")),
            None if layer.is_required() => say!("  {:<10} MISSING (required)", layer.name()),
            None => say!("  {:<10} -", layer.name()),
        }
    }
    if !raw.ignored.is_empty() {
        say!("ignored channels: {}", raw.ignored.join(", "));
    }
    for w in &raw.warnings {
        say!("warning: {w}");
    }
    let frame = raw.into_frame(Policy::Replace)?;
    say!("{}", frame.sanitized());
    Ok(())
}

fn eval(image: &Path, reference: &Path) -> gdrecon::Result<()> {
    let img = io::read_rgb(image)?;
    let reference = io::read_reference(reference)?;
    let m = metrics::compare(&img, &reference)?;
    say!("{m}");
    Ok(())
}

fn demo(output: &Path, width: usize, height: usize, spp: f32, seed: u64) -> gdrecon::Result<()> {
    synth::check_size(width, height)?;
    if !(spp.is_finite() && spp > 0.0) {
        return Err(gdrecon::Error::InvalidArgument(format!(
            "demo needs a positive spp, got {spp}"
        )));
    }
    let frame = synth::synthetic_frame(width, height, spp, seed);
    io::write_bundle(output, &frame)?;
    say!(
        "wrote synthetic bundle {} ({width} x {height}, {spp} spp, seed {seed})",
        output.display()
    );
    Ok(())
}

fn params(method: Option<&str>, markdown: bool) -> gdrecon::Result<()> {
    let methods = match method {
        Some(m) => vec![m.parse::<Method>()?],
        None => Method::ALL.to_vec(),
    };
    if markdown {
        say!("{}", params_markdown(&methods).trim_end());
        return Ok(());
    }
    for m in methods {
        say!("{m}: {}", m.summary());
        for p in m.params() {
            say!(
                "  {:<28} {:<6} default {:<8} {}",
                p.name,
                p.kind.name(),
                p.format(p.default),
                p.accepts()
            );
            say!("  {:<28} {}", "", p.doc);
        }
        for (name, doc) in m.presets() {
            say!("  preset {name}: {doc}");
        }
    }
    Ok(())
}

/// `docs/PARAMETERS.md`: every method's table (tests/cli.rs checks the file is current).
fn params_markdown(methods: &[Method]) -> String {
    let mut md = String::from(
        "# Method parameters\n\n\
         Generated by `gdrecon params --markdown` from the methods' parameter tables \
         (`src/recon/param.rs`); a test checks that this file is current. The same names are \
         taken by the CLI (`--param NAME=VALUE`, `--preset NAME`), `gdrecon bench` variants \
         (`METHOD:NAME=VALUE:PRESET`), the Rust API (`MethodConfig::set`) and the C API \
         (`gdr_filter_set_float` / `_int` / `_bool`; `gdr_method_param` lists them). A C filter \
         also takes `spp` (float, 0 = unknown) and `strict` (bool).\n",
    );
    for &m in methods {
        md += &format!("\n## `{m}`\n\n{}.\n\n", m.summary());
        let rows: Vec<ParamInfo> = m.params();
        if rows.is_empty() {
            md += "No parameters.\n";
        } else {
            md += "| name | type | default | accepts | meaning |\n|---|---|---|---|---|\n";
            for p in rows {
                md += &format!(
                    "| `{}` | {} | `{}` | {} | {} |\n",
                    p.name,
                    p.kind.name(),
                    p.format(p.default),
                    p.accepts(),
                    p.doc
                );
            }
        }
        let presets = m.presets();
        if !presets.is_empty() {
            md += "\nPresets: ";
            md += &presets
                .iter()
                .map(|(name, doc)| format!("`{name}` ({doc})"))
                .collect::<Vec<_>>()
                .join("; ");
            md += ".\n";
        }
    }
    md
}
