//! Reconstruction methods behind one plan/execute interface.
//!
//! Every method is one file (or folder) implementing the crate's `Reconstructor` trait: its
//! constructor builds everything reusable for one frame size (DCT plans, solver buffers, the
//! ONNX session), and `reconstruct_into` runs per frame. Its configuration type declares its
//! parameters once, in a table ([`param`]), and the method is registered once, in the
//! `registry!` call below: that line generates [`Method`], [`MethodConfig`] and every dispatch,
//! so the CLI, `bench`, the C API and the parameter listing see the new method with nothing
//! else to edit. [`Plan`] is what callers hold: a method planned for a size, bound to a
//! [`Context`]'s thread pool, with the checks and the output guard that keeps NaN and Inf out
//! of every result. Callers cannot run a method around those checks: the trait is internal.
//!
//! To add a method `foo`: write `recon/foo.rs` with `FooConfig` (implementing `Params`, with
//! its table, and `Register`, which plans it) and the planned type implementing
//! `Reconstructor`, then add one line to `registry!`. The `testing` cargo feature registers
//! `copy` (`recon/copy.rs`) exactly so, and `tests/registry.rs` finds it in the CLI, `bench`
//! and the C API.

pub mod auto;
mod band;
pub mod combiner;
pub mod converged;
#[cfg(feature = "testing")]
pub mod copy;
mod dct;
mod emitters;
pub mod frgr;
pub mod gradnet;
mod multigrid;
mod ops;
pub mod param;
pub mod poisson_l1;
pub mod poisson_l2;
pub mod prior;

use std::fmt;
use std::path::PathBuf;
use std::str::FromStr;

use rayon::prelude::*;

pub use auto::AutoConfig;
pub use band::BandScope;
pub use combiner::CombinerConfig;
#[cfg(feature = "testing")]
pub use copy::CopyConfig;
pub use frgr::{FrgrConfig, FrgrGuide};
pub use gradnet::{GradNetConfig, GradNetPrecision, Precision};
pub use param::{Kind, ParamInfo, Range, Value};
pub use poisson_l1::{PoissonL1Config, Preconditioner};
pub use poisson_l2::PoissonL2Config;
pub use prior::{DataTerm, PriorConfig, Quality};

use self::param::Settings;
use crate::context::Context;
use crate::error::{Error, Result};
use crate::frame::Frame;
use crate::image::Image;
use crate::progress::Progress;
use crate::report::Report;

/// A reconstruction method planned for one frame size. Internal: callers hold a [`Plan`],
/// which checks sizes, runs on the context's pool and repairs non-finite output.
pub(crate) trait Reconstructor: Send {
    /// Which method this is.
    fn method(&self) -> Method;

    /// Reconstructs `frame` into `out` (3 channels, the frame's size). The caller has checked
    /// the sizes; `report` receives stage times, skipped work and notes.
    fn reconstruct_into(
        &mut self,
        frame: &Frame,
        out: &mut Image,
        report: &mut Report,
        progress: &Progress,
    ) -> Result<()>;
}

/// What a method's configuration type provides to be registered (besides its parameter
/// table, [`param::Params`]).
pub(crate) trait Register: Settings + Clone {
    /// The variants `gdrecon bench --sweep` times: the options after `method:`, `""` being the
    /// defaults (`"reweight_steps=5"`, `"published"`).
    const SWEEP: &'static [&'static str] = &[""];

    /// Further variants that need a prior, which bench frames do not carry: swept after
    /// [`Register::SWEEP`] when OIDN can compute it (cargo feature `oidn`).
    const PRIOR_SWEEP: &'static [&'static str] = &[];

    /// Whether this build can run the method (its cargo feature is on).
    const BUILT: bool = true;

    /// Plans the method for `width` x `height` frames (sizes already checked non-zero, every
    /// parameter already checked against its table).
    fn plan(
        &self,
        context: &Context,
        width: usize,
        height: usize,
    ) -> Result<Box<dyn Reconstructor>>;

    /// The GradNet settings this configuration runs with, if it can run GradNet: where the
    /// model path goes.
    fn gradnet_mut(&mut self) -> Option<&mut GradNetConfig> {
        None
    }

    /// The ONNX Runtime library path, if this configuration runs a network.
    fn runtime_mut(&mut self) -> Option<&mut Option<PathBuf>> {
        None
    }

    /// An upper estimate of the bytes a plan for `width` x `height` frames holds at its peak
    /// (planned buffers, execution scratch, the output image, a loaded denoiser's or
    /// network's share), beyond the frame itself. [`Plan::new`] compares it with the
    /// context's `max_memory_mb` and the address space the process has left.
    fn memory_estimate(&self, width: usize, height: usize) -> u64;

    /// Lowers what this configuration may run at once (a network's whole-frame and tile
    /// budgets) so that [`Register::memory_estimate`] for `width` x `height` stays within
    /// `limit` bytes where smaller tiles can make it: the context's `max_memory_mb` bounds
    /// memory by tiling, as OIDN's `maxMemoryMB` does, and refuses a plan only when the
    /// smallest tiles are still over it. Budgets are never raised. Default: nothing to lower.
    fn fit_memory(&mut self, _width: usize, _height: usize, _limit: u64) {}
}

