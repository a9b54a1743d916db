//! `auto`: picks a method per frame from what the frame carries, and says why.
//!
//! The rule, from the validation set (`docs/benchmarks.md`):
//! 0. **a prior → the combiner** (learned weights over the prior and L1 on it), or **`l1` on
//!    the prior** (preset `prior`) when the combiner cannot run (built without ONNX Runtime,
//!    the runtime or the model not found, or the frame lacks variance, albedo or normal) or
//!    `use_combiner` is false; taken when the frame has a `prior` layer or Open Image Denoise
//!    can be loaded. (The notes quote the ten-family validation split of the fifty-fifth
//!    session, `docs/bench/val/`: combiner 0.69 / 0.63 / 0.57x OIDN, L1 on the prior 0.83 /
//!    0.78 / 0.69x, GradNet 0.54 / 0.48 / 0.70x FRGR.) On the eight-family validation split
//!    of the twenty-first session the combiner was 0.77 / 0.77 / 0.66x OIDN alone
//!    (geometric mean at 4 / 16 / 64 spp) with no frame above 1.03x; L1 on the prior 0.88 /
//!    0.85 / 0.78x (worst 1.02x); both better than every method without a prior (the best of
//!    them, GradNet, is 1.45 / 0.91 / 0.96x OIDN there). The combiner became the default in
//!    the twenty-first session, once no validation frame was worse than OIDN alone by more
//!    than #16's 5 % (`docs/benchmarks.md`). Why the combiner or OIDN could not run is part of
//!    the note when it falls through.
//! 1. **no prior → `gradnet`** when ONNX Runtime and the model load. The GPU-trained model
//!    (nineteenth session), fine-tuned against references (thirty-eighth), is 0.65 / 0.50 /
//!    0.73x FRGR's relMSE at 4 / 16 / 64 spp on the validation split (geometric mean; 0.55 /
//!    0.56 / 0.75 on test) and needs no sample count. The frame's features decide the model
//!    (with or without the feature branch).
//! 2. **GradNet unavailable** (built without it, or ONNX Runtime or the model not found) **→
//!    `frgr`** (RDFC guide) when the spp is known: the best method without a runtime. A
//!    missing variance layer is estimated by FRGR itself (3 x 3 colour statistics; noted).
//! 3. **neither → `l1`**, the most robust of the remaining methods. Why GradNet could not run
//!    is part of the note.
//!
//! Under a memory limit (`max_memory_mb`, or the address space left under `ulimit -v`) each
//! path is fitted to it (smaller tiles), and a path still over it is left out as a path whose
//! library is missing is: the frame takes the next rule, and the note says what that path
//! needs (`no combiner (needs about 2783 MiB, more than the limit of 2000 MiB)`). A plan is
//! refused only when no path fits (naming the smallest need), and a frame whose rules lead
//! only to paths left out gets `Error::OutOfMemory` saying so (GradNet not loading where only
//! it fits). With `fallback` false nothing is left out, and a plan any of whose paths is over
//! the limit is refused. A frame that brings its own prior (a `prior` layer) is held to the
//! prior paths' needs without Open Image Denoise's scratch, which it never allocates: under a
//! limit that leaves OIDN out it still takes the combiner (in tiles fitted without that
//! scratch) or L1 on its prior. Under a limit one path's plan is held at a time: a frame that
//! takes another path than the last gives the last one's plan back first.
//!
//! The chosen method is planned on the first frame that needs it and kept: a sequence of
//! frames of one kind plans once. The report names the method that ran (`auto -> combiner`)
//! and why. A render farm that must give every node the same image sets `fallback` to false:
//! a frame whose preferred path cannot run on this machine (OIDN or ONNX Runtime missing) is
//! then an error instead of another method's image.

use super::param::{Param, ParamInfo, Params, Settings, Value};
use super::prior::Scratch;
use super::{
    fit_within, CombinerConfig, FrgrConfig, GradNetConfig, Method, MethodConfig, PoissonL1Config,
    Reconstructor, Register, MIB,
};
use crate::context::Context;
use crate::error::{Error, Result};
use crate::frame::Frame;
use crate::image::Image;
use crate::progress::Progress;
use crate::report::Report;

