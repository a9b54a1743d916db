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

use clap::{Args, Parser, Subcommand, ValueEnum};

use gdrecon::recon::{
    AutoConfig, FilterConfig, FilterGuide, GradNetConfig, PoissonL1Config, PoissonL2Config,
};
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
    Reconstruct(ReconstructArgs),
    /// Describe a frame bundle: layers, size, spp, replaced values.
    Info {
        /// Frame bundle (multi-layer OpenEXR).
        input: PathBuf,
    },
    /// Compare an image with a reference: relMSE, MSE, PSNR.
    Eval {
        /// Image to evaluate (plain RGB EXR, or a bundle's color layer).
        image: PathBuf,
        /// Reference: a plain RGB EXR or a bundle with a `reference` layer.
        #[arg(long, short)]
        reference: PathBuf,
    },
    /// Write a synthetic frame bundle with a known reference (no renderer needed).
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
    Bench(bench::BenchArgs),
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum GuideArg {
    /// RDFC's first pass (the authors' release).
    Rdfc,
    /// Screened Poisson L1.
    L1,
    /// None: the noisy colour (the pre-denoiser's ablation).
    None,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum L1Preset {
    /// Preconditioned CG with early stopping (the default).
    Fast,
    /// Gradient-domain path tracing's schedule: 20 steps x 50 plain CG iterations.
    Published,
}

/// Method selection and settings shared by `reconstruct` and `bench`.
#[derive(Args, Clone, Debug)]
pub(crate) struct MethodArgs {
    /// Reconstruction method: l2, l1, filter, gradnet or auto (the filter needs spp: from the
    /// file or --spp; gradnet needs ONNX Runtime, see --onnxruntime; auto picks one per frame
    /// and prints why).
    #[arg(long, short, default_value = "l2")]
    method: String,
    /// Screened Poisson data weight (residual alpha (I - I_b)).
    #[arg(long, default_value_t = 0.2)]
    alpha: f32,
    /// L1 schedule preset.
    #[arg(long, value_enum, default_value = "fast")]
    l1_preset: L1Preset,
    /// L1: IRLS reweighting steps (overrides the preset).
    #[arg(long)]
    irls_steps: Option<u32>,
    /// L1: maximum CG iterations per step (overrides the preset).
    #[arg(long)]
    cg_iterations: Option<u32>,
    /// L1: relative CG tolerance, 0 runs every iteration (overrides the preset).
    #[arg(long)]
    cg_tolerance: Option<f32>,
    /// filter: the pre-denoised guide image.
    #[arg(long, value_enum, default_value = "rdfc")]
    filter_guide: GuideArg,
    /// filter: window radius (3 or 4).
    #[arg(long, default_value_t = 4)]
    filter_radius: usize,
    /// filter: resolution levels (1 to 4).
    #[arg(long, default_value_t = FilterConfig::default().levels)]
    filter_levels: usize,
    /// filter: gradient-enhancement iterations (1000: the release's reference mode; 0: no
    /// enhancement, the ablation).
    #[arg(long, default_value_t = FilterConfig::default().enhance_iterations)]
    filter_enhance_iterations: u32,
    /// filter: skip the feature prefilter (its ablation).
    #[arg(long)]
    filter_no_prefilter: bool,
    /// gradnet: ONNX Runtime library to load first (then ORT_DYLIB_PATH, a library next to
    /// gdrecon, the project's Python environment).
    #[arg(long)]
    onnxruntime: Option<PathBuf>,
    /// gradnet: model file instead of the embedded models (checked against its .sha256).
    #[arg(long)]
    model: Option<PathBuf>,
    /// gradnet: largest tile side in pixels, 0 = never tile.
    #[arg(long, default_value_t = gdrecon::recon::gradnet::DEFAULT_TILE)]
    tile: usize,
    /// gradnet: skip the Gaussian bias correction.
    #[arg(long)]
    no_bias_correction: bool,
    /// gradnet: ignore the frame's features (run the no-feature model).
    #[arg(long)]
    no_features: bool,
}

impl MethodArgs {
    pub(crate) fn config(&self) -> gdrecon::Result<MethodConfig> {
        let method: Method = self.method.parse()?;
        Ok(match method {
            Method::PoissonL2 => MethodConfig::PoissonL2(PoissonL2Config { alpha: self.alpha }),
            Method::PoissonL1 => MethodConfig::PoissonL1(self.l1()),
            Method::Filter => MethodConfig::Filter(self.filter()),
            Method::GradNet => MethodConfig::GradNet(self.gradnet()),
            Method::Auto => {
                let mut c = AutoConfig::default();
                c.filter = self.filter();
                c.gradnet = self.gradnet();
                c.l1 = self.l1();
                MethodConfig::Auto(c)
            }
            other => MethodConfig::default_for(other).with_alpha(self.alpha),
        })
    }

    fn l1(&self) -> PoissonL1Config {
        let mut c = match self.l1_preset {
            L1Preset::Fast => PoissonL1Config::default(),
            L1Preset::Published => PoissonL1Config::published(),
        };
        c.alpha = self.alpha;
        c.reweight_steps = self.irls_steps.unwrap_or(c.reweight_steps);
        c.cg_iterations = self.cg_iterations.unwrap_or(c.cg_iterations);
        c.cg_tolerance = self.cg_tolerance.unwrap_or(c.cg_tolerance);
        c
    }

    fn filter(&self) -> FilterConfig {
        FilterConfig {
            radius: self.filter_radius,
            levels: self.filter_levels,
            enhance_iterations: self.filter_enhance_iterations,
            guide: match self.filter_guide {
                GuideArg::Rdfc => FilterGuide::Rdfc,
                GuideArg::L1 => FilterGuide::PoissonL1,
                GuideArg::None => FilterGuide::Colour,
            },
            prefilter: !self.filter_no_prefilter,
        }
    }

    fn gradnet(&self) -> GradNetConfig {
        let mut c = GradNetConfig::default();
        c.runtime = self.onnxruntime.clone();
        c.model = self.model.clone();
        c.tile_size = self.tile;
        c.bias_correction = !self.no_bias_correction;
        c.use_features = !self.no_features;
        c
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
    /// Refuse frames with NaN, Inf or negative colour instead of replacing them.
    #[arg(long)]
    strict: bool,
    /// Print nothing but errors.
    #[arg(long, short)]
    quiet: bool,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
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
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("gdrecon: error: {e}");
            ExitCode::FAILURE
        }
    }
}