/// [`Register::fit_memory`] where `config`'s estimate is over `limit`: a configuration that
/// fits is left as it is.
pub(crate) fn fit_within<C: Register>(config: &mut C, width: usize, height: usize, limit: u64) {
    if config.memory_estimate(width, height) > limit {
        config.fit_memory(width, height, limit);
    }
}

/// The most pixels a run taking `bytes_per_pixel` and `fixed` bytes may hold when `taken`
/// bytes are already spoken for, under `limit`: the inverse of [`bytes_for`] that
/// [`Register::fit_memory`] sizes tiles with.
pub(crate) fn pixels_within(limit: u64, taken: u64, bytes_per_pixel: u64, fixed: u64) -> usize {
    let left = limit.saturating_sub(taken.saturating_add(fixed));
    usize::try_from(left / bytes_per_pixel.max(1)).unwrap_or(usize::MAX)
}

/// `bytes_per_pixel` bytes for each pixel of a `width` x `height` frame plus `fixed` bytes,
/// saturating: the form of every method's [`Register::memory_estimate`].
pub(crate) fn bytes_for(width: usize, height: usize, bytes_per_pixel: u64, fixed: u64) -> u64 {
    (width as u64)
        .saturating_mul(height as u64)
        .saturating_mul(bytes_per_pixel)
        .saturating_add(fixed)
}

/// One MiB.
pub(crate) const MIB: u64 = 1 << 20;