/// Settings of `Auto`: the configurations it chooses between.
#[derive(Clone, Debug, PartialEq)]
#[non_exhaustive]
pub struct AutoConfig {
    /// Used without a prior, when GradNet cannot run and the frame has its spp.
    pub frgr: FrgrConfig,
    /// Used without a prior, when it can run.
    pub gradnet: GradNetConfig,
    /// The fallback.
    pub l1: PoissonL1Config,
    /// Used whenever a prior is given or can be computed ([`PoissonL1Config::prior`]), when
    /// the combiner cannot run.
    pub prior: PoissonL1Config,
    /// Used whenever a prior is given or can be computed, ONNX Runtime loads and the frame
    /// has variance, albedo and normal (its runtime path is `gradnet`'s).
    pub combiner: CombinerConfig,
    /// Take the prior path when a prior is given or Open Image Denoise loads (rule 0).
    pub use_prior: bool,
    /// On the prior path, run the combiner when it can run.
    pub use_combiner: bool,
    /// Fall back to the next rule when the preferred path cannot run here (the default);
    /// false: fail instead, so that one frame gives one image on every machine.
    pub fallback: bool,
    /// The memory limit the paths were fitted to (set by [`Register::fit_memory`] when
    /// `fallback` is set): a path whose estimate is still over it is left out
    /// ([`AutoConfig::over`]).
    limit: Option<u64>,
    /// The combiner fitted for frames that bring their own prior (no OIDN scratch), set
    /// beside the limit when the one fitted with the scratch is still over it: only such
    /// frames can take the combiner then, in the larger tiles this leaves them.
    given: Option<CombinerConfig>,
}

/// `auto`'s own switch, declared in a table like every parameter.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Rules {
    use_prior: bool,
    use_combiner: bool,
    fallback: bool,
}

impl Default for Rules {
    fn default() -> Self {
        Rules {
            use_prior: true,
            use_combiner: true,
            fallback: true,
        }
    }
}

impl Params for Rules {
    const TABLE: &'static [Param<Self>] = &[
        Param::bool(
            "use_prior",
            "Take the prior path (the combiner, or l1 on the prior) when the frame has a 'prior' \
             layer or Open Image Denoise loads; false: never load OIDN, pick among frgr, gradnet \
             and l1",
            |c| c.use_prior,
            |c, v| c.use_prior = v,
        ),
        Param::bool(
            "use_combiner",
            "On the prior path, run the combiner (learned weights over the prior and L1 on it) \
             when ONNX Runtime loads and the frame has variance, albedo and normal; false, or \
             when it cannot run: L1 on the prior",
            |c| c.use_combiner,
            |c, v| c.use_combiner = v,
        ),
        Param::bool(
            "fallback",
            "When the preferred path cannot run here (Open Image Denoise or ONNX Runtime \
             missing, or over the memory limit even in its smallest tiles), take the next \
             rule's method; false: fail instead, so one frame gives one image on every machine",
            |c| c.fallback,
            |c, v| c.fallback = v,
        ),
    ];
}

impl Default for AutoConfig {
    fn default() -> Self {
        AutoConfig {
            frgr: FrgrConfig::default(),
            gradnet: GradNetConfig::default(),
            l1: PoissonL1Config::default(),
            prior: PoissonL1Config::prior(),
            combiner: CombinerConfig::default(),
            use_prior: Rules::default().use_prior,
            use_combiner: Rules::default().use_combiner,
            fallback: Rules::default().fallback,
            limit: None,
            given: None,
        }
    }
}

impl AutoConfig {
    fn rules(&self) -> Rules {
        Rules {
            use_prior: self.use_prior,
            use_combiner: self.use_combiner,
            fallback: self.fallback,
        }
    }

    /// Why `path` is left out under the memory limit it was fitted to, `None` when it fits
    /// (or there is none): "needs about N MiB, more than the limit of L MiB".
    fn over(&self, path: &MethodConfig, width: usize, height: usize) -> Option<String> {
        let limit = self.limit?;
        let estimate = path.memory_estimate(width, height);
        (estimate > limit).then(|| {
            format!(
                "needs about {} MiB, more than the limit of {} MiB",
                estimate.div_ceil(MIB),
                limit / MIB
            )
        })
    }

