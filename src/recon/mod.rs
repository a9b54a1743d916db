//! Reconstruction methods behind one plan/execute interface.
//!
//! Every method is one file implementing [`Reconstructor`]: its constructor builds everything
//! reusable for one frame size (DCT plans, solver buffers, later the ONNX session), and
//! [`Reconstructor::reconstruct_into`] runs without allocating. [`Method`] is the closed
//! registry the CLI and the C ABI dispatch on; [`Plan`] is what callers hold: a method planned
//! for a size, bound to a [`Context`]'s thread pool, with the output guard that keeps NaN and Inf
//! out of every result.

pub mod auto;
pub mod converged;
mod dct;
pub mod filter;
pub mod gradnet;
mod ops;
pub mod poisson_l1;
pub mod poisson_l2;

use std::fmt;
use std::str::FromStr;

use rayon::prelude::*;

pub use auto::{Auto, AutoConfig};
pub use filter::{Filter, FilterConfig, FilterGuide};
#[cfg(feature = "gradnet")]
pub use gradnet::GradNet;
pub use gradnet::GradNetConfig;
pub use poisson_l1::{PoissonL1, PoissonL1Config};
pub use poisson_l2::{PoissonL2, PoissonL2Config};

use crate::context::Context;
use crate::error::{Error, Result};
use crate::frame::Frame;
use crate::image::Image;
use crate::progress::Progress;
use crate::report::Report;

/// A reconstruction method planned for one frame size.
pub trait Reconstructor: Send {
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

/// The methods gdrecon offers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum Method {
    /// Screened Poisson, L2, solved exactly by the DCT (`l2`).
    PoissonL2,
    /// Screened Poisson, group L1, by IRLS with preconditioned CG (`l1`).
    PoissonL1,
    /// Gradient-guided filtering, FRGR (Yan et al. 2024) (`filter`).
    Filter,
    /// GradNet (Guo et al. 2019) through ONNX Runtime (`gradnet`); needs the `gradnet` cargo
    /// feature and the runtime library at run time.
    GradNet,
    /// Picks one of the others per frame from its spp and layers, and says why (`auto`).
    Auto,
}

impl Method {
    /// Every method, in the order the CLI lists them.
    pub const ALL: [Method; 5] = [
        Method::PoissonL2,
        Method::PoissonL1,
        Method::Filter,
        Method::GradNet,
        Method::Auto,
    ];

    /// The CLI / C ABI name.
    pub fn name(self) -> &'static str {
        match self {
            Method::PoissonL2 => "l2",
            Method::PoissonL1 => "l1",
            Method::Filter => "filter",
            Method::GradNet => "gradnet",
            Method::Auto => "auto",
        }
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

/// A method with its settings.
#[derive(Clone, Debug, PartialEq)]
#[non_exhaustive]
pub enum MethodConfig {
    /// See [`PoissonL2Config`].
    PoissonL2(PoissonL2Config),
    /// See [`PoissonL1Config`].
    PoissonL1(PoissonL1Config),
    /// See [`FilterConfig`].
    Filter(FilterConfig),
    /// See [`GradNetConfig`].
    GradNet(GradNetConfig),
    /// See [`AutoConfig`].
    Auto(AutoConfig),
}

impl MethodConfig {
    /// The method's default settings.
    pub fn default_for(method: Method) -> Self {
        match method {
            Method::PoissonL2 => MethodConfig::PoissonL2(PoissonL2Config::default()),
            Method::PoissonL1 => MethodConfig::PoissonL1(PoissonL1Config::default()),
            Method::Filter => MethodConfig::Filter(FilterConfig::default()),
            Method::GradNet => MethodConfig::GradNet(GradNetConfig::default()),
            Method::Auto => MethodConfig::Auto(AutoConfig::default()),
        }
    }

    /// Which method this configures.
    pub fn method(&self) -> Method {
        match self {
            MethodConfig::PoissonL2(_) => Method::PoissonL2,
            MethodConfig::PoissonL1(_) => Method::PoissonL1,
            MethodConfig::Filter(_) => Method::Filter,
            MethodConfig::GradNet(_) => Method::GradNet,
            MethodConfig::Auto(_) => Method::Auto,
        }
    }

    /// Sets the screened Poisson weight, for the methods that have one.
    pub fn with_alpha(mut self, alpha: f32) -> Self {
        match &mut self {
            MethodConfig::PoissonL2(c) => c.alpha = alpha,
            MethodConfig::PoissonL1(c) => c.alpha = alpha,
            MethodConfig::Auto(c) => {
                c.l1.alpha = alpha;
            }
            MethodConfig::Filter(_) | MethodConfig::GradNet(_) => {}
        }
        self
    }

    pub(crate) fn instantiate(
        &self,
        context: &Context,
        width: usize,
        height: usize,
    ) -> Result<Box<dyn Reconstructor>> {
        Ok(match self {
            MethodConfig::PoissonL2(c) => Box::new(PoissonL2::new(*c, width, height)?),
            MethodConfig::PoissonL1(c) => Box::new(PoissonL1::new(*c, width, height)?),
            MethodConfig::Filter(c) => Box::new(Filter::new(*c, width, height)?),
            #[cfg(feature = "gradnet")]
            MethodConfig::GradNet(c) => Box::new(GradNet::new(c.clone(), context, width, height)?),
            MethodConfig::Auto(c) => Box::new(Auto::new(c.clone(), context, width, height)),
            #[cfg(not(feature = "gradnet"))]
            MethodConfig::GradNet(_) => {
                let _ = context;
                return Err(Error::Unsupported(
                    "this build of gdrecon has no GradNet (cargo feature `gradnet` is off)".into(),
                ));
            }
        })
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
    /// Whatever the method does, `out` holds only finite values afterwards: any non-finite
    /// value is replaced by the base colour and counted in [`Report::output_repaired`].
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
            report.output_repaired = repair_non_finite(out, frame.color());
            Ok::<_, Error>(())
        })?;
        Ok(report)
    }

    /// Reconstructs `frame` into a new image.
    pub fn execute(&mut self, frame: &Frame, progress: &Progress) -> Result<(Image, Report)> {
        let mut out = Image::zeros(3, self.height, self.width);
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

/// Replaces non-finite output values by the base colour; returns how many there were.
fn repair_non_finite(out: &mut Image, base: &Image) -> u64 {
    out.as_mut_slice()
        .par_iter_mut()
        .zip(base.as_slice().par_iter())
        .map(|(o, &b)| {
            if o.is_finite() {
                0
            } else {
                *o = b;
                1
            }
        })
        .sum()
}

/// Reconstructs one frame with `config` on a default context (all cores): plans, executes and
/// drops the plan. For repeated frames of one size, keep a [`Plan`] instead.
pub fn reconstruct(frame: &Frame, config: &MethodConfig) -> Result<(Image, Report)> {
    let context = Context::new(Default::default())?;
    Plan::new(&context, config, frame.width(), frame.height())?.execute(frame, &Progress::none())
}