/// Declares the methods: one line each, `Variant(ConfigType) = "name", "summary";`, optionally
/// behind a `#[cfg(...)]`. Generates [`Method`], [`MethodConfig`] and their dispatch.
macro_rules! registry {
    ($( $(#[cfg($cfg:meta)])? $variant:ident($config:ty) = $name:literal, $summary:literal; )*) => {
        /// The methods gdrecon offers (the CLI and C name in brackets).
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
        #[non_exhaustive]
        pub enum Method {
            $( $(#[cfg($cfg)])? #[doc = concat!($summary, " (`", $name, "`).")] $variant, )*
        }

        /// How many methods this build has.
        const COUNT: usize = {
            let mut n = 0;
            $( $(#[cfg($cfg)])? { n += 1; } )*
            n
        };

        impl Method {
            /// Every method, in the order they are listed.
            pub const ALL: [Method; COUNT] = {
                let mut all = [Method::PoissonL2; COUNT];
                let mut i = 0;
                $( $(#[cfg($cfg)])? { all[i] = Method::$variant; i += 1; } )*
                assert!(i == COUNT);
                all
            };

            /// The CLI / C ABI name.
            pub fn name(self) -> &'static str {
                match self { $( $(#[cfg($cfg)])? Method::$variant => $name, )* }
            }

            /// One line: what the method does.
            pub fn summary(self) -> &'static str {
                match self { $( $(#[cfg($cfg)])? Method::$variant => $summary, )* }
            }

            /// The method's parameters with their types, ranges and defaults.
            pub fn params(self) -> Vec<ParamInfo> {
                match self { $( $(#[cfg($cfg)])? Method::$variant => <$config>::infos(""), )* }
            }

            /// The method's presets: `(name, what it sets)`.
            pub fn presets(self) -> Vec<(String, &'static str)> {
                match self { $( $(#[cfg($cfg)])? Method::$variant => <$config>::presets(), )* }
            }

            /// Whether this build can run the method: false for `gradnet` without its cargo
            /// feature (its plans then fail with [`Error::Unsupported`]), and for `prior`
            /// without `oidn` (it then runs only on frames that carry a `prior` layer). Whether
            /// ONNX Runtime or Open Image Denoise can be found is only known when it is needed.
            pub fn is_built(self) -> bool {
                match self {
                    $( $(#[cfg($cfg)])? Method::$variant => <$config as Register>::BUILT, )*
                }
            }

            /// The variants `gdrecon bench --sweep` times: options after `method:` (`""`:
            /// the defaults); those that need a prior only when OIDN is built in.
            pub fn sweep(self) -> Vec<&'static str> {
                let (all, prior) = match self {
                    $( $(#[cfg($cfg)])? Method::$variant => (
                        <$config as Register>::SWEEP,
                        <$config as Register>::PRIOR_SWEEP,
                    ), )*
                };
                let prior: &[&str] = if cfg!(feature = "oidn") { prior } else { &[] };
                all.iter().chain(prior).copied().collect()
            }
        }

        /// A method with its settings.
        // `auto`'s settings hold every method it may run (about 290 bytes): a configuration is
        // made once per plan, so its size costs nothing, and boxing it would change the API.
        #[allow(clippy::large_enum_variant)]
        #[derive(Clone, Debug, PartialEq)]
        #[non_exhaustive]
        pub enum MethodConfig {
            $( $(#[cfg($cfg)])? #[doc = concat!("See [`", stringify!($config), "`].")] $variant($config), )*
        }

        impl MethodConfig {
            /// The method's default settings.
            pub fn default_for(method: Method) -> Self {
                match method {
                    $( $(#[cfg($cfg)])? Method::$variant => MethodConfig::$variant(Default::default()), )*
                }
            }

            /// Which method this configures.
            pub fn method(&self) -> Method {
                match self { $( $(#[cfg($cfg)])? MethodConfig::$variant(_) => Method::$variant, )* }
            }

            /// The preset `name` of `method` (see [`Method::presets`]).
            pub fn preset(method: Method, name: &str) -> Result<Self> {
                let found = match method {
                    $( $(#[cfg($cfg)])? Method::$variant => <$config>::preset(name).map(MethodConfig::$variant), )*
                };
                found.ok_or_else(|| {
                    let names: Vec<String> = method.presets().into_iter().map(|(n, _)| n).collect();
                    Error::arg(format!(
                        "unknown preset '{name}' for method '{method}', {}",
                        if names.is_empty() { "it has none".to_owned() } else { format!("expected one of: {}", names.join(", ")) }
                    ))
                })
            }

            fn read(&self, name: &str) -> Option<Value> {
                match self { $( $(#[cfg($cfg)])? MethodConfig::$variant(c) => c.read(name), )* }
            }

            fn write(&mut self, name: &str, value: Value) -> bool {
                match self { $( $(#[cfg($cfg)])? MethodConfig::$variant(c) => c.write(name, value), )* }
            }

            fn register(&mut self) -> &mut dyn RegisterDyn {
                match self { $( $(#[cfg($cfg)])? MethodConfig::$variant(c) => c, )* }
            }

            fn register_ref(&self) -> &dyn RegisterDyn {
                match self { $( $(#[cfg($cfg)])? MethodConfig::$variant(c) => c, )* }
            }
        }
    };
}

registry! {
    PoissonL2(PoissonL2Config) = "l2",
        "Screened Poisson, L2, solved exactly by two 2-D DCTs";
    PoissonL1(PoissonL1Config) = "l1",
        "Screened Poisson, group L1, by IRLS with multigrid-preconditioned CG";
    Frgr(FrgrConfig) = "frgr",
        "Filtering-based reconstruction, FRGR (Yan et al. 2024); needs the frame's spp";
    GradNet(GradNetConfig) = "gradnet",
        "GradNet (Guo et al. 2019) through ONNX Runtime, loaded at run time";
    Prior(PriorConfig) = "prior",
        "The prior alone: the frame's 'prior' layer, or Open Image Denoise on the base image";
    Combiner(CombinerConfig) = "combiner",
        "Learned per-pixel weights over the prior and L1 on the prior (two data-term weights), through ONNX Runtime";
    Auto(AutoConfig) = "auto",
        "Picks per frame and says why: L1 on the prior when a prior is given or OIDN loads, else gradnet, frgr or l1, by what can run here and what the frame carries";
    #[cfg(feature = "testing")]
    Copy(CopyConfig) = "copy",
        "Test-only: the base image scaled by a gain (shows how a method is registered)";
}

/// [`Register`]'s object-safe part, so [`MethodConfig`] dispatches once.
trait RegisterDyn {
    fn plan_dyn(
        &self,
        context: &Context,
        width: usize,
        height: usize,
    ) -> Result<Box<dyn Reconstructor>>;
    fn gradnet_dyn(&mut self) -> Option<&mut GradNetConfig>;
    fn runtime_dyn(&mut self) -> Option<&mut Option<PathBuf>>;
    fn memory_dyn(&self, width: usize, height: usize) -> u64;
    fn fit_memory_dyn(&mut self, width: usize, height: usize, limit: u64);
}

impl<C: Register> RegisterDyn for C {
    fn plan_dyn(
        &self,
        context: &Context,
        width: usize,
        height: usize,
    ) -> Result<Box<dyn Reconstructor>> {
        // The one place a configuration is checked (fields set directly in Rust included).
        param::validate(self)?;
        self.plan(context, width, height)
    }

    fn gradnet_dyn(&mut self) -> Option<&mut GradNetConfig> {
        self.gradnet_mut()
    }

    fn runtime_dyn(&mut self) -> Option<&mut Option<PathBuf>> {
        self.runtime_mut()
    }

    fn memory_dyn(&self, width: usize, height: usize) -> u64 {
        self.memory_estimate(width, height)
    }

    fn fit_memory_dyn(&mut self, width: usize, height: usize, limit: u64) {
        fit_within(self, width, height, limit);
    }
}

impl fmt::Display for Method {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Method {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        Method::ALL
            .into_iter()
            .find(|m| m.name().eq_ignore_ascii_case(s))
            .ok_or_else(|| {
                Error::arg(format!(
                    "unknown method '{s}', expected one of: {}",
                    Method::ALL.map(Method::name).join(", ")
                ))
            })
    }
}

impl MethodConfig {
    /// The description of parameter `name` of this method.
    pub fn param(&self, name: &str) -> Result<ParamInfo> {
        let method = self.method();
        let infos = method.params();
        match infos.iter().find(|i| i.name == name) {
            Some(info) => Ok(info.clone()),
            None => Err(param::unknown(method.name(), name, &infos)),
        }
    }

    /// The value of parameter `name` (a choice as its index).
    pub fn get(&self, name: &str) -> Result<Value> {
        let info = self.param(name)?;
        Ok(self
            .read(&info.name)
            .expect("listed parameters can be read"))
    }

    /// Sets parameter `name`, checking its type and range against the method's table.
    pub fn set(&mut self, name: &str, value: Value) -> Result<()> {
        let value = self.param(name)?.check(value)?;
        self.write_checked(name, value);
        Ok(())
    }

    /// Writes a value its [`ParamInfo`] accepted.
    fn write_checked(&mut self, name: &str, value: Value) {
        let written = self.write(name, value);
        debug_assert!(written, "listed parameters can be written");
    }

    /// Sets parameter `name` from text (`"0.3"`, `"true"`, a choice's name), as the CLI's
    /// `--param name=value` and bench variants do.
    pub fn set_text(&mut self, name: &str, text: &str) -> Result<()> {
        let value = self.param(name)?.parse(text)?;
        self.write_checked(name, value);
        Ok(())
    }

    /// Sets `name=value` (the form `--param` takes).
    pub fn set_assignment(&mut self, assignment: &str) -> Result<()> {
        match assignment.split_once('=') {
            Some((name, value)) => self.set_text(name.trim(), value),
            None => Err(Error::arg(format!(
                "parameter '{assignment}' has no value: write NAME=VALUE"
            ))),
        }
    }

    /// The GradNet settings this configuration uses (`gradnet`, and `auto`'s), to set the
    /// runtime library and model paths; `None` for methods that never run GradNet.
    pub fn gradnet_mut(&mut self) -> Option<&mut GradNetConfig> {
        self.register().gradnet_dyn()
    }

    /// The ONNX Runtime library path of a configuration that runs a network (`gradnet`,
    /// `combiner`, `auto`): what the CLI's `--onnxruntime` and the C context's
    /// `"onnxruntime_path"` set; `None` for methods that run none.
    pub fn runtime_mut(&mut self) -> Option<&mut Option<PathBuf>> {
        self.register().runtime_dyn()
    }

    /// An upper estimate of the bytes a plan of this configuration for `width` x `height`
    /// frames needs at its peak, beyond the frame: what [`Plan::new`] checks against the
    /// context's `max_memory_mb` and the process's address-space limit.
    pub fn memory_estimate(&self, width: usize, height: usize) -> u64 {
        self.register_ref().memory_dyn(width, height)
    }

    /// This configuration with its tile budgets lowered so that its estimate for `width` x
    /// `height` frames fits in `limit` bytes where tiles can make it fit (GradNet, the
    /// combiner, OIDN on the prior paths, and `auto`'s), as [`Plan::new`] does under the
    /// context's `max_memory_mb` and the address space the process has left; unchanged when
    /// the estimate already fits, and for the methods that do not tile.
    pub fn fitted_to(&self, width: usize, height: usize, limit: u64) -> MethodConfig {
        let mut fitted = self.clone();
        fitted.register().fit_memory_dyn(width, height, limit);
        fitted
    }

    /// This configuration for frames that bring their own prior (a `prior` layer): planned
    /// without Open Image Denoise's scratch, which such frames never allocate, so that a
    /// memory limit leaves the rest of the plan more (every path that can compute a prior; the
    /// others, and `auto`, which sees each frame, unchanged). A plan made from it refuses a
    /// frame without a `prior` layer where it would have run OIDN.
    pub fn given_prior(&self) -> MethodConfig {
        let mut given = self.clone();
        match &mut given {
            MethodConfig::PoissonL2(c) => c.scratch = prior::Scratch::NONE,
            MethodConfig::PoissonL1(c) => c.scratch = prior::Scratch::NONE,
            MethodConfig::Frgr(c) => c.scratch = prior::Scratch::NONE,
            MethodConfig::Prior(c) => c.scratch = prior::Scratch::NONE,
            MethodConfig::Combiner(c) => c.scratch = prior::Scratch::NONE,
            _ => {}
        }
        given
    }

    pub(crate) fn instantiate(
        &self,
        context: &Context,
        width: usize,
        height: usize,
    ) -> Result<Box<dyn Reconstructor>> {
        self.register_ref().plan_dyn(context, width, height)
    }
}

/// A method planned for one frame size on a context: create once, execute per frame.
pub struct Plan {
    context: Context,
    inner: Box<dyn Reconstructor>,
    width: usize,
    height: usize,
}

impl Plan {
    /// Plans `config` for `width` x `height` frames on `context`.
    pub fn new(
        context: &Context,
        config: &MethodConfig,
        width: usize,
        height: usize,
    ) -> Result<Self> {
        if width == 0 || height == 0 {
            return Err(Error::arg(format!(
                "plan size is {width} x {height}: an image needs at least one pixel"
            )));
        }
        // Tiles sized to the limit first: only a plan whose smallest tiles are over it is
        // refused.
        let left = address_space_left();
        let fitted =
            memory_limit(context, left).map(|limit| config.fitted_to(width, height, limit));
        let config = fitted.as_ref().unwrap_or(config);
        check_memory(context, left, config, width, height)?;
        let inner = context.install(|| config.instantiate(context, width, height))?;
        Ok(Plan {
            context: context.clone(),
            inner,
            width,
            height,
        })
    }

    /// The planned method.
    pub fn method(&self) -> Method {
        self.inner.method()
    }

    /// `(width, height)` the plan was made for.
    pub fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// Reconstructs `frame` into `out` (3 channels, planned size), reporting progress.
    ///
    /// Whatever the method does, `out` holds only finite, non-negative values afterwards: any
    /// non-finite value is replaced by the base colour (counted in
    /// [`Report::output_repaired`]) and any negative one by 0 ([`Report::output_clamped`]).
    pub fn execute_into(
        &mut self,
        frame: &Frame,
        out: &mut Image,
        progress: &Progress,
    ) -> Result<Report> {
        let expected = (self.width, self.height);
        if frame.size() != expected {
            return Err(Error::input(format!(
                "frame is {} x {}, but the plan was made for {} x {}",
                frame.width(),
                frame.height(),
                expected.0,
                expected.1
            )));
        }
        if out.size() != expected || out.channels() != 3 {
            return Err(Error::arg(format!(
                "output is {} x {} x {}, expected {} x {} x 3",
                out.width(),
                out.height(),
                out.channels(),
                expected.0,
                expected.1
            )));
        }
        let mut report = Report {
            method: self.method().name().to_owned(),
            sanitized: frame.sanitized().clone(),
            ..Report::default()
        };
        let inner = &mut self.inner;
        self.context.install(|| {
            inner.reconstruct_into(frame, out, &mut report, progress)?;
            (report.output_repaired, report.output_clamped) = repair(out, frame.color());
            Ok::<_, Error>(())
        })?;
        Ok(report)
    }

    /// Reconstructs `frame` into a new image.
    pub fn execute(&mut self, frame: &Frame, progress: &Progress) -> Result<(Image, Report)> {
        let mut out = Image::try_zeros(3, self.width, self.height)?;
        let report = self.execute_into(frame, &mut out, progress)?;
        Ok((out, report))
    }
}

impl fmt::Debug for Plan {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Plan")
            .field("method", &self.method())
            .field("width", &self.width)
            .field("height", &self.height)
            .finish()
    }
}

/// The bytes a plan may take: the context's `max_memory_mb` and the address space `left`
/// under `RLIMIT_AS` ([`address_space_left`]), whichever is less; `None` when neither limits
/// it.
fn memory_limit(context: &Context, left: Option<u64>) -> Option<u64> {
    let set = match context.max_memory_mb() {
        0 => None,
        mb => Some(mb.saturating_mul(MIB)),
    };
    match (set, left) {
        (Some(a), Some(b)) => Some(a.min(b)),
        (a, b) => a.or(b),
    }
}

/// Refuses a plan whose [`MethodConfig::memory_estimate`] exceeds the context's
/// `max_memory_mb` or the address space `left` under `RLIMIT_AS` (read once per plan).
fn check_memory(
    context: &Context,
    left: Option<u64>,
    config: &MethodConfig,
    width: usize,
    height: usize,
) -> Result<()> {
    let estimate = config.memory_estimate(width, height);
    let mib = |b: u64| b.div_ceil(MIB);
    let limit = context.max_memory_mb();
    if limit > 0 && estimate > limit.saturating_mul(MIB) {
        return Err(Error::OutOfMemory(format!(
            "method {} for {width} x {height} needs about {} MiB, more than max_memory_mb = {limit}",
            config.method(),
            mib(estimate)
        )));
    }
    if let Some(left) = left {
        if estimate > left {
            return Err(Error::OutOfMemory(format!(
                "method {} for {width} x {height} needs about {} MiB, more than the {} MiB of \
                 address space a plan may count on under the process's limit (ulimit -v: what \
                 is left, less {} MiB for the libraries and threads it loads)",
                config.method(),
                mib(estimate),
                left / MIB,
                ADDRESS_MARGIN / MIB
            )));
        }
    }
    Ok(())
}

/// Address space a plan's estimate may not count on under `RLIMIT_AS`: estimates are of
/// resident memory, and a plan maps more than it touches once OIDN or ONNX Runtime is loaded
/// (libraries, their threads' stacks and allocator arenas). Measured at 3840 x 2160, peak
/// virtual size less the frame's (`VmPeak`, 1.0 GB after reading) against the estimate:
/// `prior` 1.81 GB against 1.62 GB, `l1` on the prior 2.88 against about 2.5 GB, `l1` 1.13
/// against 1.27, `gradnet` 0.73 against 0.97 (AMD EPYC Zen 4, fifty-ninth session). Without
/// it, `l1 --preset prior` planned under `ulimit -v 3500000` and failed 16 s later allocating
/// an image.
const ADDRESS_MARGIN: u64 = 512 * MIB;

/// What a plan may count on under an address-space limit of `limit` bytes with `used` already
/// mapped: the rest, less [`ADDRESS_MARGIN`].
#[cfg(any(target_os = "linux", test))]
fn address_budget(limit: u64, used: u64) -> u64 {
    limit.saturating_sub(used).saturating_sub(ADDRESS_MARGIN)
}

/// Bytes of address space a plan may count on under `RLIMIT_AS` ([`address_budget`] of the
/// soft limit and the current virtual size), `None` when there is no limit or it cannot be
/// read.
#[cfg(target_os = "linux")]
#[allow(unsafe_code)]
fn address_space_left() -> Option<u64> {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit writes one rlimit through a valid pointer.
    if unsafe { libc::getrlimit(libc::RLIMIT_AS, &mut limit) } != 0
        || limit.rlim_cur == libc::RLIM_INFINITY
    {
        return None;
    }
    // The first field of /proc/self/statm is the virtual size in pages.
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: u64 = statm.split_whitespace().next()?.parse().ok()?;
    // SAFETY: sysconf has no preconditions.
    let page = u64::try_from(unsafe { libc::sysconf(libc::_SC_PAGESIZE) }).ok()?;
    // rlim_t is 32 bits on 32-bit targets.
    #[allow(clippy::unnecessary_cast)]
    let limit = limit.rlim_cur as u64;
    Some(address_budget(limit, pages.saturating_mul(page)))
}

#[cfg(not(target_os = "linux"))]
fn address_space_left() -> Option<u64> {
    None
}

/// Replaces the non-finite values of `out` by the base colour (sanitised: finite and never
/// negative) and its negative values by 0: radiance is never negative, and the projection onto
/// `x >= 0` moves a value closer to any non-negative reference, so no pixel's error rises. On
/// the test split it took `l1`'s `lamps` 4 spp from 1.46x its base image's relMSE to 0.45x
/// (a pixel of -17.7 beside a bulb) and the combiner's from 0.74x OIDN's to 0.25x
/// (`docs/benchmarks.md`, twenty-second session). Returns how many of each it replaced.
pub(crate) fn repair(out: &mut Image, base: &Image) -> (u64, u64) {
    out.as_mut_slice()
        .par_iter_mut()
        .zip(base.as_slice().par_iter())
        .map(|(o, &b)| {
            if !o.is_finite() {
                *o = b;
                (1, 0)
            } else if *o < 0.0 {
                *o = 0.0;
                (0, 1)
            } else {
                (0, 0)
            }
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
}

/// Reconstructs one frame with `config` on a default context (all cores): plans, executes and
/// drops the plan. For repeated frames of one size, keep a [`Plan`] instead.
pub fn reconstruct(frame: &Frame, config: &MethodConfig) -> Result<(Image, Report)> {
    let context = Context::new(Default::default())?;
    Plan::new(&context, config, frame.width(), frame.height())?.execute(frame, &Progress::none())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Under an address-space limit a plan counts on what is left less the margin, and on
    /// nothing once the margin is not left.
    #[test]
    fn the_address_budget_keeps_a_margin() {
        let gib = 1 << 30;
        assert_eq!(address_budget(4 * gib, gib), 3 * gib - ADDRESS_MARGIN);
        assert_eq!(address_budget(gib, gib - ADDRESS_MARGIN / 2), 0);
        assert_eq!(address_budget(gib, 2 * gib), 0);
    }

    /// Non-finite values take the base colour, negative ones 0, the rest stay; both counted.
    #[test]
    fn repair_makes_the_output_finite_and_non_negative() {
        let base = Image::from_fn(3, 4, 2, |(c, x, y)| 0.25 * (c + x + y) as f32);
        let values = [
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            -3.0,
            -0.0,
            0.0,
            2.5,
        ];
        let mut out = Image::from_fn(3, 4, 2, |(c, x, y)| values[(c * 8 + y * 4 + x) % 7]);
        let before = out.clone();
        let (repaired, clamped) = repair(&mut out, &base);
        let (mut want_repaired, mut want_clamped) = (0, 0);
        for (i, (&o, &b)) in before.as_slice().iter().zip(base.as_slice()).enumerate() {
            let got = out.as_slice()[i];
            if !o.is_finite() {
                want_repaired += 1;
                assert_eq!(got, b);
            } else if o < 0.0 {
                want_clamped += 1;
                assert_eq!(got, 0.0);
            } else {
                assert_eq!(got.to_bits(), o.to_bits());
            }
        }
        assert_eq!((repaired, clamped), (want_repaired, want_clamped));
        assert!(repaired > 0 && clamped > 0);
    }
}