    /// The combiner's settings with `gradnet`'s runtime path.
    fn combiner(&self) -> CombinerConfig {
        self.with_runtime(&self.combiner)
    }

    /// The combiner as `frame` runs it: fitted without OIDN's scratch when it brings its own
    /// prior and a limit left out the combiner that counts it.
    fn combiner_for(&self, frame: &Frame) -> CombinerConfig {
        match (&self.given, frame.prior()) {
            (Some(given), Some(_)) => self.with_runtime(given),
            _ => self.combiner(),
        }
    }

    /// `combiner` with GradNet's runtime path, which it shares.
    fn with_runtime(&self, combiner: &CombinerConfig) -> CombinerConfig {
        let mut combiner = combiner.clone();
        combiner.runtime.clone_from(&self.gradnet.runtime);
        combiner
    }

    /// The method `frame` gets without a prior, and why (before checking that GradNet can
    /// run: see [`AutoConfig::without_gradnet`]).
    pub fn choose(&self, frame: &Frame) -> (MethodConfig, String) {
        (
            MethodConfig::GradNet(self.gradnet.clone()),
            format!(
                "gradnet ({} features; 0.48-0.70x frgr's relMSE on the validation split)",
                if frame.albedo().is_some() && frame.normal().is_some() && frame.depth().is_some() {
                    "with"
                } else {
                    "without"
                }
            ),
        )
    }

    /// The method `frame` gets when GradNet cannot run, and why.
    pub fn without_gradnet(&self, frame: &Frame) -> (MethodConfig, String) {
        match frame.spp() {
            Some(spp) => (
                MethodConfig::Frgr(self.frgr),
                format!(
                    "spp {spp} is known: frgr{}",
                    if frame.variance().is_some() {
                        ""
                    } else {
                        " (no variance layer: frgr estimates it)"
                    }
                ),
            ),
            None => (
                MethodConfig::PoissonL1(self.l1),
                "spp unknown: l1".to_owned(),
            ),
        }
    }
}

/// `auto`'s parameters are those of the methods it chooses between, named `frgr.radius`,
/// `gradnet.tile_pixels`, `l1.alpha`, `prior.prior_alpha` (the prior path's L1), ...
impl Settings for AutoConfig {
    fn infos(prefix: &str) -> Vec<ParamInfo> {
        let mut all = Rules::infos(prefix);
        let mut prior = PoissonL1Config::infos(&format!("{prefix}prior."));
        // The prior path's table lists the L1 defaults; its own are those of the preset.
        let preset = PoissonL1Config::prior();
        for info in &mut prior {
            let own = info.name.rsplit('.').next().unwrap_or_default();
            if let Some(v) = preset.read(own) {
                info.default = v;
            }
        }
        all.extend(prior);
        all.extend(CombinerConfig::infos(&format!("{prefix}combiner.")));
        all.extend(FrgrConfig::infos(&format!("{prefix}frgr.")));
        all.extend(GradNetConfig::infos(&format!("{prefix}gradnet.")));
        all.extend(PoissonL1Config::infos(&format!("{prefix}l1.")));
        all
    }

    fn read(&self, name: &str) -> Option<Value> {
        if !name.contains('.') {
            return self.rules().read(name);
        }
        match name.split_once('.')? {
            ("prior", rest) => self.prior.read(rest),
            ("combiner", rest) => self.combiner.read(rest),
            ("frgr", rest) => self.frgr.read(rest),
            ("gradnet", rest) => self.gradnet.read(rest),
            ("l1", rest) => self.l1.read(rest),
            _ => None,
        }
    }

