//! `auto`: picks a method per frame from what the frame carries, and says why.
//!
//! The rule, from the validation set (six scenes at 4, 16 and 64 spp; `docs/benchmarks.md`):
//! 1. **spp known → `frgr`** (RDFC guide). It has the lowest geometric-mean relMSE at 4 and
//!    16 spp and is within 6 % of the best (the same method with an L1 guide) at 64 spp, and it
//!    is the only method that is never far off on any scene (caustics included). A missing
//!    variance layer is estimated by FRGR itself (3 x 3 colour statistics; noted).
//! 2. **spp unknown → `gradnet`**, which needs no sample count: on the validation set it is 0.54x
//!    L1 at 4 spp and on par at 16 spp. The frame's features decide the model (with or without
//!    the feature branch).
//! 3. **GradNet unavailable** (built without it, or ONNX Runtime not found) **→ `l1`**, the most
//!    robust of the remaining methods; the reason GradNet could not run is part of the note.
//!
//! The chosen method is planned on the first frame that needs it and kept: a sequence of
//! frames of one kind plans once.

use super::param::{ParamInfo, Settings, Value};
use super::{
    FrgrConfig, GradNetConfig, Method, MethodConfig, PoissonL1Config, Reconstructor, Register,
};
use crate::context::Context;
use crate::error::Result;
use crate::frame::Frame;
use crate::image::Image;
use crate::progress::Progress;
use crate::report::Report;

/// Settings of [`Auto`]: the configurations it chooses between.
#[derive(Clone, Debug, PartialEq, Default)]
#[non_exhaustive]
pub struct AutoConfig {
    /// Used when the frame has its spp.
    pub frgr: FrgrConfig,
    /// Used when it has not, if GradNet can run.
    pub gradnet: GradNetConfig,
    /// The fallback.
    pub l1: PoissonL1Config,
}

impl AutoConfig {
    /// The method `frame` gets, and why (before checking that GradNet can run).
    pub fn choose(&self, frame: &Frame) -> (MethodConfig, String) {
        match frame.spp() {
            Some(spp) => (
                MethodConfig::Frgr(self.frgr),
                format!(
                    "spp {spp} is known: frgr (lowest validation relMSE at 4 and 16 spp, \
                     within 6 % of the best at 64){}",
                    if frame.variance().is_some() {
                        ""
                    } else {
                        "; no variance layer: frgr estimates it"
                    }
                ),
            ),
            None => (
                MethodConfig::GradNet(self.gradnet.clone()),
                format!(
                    "spp unknown: gradnet ({} features)",
                    if frame.albedo().is_some()
                        && frame.normal().is_some()
                        && frame.depth().is_some()
                    {
                        "with"
                    } else {
                        "without"
                    }
                ),
            ),
        }
    }
}

/// `auto`'s parameters are those of the methods it chooses between, named `frgr.radius`,
/// `gradnet.tile_size`, `l1.alpha`, ...
impl Settings for AutoConfig {
    fn infos(prefix: &str) -> Vec<ParamInfo> {
        let mut all = FrgrConfig::infos(&format!("{prefix}frgr."));
        all.extend(GradNetConfig::infos(&format!("{prefix}gradnet.")));
        all.extend(PoissonL1Config::infos(&format!("{prefix}l1.")));
        all
    }

    fn read(&self, name: &str) -> Option<Value> {
        match name.split_once('.')? {
            ("frgr", rest) => self.frgr.read(rest),
            ("gradnet", rest) => self.gradnet.read(rest),
            ("l1", rest) => self.l1.read(rest),
            _ => None,
        }
    }

    fn write(&mut self, name: &str, value: Value) -> bool {
        match name.split_once('.') {
            Some(("frgr", rest)) => self.frgr.write(rest, value),
            Some(("gradnet", rest)) => self.gradnet.write(rest, value),
            Some(("l1", rest)) => self.l1.write(rest, value),
            _ => false,
        }
    }

    fn preset(_name: &str) -> Option<Self> {
        None
    }

    fn presets() -> Vec<(String, &'static str)> {
        Vec::new()
    }
}

impl Register for AutoConfig {
    fn plan(
        &self,
        context: &Context,
        width: usize,
        height: usize,
    ) -> Result<Box<dyn Reconstructor>> {
        Ok(Box::new(Auto::new(self.clone(), context, width, height)))
    }

    fn gradnet_mut(&mut self) -> Option<&mut GradNetConfig> {
        Some(&mut self.gradnet)
    }
}

/// The `auto` method planned for one size.
pub(crate) struct Auto {
    config: AutoConfig,
    context: Context,
    width: usize,
    height: usize,
    /// Plans made so far, by method; GradNet's failure to load is remembered too.
    plans: Vec<(Method, Box<dyn Reconstructor>)>,
    gradnet_error: Option<String>,
}

impl Auto {
    /// Plans nothing yet: the choice depends on the frames.
    pub(crate) fn new(config: AutoConfig, context: &Context, width: usize, height: usize) -> Self {
        Auto {
            config,
            context: context.clone(),
            width,
            height,
            plans: Vec::new(),
            gradnet_error: None,
        }
    }

    fn plan(&mut self, config: &MethodConfig) -> Result<&mut Box<dyn Reconstructor>> {
        let method = config.method();
        if let Some(i) = self.plans.iter().position(|(m, _)| *m == method) {
            return Ok(&mut self.plans[i].1);
        }
        let inner = config.instantiate(&self.context, self.width, self.height)?;
        self.plans.push((method, inner));
        Ok(&mut self.plans.last_mut().expect("just pushed").1)
    }
}

impl Reconstructor for Auto {
    fn method(&self) -> Method {
        Method::Auto
    }

    fn reconstruct_into(
        &mut self,
        frame: &Frame,
        out: &mut Image,
        report: &mut Report,
        progress: &Progress,
    ) -> Result<()> {
        let (mut choice, mut reason) = self.config.choose(frame);
        if choice.method() == Method::GradNet {
            if self.gradnet_error.is_none() {
                if let Err(e) = self.plan(&choice) {
                    self.gradnet_error = Some(e.to_string());
                }
            }
            if let Some(why) = &self.gradnet_error {
                let first_line = why.lines().next().unwrap_or_default();
                reason = format!("spp unknown and GradNet cannot run ({first_line}): l1");
                choice = MethodConfig::PoissonL1(self.config.l1);
            }
        }
        report.note(format!("auto: {reason}"));
        report.method = format!("auto -> {}", choice.method());
        self.plan(&choice)?
            .reconstruct_into(frame, out, report, progress)
    }
}