/// Reads a bundle and applies a `--spp` override.
pub(crate) fn load_frame(path: &Path, policy: Policy, spp: Option<f32>) -> gdrecon::Result<Frame> {
    let frame = io::read_bundle(path, policy)?;
    match spp {
        Some(s) => frame.into_builder().spp(Some(s)).build(policy),
        None => Ok(frame),
    }
}

fn reconstruct(args: ReconstructArgs) -> gdrecon::Result<()> {
    let policy = if args.strict {
        Policy::Strict
    } else {
        Policy::Replace
    };
    let t0 = Instant::now();
    let frame = load_frame(&args.input, policy, args.spp)?;
    let read_time = t0.elapsed();
    let config = args.method.config()?;
    let context = Context::new(ContextOptions {
        threads: args.threads,
    })?;
    let mut plan = Plan::new(&context, &config, frame.width(), frame.height())?;
    let bar = bar::DelayedBar::new(args.quiet);
    let callback = |f: f64| bar.update(f);
    let (image, report) = plan.execute(&frame, &gdrecon::Progress::new(&callback))?;
    bar.finish();
    io::write_rgb(&args.output, &image)?;
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
        let base = metrics::compare(frame.color(), reference)?;
        let out = metrics::compare(&image, reference)?;
        say!("base     {base}");
        say!("{:<8} {out}", config.method().name());
    }
    say!("wrote {}", args.output.display());
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
    let reference = io::read_rgb(reference)?;
    let m = metrics::compare(&img, &reference)?;
    say!("{m}");
    Ok(())
}

fn demo(output: &Path, width: usize, height: usize, spp: f32, seed: u64) -> gdrecon::Result<()> {
    if width == 0 || height == 0 || !(spp.is_finite() && spp > 0.0) {
        return Err(gdrecon::Error::InvalidArgument(format!(
            "demo needs a positive size and spp, got {width} x {height} at {spp} spp"
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