    fn write(&mut self, name: &str, value: Value) -> bool {
        if !name.contains('.') {
            let mut rules = self.rules();
            let written = rules.write(name, value);
            (self.use_prior, self.use_combiner, self.fallback) =
                (rules.use_prior, rules.use_combiner, rules.fallback);
            return written;
        }
        match name.split_once('.') {
            Some(("prior", rest)) => self.prior.write(rest, value),
            Some(("combiner", rest)) => self.combiner.write(rest, value),
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
        Ok(Box::new(Auto::new(self.clone(), context, width, height)?))
    }

    fn gradnet_mut(&mut self) -> Option<&mut GradNetConfig> {
        Some(&mut self.gradnet)
    }

    fn runtime_mut(&mut self) -> Option<&mut Option<std::path::PathBuf>> {
        Some(&mut self.gradnet.runtime)
    }

    /// The largest of the paths it may plan (a frame's choice is made at execute), leaving
    /// out those switched off (`use_prior`, `use_combiner`) and those a memory limit left out
    /// (when it left out all, the smallest: what a plan needs at least): one path, as one
    /// frame takes. Without a limit, plans made for earlier frames are kept, so a sequence
    /// whose frames take different paths can hold more than this; under one, a frame that
    /// takes another path gives the plan it holds back first.
    fn memory_estimate(&self, width: usize, height: usize) -> u64 {
        let (prior, combiner) = (self.use_prior, self.use_prior && self.use_combiner);
        let estimates: Vec<u64> = [
            (MethodConfig::Frgr(self.frgr), true),
            (MethodConfig::GradNet(self.gradnet.clone()), true),
            (MethodConfig::PoissonL1(self.l1), true),
            (MethodConfig::PoissonL1(self.prior), prior),
            (MethodConfig::Combiner(self.combiner()), combiner),
        ]
        .into_iter()
        .filter(|(_, used)| *used)
        .map(|(path, _)| path.memory_estimate(width, height))
        .collect();
        let fits = |e: &u64| self.limit.is_none_or(|limit| *e <= limit);
        match estimates.iter().copied().filter(fits).max() {
            Some(most) => most,
            None => estimates.iter().copied().min().unwrap_or(0),
        }
    }

    /// Fits each path over the limit on its own, as the estimate takes the largest; then,
    /// with `fallback` set, keeps the limit, so that each path still over it is left out, as
    /// a path whose library is missing is: the frame takes the next rule.
    fn fit_memory(&mut self, width: usize, height: usize, limit: u64) {
        let unfitted = self.combiner.clone();
        fit_within(&mut self.frgr, width, height, limit);
        fit_within(&mut self.gradnet, width, height, limit);
        fit_within(&mut self.l1, width, height, limit);
        fit_within(&mut self.prior, width, height, limit);
        fit_within(&mut self.combiner, width, height, limit);
        if self.fallback {
            self.limit = Some(limit);
            if MethodConfig::Combiner(self.combiner()).memory_estimate(width, height) > limit {
                let mut given = CombinerConfig {
                    scratch: Scratch::NONE,
                    ..unfitted
                };
                fit_within(&mut given, width, height, limit);
                self.given = Some(given);
            }
        }
    }
}

/// The `auto` method planned for one size.
pub(crate) struct Auto {
    config: AutoConfig,
    context: Context,
    width: usize,
    height: usize,
    /// Plans made so far, by path (`prior`, `frgr`, `gradnet`, `l1`); why GradNet or OIDN
    /// could not be loaded is remembered too.
    plans: Vec<(&'static str, Box<dyn Reconstructor>)>,
    gradnet_error: Option<String>,
    combiner_error: Option<String>,
    oidn_error: Option<String>,
}

impl Auto {
    /// Plans the prior path when `use_prior` is set and a memory limit leaves it in (its
    /// buffers, not OIDN, which is loaded by the first frame that needs it), so that its
    /// allocation fails here rather than in an execute, and does not delay a cancel of the
    /// first frame (making a 1280 x 720 L1 plan writes 140 MB: 70 ms; the combiner's, with
    /// one and ONNX Runtime's session, about 0.2 s): the combiner when `use_combiner` is set and it can be planned (else why not is
    /// kept for the notes), L1 on the prior otherwise. The other paths depend on the frames
    /// and are planned by the first frame that takes them.
    pub(crate) fn new(
        config: AutoConfig,
        context: &Context,
        width: usize,
        height: usize,
    ) -> Result<Self> {
        let mut auto = Auto {
            context: context.clone(),
            width,
            height,
            plans: Vec::new(),
            // A path a memory limit left out is one that cannot run here.
            gradnet_error: config.over(
                &MethodConfig::GradNet(config.gradnet.clone()),
                width,
                height,
            ),
            combiner_error: None,
            oidn_error: None,
            config,
        };
        let prior = MethodConfig::PoissonL1(auto.config.prior);
        let combiner = MethodConfig::Combiner(auto.config.combiner());
        if auto.config.use_prior && auto.over(&prior).is_none() {
            let planned = auto.config.use_combiner
                && auto.over(&combiner).is_none()
                && auto.combiner_unplanned(&combiner).is_none();
            if !planned {
                auto.plan("prior", &MethodConfig::PoissonL1(auto.config.prior))?;
            }
        }
        Ok(auto)
    }

    /// Why `path` is left out under the memory limit ([`AutoConfig::over`] at this size).
    fn over(&self, path: &MethodConfig) -> Option<String> {
        self.config.over(path, self.width, self.height)
    }

    /// [`Auto::over`] for a path as `frame` runs it: a prior path without OIDN's scratch when
    /// the frame brings its own prior (other paths as they are).
    fn over_for(&self, frame: &Frame, path: &MethodConfig) -> Option<String> {
        match frame.prior() {
            Some(_) => self.over(&path.given_prior()),
            None => self.over(path),
        }
    }

    fn plan(
        &mut self,
        path: &'static str,
        config: &MethodConfig,
    ) -> Result<&mut Box<dyn Reconstructor>> {
        if let Some(i) = self.plans.iter().position(|(p, _)| *p == path) {
            return Ok(&mut self.plans[i].1);
        }
        // Under a memory limit one path's plan at a time: the limit is what one path needs,
        // and a frame that takes another path than the last (or than the one planned ahead)
        // would otherwise hold both.
        if self.config.limit.is_some() {
            self.plans.clear();
        }
        let inner = config.instantiate(&self.context, self.width, self.height)?;
        self.plans.push((path, inner));
        Ok(&mut self.plans.last_mut().expect("just pushed").1)
    }

    /// Whether this frame gets the prior path: it has a prior, or OIDN can be loaded (tried
    /// once; the failure is kept for the notes).
    fn prior_available(&mut self, frame: &Frame) -> std::result::Result<String, String> {
        if frame.prior().is_some() {
            return Ok("the frame has a 'prior' layer".into());
        }
        if self.oidn_error.is_none() {
            #[cfg(feature = "oidn")]
            let loaded = self.context.denoiser().map(|d| {
                format!(
                    "Open Image Denoise computes the prior ({})",
                    d.path().display()
                )
            });
            #[cfg(not(feature = "oidn"))]
            let loaded: Result<String> = Err(crate::Error::Unsupported(
                "built without the 'oidn' feature".into(),
            ));
            match loaded {
                Ok(found) => return Ok(found),
                Err(e) => {
                    self.oidn_error = Some(e.to_string().lines().next().unwrap_or_default().into());
                    // Without OIDN only frames with a prior layer take that path: its plans
                    // are given back, and made again by such a frame.
                    self.plans
                        .retain(|(path, _)| *path != "prior" && *path != "combiner");
                }
            }
        }
        Err(self.oidn_error.clone().unwrap_or_default())
    }
}

impl Auto {
    /// Why this frame cannot take the combiner (`None`: it can): switched off, a layer it
    /// needs is missing, over the memory limit as this frame runs it ([`Auto::over_for`]), or
    /// it could not be planned (ONNX Runtime or the model; tried once, the failure kept).
    fn combiner_blocked(&mut self, frame: &Frame) -> Option<String> {
        if !self.config.use_combiner {
            return Some("use_combiner is false".into());
        }
        let missing: Vec<&str> = [
            ("variance", frame.variance().is_none()),
            ("albedo", frame.albedo().is_none()),
            ("normal", frame.normal().is_none()),
        ]
        .into_iter()
        .filter_map(|(name, absent)| absent.then_some(name))
        .collect();
        if !missing.is_empty() {
            return Some(format!("the frame lacks {}", missing.join(", ")));
        }
        // A limit leaves it out, as a library that does not load does.
        let combiner = MethodConfig::Combiner(self.config.combiner_for(frame));
        if let Some(over) = self.over_for(frame, &combiner) {
            return Some(over);
        }
        self.combiner_unplanned(&combiner)
    }

    /// Plans the combiner unless it is planned already or could not be; why it could not
    /// (ONNX Runtime or the model, or memory; tried once, the failure kept), `None` when it is
    /// planned.
    fn combiner_unplanned(&mut self, choice: &MethodConfig) -> Option<String> {
        if self.combiner_error.is_none() {
            if let Err(e) = self.plan("combiner", choice) {
                self.combiner_error = Some(e.to_string().lines().next().unwrap_or_default().into());
            }
        }
        self.combiner_error.clone()
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
        let available = if !self.config.use_prior {
            Err("use_prior is false".into())
        } else if let Some(over) = self.over_for(frame, &MethodConfig::PoissonL1(self.config.prior))
        {
            Err(format!("the prior path {over}"))
        } else {
            self.prior_available(frame)
        };
        let no_prior = match available {
            Ok(why) => {
                match self.combiner_blocked(frame) {
                    None => {
                        report.note(format!(
                            "auto: {why}: combiner (0.57-0.69x Open Image Denoise alone on \
                             the validation split)"
                        ));
                        report.method = "auto -> combiner".into();
                        let choice = MethodConfig::Combiner(self.config.combiner_for(frame));
                        let plan = self.plan("combiner", &choice)?;
                        progress.check()?;
                        return plan.reconstruct_into(frame, out, report, progress);
                    }
                    Some(blocked) if !self.config.fallback && self.combiner_error.is_some() => {
                        return Err(Error::Unsupported(format!(
                            "auto: the combiner cannot run here ({blocked}), and fallback is false"
                        )));
                    }
                    Some(blocked) => report.note(format!(
                        "auto: {why}; no combiner ({blocked}): l1 on the prior (0.69-0.83x Open \
                         Image Denoise alone on the validation split)"
                    )),
                }
                report.method = "auto -> l1 (prior)".into();
                let choice = MethodConfig::PoissonL1(self.config.prior);
                let plan = self.plan("prior", &choice)?;
                progress.check()?;
                return plan.reconstruct_into(frame, out, report, progress);
            }
            Err(why) => why,
        };
        if self.config.use_prior && !self.config.fallback {
            return Err(Error::Unsupported(format!(
                "auto: the prior path cannot run here ({no_prior}), and fallback is false"
            )));
        }
        let (mut choice, mut reason) = self.config.choose(frame);
        let mut path = "gradnet";
        if self.gradnet_error.is_none() {
            if let Err(e) = self.plan(path, &choice) {
                self.gradnet_error = Some(e.to_string());
            }
        }
        if let Some(why) = &self.gradnet_error {
            let first_line = why.lines().next().unwrap_or_default();
            if !self.config.fallback {
                return Err(Error::Unsupported(format!(
                    "auto: GradNet cannot run here ({first_line}), and fallback is false"
                )));
            }
            let (mut fallback, mut because) = self.config.without_gradnet(frame);
            if let (MethodConfig::Frgr(_), Some(over)) = (&fallback, self.over(&fallback)) {
                because = format!("{because}, but it {over}: l1");
                fallback = MethodConfig::PoissonL1(self.config.l1);
            }
            reason = format!("GradNet cannot run ({first_line}); {because}");
            path = fallback.method().name();
            choice = fallback;
        }
        if let (MethodConfig::PoissonL1(_), Some(over)) = (&choice, self.over(&choice)) {
            return Err(Error::OutOfMemory(format!(
                "auto: no path for this frame fits the memory limit: no prior ({no_prior}); \
                 {reason}, but l1 {over}"
            )));
        }
        report.note(format!("auto: no prior ({no_prior}); {reason}"));
        report.method = format!("auto -> {}", choice.method());
        let plan = self.plan(path, &choice)?;
        // Planning a path the first time takes tens of milliseconds: a cancel meanwhile
        // stops here.
        progress.check()?;
        plan.reconstruct_into(frame, out, report, progress)
    }
}
