//! The prior: a denoiser's output for the frame, which the prior paths of the filter and of
//! screened Poisson build on (the gradients then add what the denoiser missed).
//!
//! A frame's `prior` layer, when the caller gives one, is used as is: a renderer that already
//! ran its denoiser pays nothing more. Otherwise the plan computes it with Intel Open Image
//! Denoise (`oidn`, opened at run time) from the base image as rendered, with the albedo and
//! normal when the frame has them: RT filter, HDR, quality high, auxiliary images not marked
//! clean (OIDN prefilters them), the settings of `python -m gdrecon_py.oidn`, whose output
//! `gdrecon bench --baselines` shows as "oidn". The denoiser must see the base image itself:
//! OIDN assumes uncorrelated pixel noise, which a neighbourhood average of shifted estimates
//! does not have. Its output is confined to [0, max colour] (`confine`): bit-identical to
//! `pyoidn`'s otherwise.
//!
//! Nothing here loads OIDN until a frame without a prior reaches a plan that needs one.

mod method;
#[cfg(feature = "oidn")]
pub(crate) mod oidn;

pub use method::PriorConfig;

use std::borrow::Cow;

use crate::context::Context;
use crate::error::Result;
use crate::frame::{Frame, FrameBuilder, Layer};
use crate::image::Image;
use crate::progress::Progress;
use crate::recon::param::choices;
use crate::recon::{Method, Reconstructor};
use crate::report::Report;
use crate::validate::Policy;

/// OIDN's quality setting (`quality`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum Quality {
    /// Final-frame quality (`OIDN_QUALITY_HIGH`), the default.
    High,
    /// Interactive quality (`OIDN_QUALITY_BALANCED`).
    Balanced,
    /// Preview quality (`OIDN_QUALITY_FAST`).
    Fast,
}

choices!(Quality { High => "high", Balanced => "balanced", Fast => "fast" });

/// The data term of screened Poisson (`data`): what the reconstruction is anchored to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum DataTerm {
    /// The base image `I_b` (the published formulation), with weight `alpha`.
    Colour,
    /// The prior, with weight `prior_alpha`: the gradients add what the denoiser missed.
    Prior,
}

choices!(DataTerm { Colour => "color", Prior => "prior" });

/// The `data` parameter's meaning, shared by the screened Poisson methods' tables.
pub(crate) const DATA_DOC: &str = "What the data term anchors to: the base image (color), or \
     the prior (the frame's 'prior' layer, else Open Image Denoise on the base image) with \
     weight prior_alpha";

/// The `prior_alpha` parameter's meaning, shared likewise.
pub(crate) const PRIOR_ALPHA_DOC: &str =
    "Weight of the data term when it is the prior: residual rows are prior_alpha (I - prior)";

/// OIDN's `maxMemoryMB`, set on every filter: the most scratch memory it may use, beyond
/// which it denoises in tiles. OIDN's own default let a 3840 x 2160 frame take 2.5 GB of
/// scratch; at 1024 it takes 1.0 GB there in the same time (13.8 s against 14.1 s, 2 cores;
/// 512: 0.47 GB, 11 % slower), and frames up to about 2 Mpx (1920 x 1080) are not tiled.
pub(crate) const OIDN_MAX_MEMORY_MB: u64 = 1024;

/// Bytes a [`Prior`] computed by OIDN 2 holds at its peak for a `width` x `height` frame: its
/// four interleaved buffers and planar output (60 B a pixel) and OIDN's own (the library,
/// weights and its tensors, at most [`OIDN_MAX_MEMORY_MB`] of scratch).
///
/// Peak RSS of `gdrecon reconstruct -m prior` (OIDN 2.3, CPU, the demo bundle) minus that of
/// `gdrecon info` on the same bundle (the process, and the frame as read):
///
/// | size | peak RSS | baseline | difference |
/// | --- | --- | --- | --- |
/// | 640 x 360 | 188412 KiB | 51408 KiB | 134 MiB |
/// | 1280 x 720 | 691548 KiB | 180216 KiB | 499 MiB |
///
/// The slope is 554 B a pixel and the intercept 12 MiB; the estimate takes 640 B a pixel (60
/// ours, 580 OIDN's up to its cap) and 64 MiB (OIDN's tile size and its weights vary with the
/// build and the CPU).
///
/// A memory limit lowers the scratch OIDN may take ([`Scratch::fit`]).
pub(crate) fn prior_memory(width: usize, height: usize, scratch: Scratch) -> u64 {
    ours(width, height).saturating_add(
        super::bytes_for(width, height, 580, 0).min(scratch.0.saturating_mul(super::MIB)),
    )
}

/// What an [`OnPrior`] holds beside the solve it wraps: the prior's share ([`prior_memory`])
/// and the [`anchored`] frame's copies of the gradients (6 f32 planes, 24 B a pixel; its colour
/// is the prior, counted there). Without the copies `l1 --preset prior` at 3840 x 2160 peaked
/// 190 MiB beyond its estimate, and over a limit it had been fitted to (`docs/benchmarks.md`,
/// sixtieth session).
pub(crate) fn on_prior_memory(width: usize, height: usize, scratch: Scratch) -> u64 {
    prior_memory(width, height, scratch).saturating_add(gradient_copies(width, height))
}

/// The [`anchored`] frame's gradients.
fn gradient_copies(width: usize, height: usize) -> u64 {
    super::bytes_for(width, height, 24, 0)
}

/// Our share of [`prior_memory`]: the buffers and planar output, and OIDN's fixed part.
fn ours(width: usize, height: usize) -> u64 {
    super::bytes_for(width, height, 60, 64 * super::MIB)
}

/// The least scratch a memory limit lowers OIDN's to. Below it OIDN takes more than it is
/// given: at 3840 x 2160 a `maxMemoryMB` of 512 took 0.5 GB beyond our buffers and 21 % more
/// time than 1024, one of 256 took 0.5 GB as well and 41 % more time (docs/benchmarks.md,
/// "Fifty-eighth session").
pub(crate) const OIDN_LEAST_MB: u64 = 512;

/// The scratch memory, in MiB, OIDN may use in one plan (its `maxMemoryMB`, beyond which it
/// denoises in tiles, the same image): [`OIDN_MAX_MEMORY_MB`] unless a plan's memory limit
/// lowers it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Scratch(u64);

impl Default for Scratch {
    fn default() -> Self {
        Scratch(OIDN_MAX_MEMORY_MB)
    }
}

impl Scratch {
    /// None: no OIDN run, as for a frame that brings its own prior (what `auto` holds such a
    /// frame's prior paths to).
    pub(crate) const NONE: Scratch = Scratch(0);

    /// OIDN's `maxMemoryMB`.
    #[cfg_attr(not(feature = "oidn"), allow(dead_code))]
    pub(crate) fn mb(self) -> u64 {
        self.0
    }

    /// Lowers the scratch to what `limit` bytes leave when the rest of the plan takes `taken`
    /// (the prior's own buffers apart), but not under [`OIDN_LEAST_MB`]; never raises it.
    pub(crate) fn fit(&mut self, width: usize, height: usize, limit: u64, taken: u64) {
        let left = limit.saturating_sub(taken.saturating_add(ours(width, height))) / super::MIB;
        self.0 = self.0.min(left.max(OIDN_LEAST_MB));
    }

    /// [`Scratch::fit`] for an [`OnPrior`] around a solve that holds `own` bytes (see
    /// [`on_prior_memory`]).
    pub(crate) fn fit_on_prior(&mut self, width: usize, height: usize, limit: u64, own: u64) {
        let taken = own.saturating_add(gradient_copies(width, height));
        self.fit(width, height, limit, taken);
    }
}

/// A planned screened Poisson solve run on the prior instead of the base image: each frame is
/// handed to it as the prior (its `color`) and the frame's gradients.
pub(crate) struct OnPrior {
    prior: Prior,
    inner: Box<dyn Reconstructor>,
}

impl OnPrior {
    /// `inner` (planned for `width` x `height`) fed the prior.
    pub(crate) fn new(
        context: &Context,
        width: usize,
        height: usize,
        scratch: Scratch,
        inner: Box<dyn Reconstructor>,
    ) -> Result<Self> {
        Ok(OnPrior {
            prior: Prior::new(context, width, height, Quality::High, scratch)?,
            inner,
        })
    }
}

impl Reconstructor for OnPrior {
    fn method(&self) -> Method {
        self.inner.method()
    }

    fn reconstruct_into(
        &mut self,
        frame: &Frame,
        out: &mut Image,
        report: &mut Report,
        progress: &Progress,
    ) -> Result<()> {
        let prior = match self.prior.get(frame, report, progress)? {
            Cow::Borrowed(given) => given.try_clone()?,
            Cow::Owned(computed) => computed,
        };
        let anchored = anchored(prior, frame)?;
        report.note("data term: the prior");
        self.inner
            .reconstruct_into(&anchored, out, report, progress)
    }
}

/// The frame a screened Poisson solve on the prior reads: `prior` as its colour, and `frame`'s
/// gradients and spp. Only what the solve reads (copying the other layers cost 60 MB and a
/// sanitising pass at 720p). All are already clean (a given prior is sanitised like colour,
/// OIDN's output is confined), so building replaces nothing.
pub(crate) fn anchored(prior: Image, frame: &Frame) -> Result<Frame> {
    FrameBuilder::new()
        .image(Layer::Color, prior)
        .image(Layer::Dx, frame.dx().try_clone()?)
        .image(Layer::Dy, frame.dy().try_clone()?)
        .spp(frame.spp())
        .build(Policy::Replace)
}

/// A plan's source of priors for one frame size.
pub(crate) struct Prior {
    context: Context,
    quality: Quality,
    /// OIDN's scratch memory (read only when OIDN is built in).
    #[cfg_attr(not(feature = "oidn"), allow(dead_code))]
    scratch: Scratch,
    width: usize,
    height: usize,
    /// OIDN's filter and the planar image it writes, made on the first frame without a prior.
    #[cfg(feature = "oidn")]
    computed: Option<(oidn::Runner, Image)>,
    /// The filter's buffers and that image, made by the plan, until the first frame takes them.
    #[cfg(feature = "oidn")]
    made: Option<(oidn::Buffers, Image)>,
}

impl Prior {
    /// A prior source for `width` x `height` frames: OIDN's buffers are made here, the library
    /// is loaded by the first frame without a prior.
    pub(crate) fn new(
        context: &Context,
        width: usize,
        height: usize,
        quality: Quality,
        scratch: Scratch,
    ) -> Result<Self> {
        Ok(Prior {
            context: context.clone(),
            quality,
            scratch,
            width,
            height,
            #[cfg(feature = "oidn")]
            computed: None,
            #[cfg(feature = "oidn")]
            made: Some((
                oidn::Buffers::new(width, height)?,
                Image::try_zeros(3, width, height)?,
            )),
        })
    }

    /// The frame's prior: its `prior` layer when it has one, else OIDN's output on its base
    /// image (timed as the stage "prior (oidn)"; a cancel of `progress` stops OIDN). The report
    /// says which.
    pub(crate) fn get<'a>(
        &'a mut self,
        frame: &'a Frame,
        report: &mut Report,
        progress: &Progress,
    ) -> Result<Cow<'a, Image>> {
        if let Some(given) = frame.prior() {
            report.note("prior: the frame's 'prior' layer (given by the caller)");
            return Ok(Cow::Borrowed(given));
        }
        if self.scratch == Scratch::NONE {
            // Planned without OIDN's scratch (`MethodConfig::given_prior`): running OIDN now
            // would take memory the plan was not held to.
            return Err(crate::Error::input(
                "the plan was made for frames that bring their own prior (a 'prior' layer), \
                 and this frame has none",
            ));
        }
        self.compute(frame, report, progress).map(Cow::Borrowed)
    }

    #[cfg(feature = "oidn")]
    fn compute(
        &mut self,
        frame: &Frame,
        report: &mut Report,
        progress: &Progress,
    ) -> Result<&Image> {
        if self
            .computed
            .as_ref()
            .is_none_or(|(runner, _)| runner.is_lost())
        {
            let device = self.context.denoiser()?;
            let quality = match self.quality {
                Quality::High => oidn::QUALITY_HIGH,
                Quality::Balanced => oidn::QUALITY_BALANCED,
                Quality::Fast => oidn::QUALITY_FAST,
            };
            // A lost runner took its buffers with it: new ones (rare: a thread that died).
            let (buffers, image) = match self.made.take() {
                Some(made) => made,
                None => (
                    oidn::Buffers::new(self.width, self.height)?,
                    Image::try_zeros(3, self.width, self.height)?,
                ),
            };
            let filter = oidn::Filter::new(device, buffers, quality, self.scratch.mb());
            self.computed = Some((oidn::Runner::new(filter), image));
        }
        let (runner, image) = self.computed.as_mut().expect("made above");
        let (albedo, normal) = (frame.albedo(), frame.normal());
        let mut version = 0;
        let mut path = String::new();
        report.time("prior (oidn)", || {
            let filter = runner.filter(progress)?;
            version = filter.version();
            path = filter.path().display().to_string();
            let (c, a, n) = filter.inputs();
            interleave(frame.color(), c, 0.0, f32::MAX);
            if let Some(albedo) = albedo {
                interleave(albedo, a, 0.0, 1.0);
            }
            if let Some(normal) = normal {
                interleave(normal, n, -1.0, 1.0);
            }
            let out = runner.run(albedo.is_some(), normal.is_some(), progress)?;
            deinterleave(out, image);
            Ok::<_, crate::Error>(())
        })?;
        let repaired = confine(image, frame.color());
        if repaired > 0 {
            report.note(format!(
                "prior: {repaired} values of OIDN's output were not finite: the base colour \
                 stands in"
            ));
        }
        report.note(format!(
            "prior: Open Image Denoise {}.{}.{} ({path}), RT filter, hdr, quality {}, {}, \
             scratch {} MiB{}",
            version / 10000,
            version / 100 % 100,
            version % 100,
            Quality::NAMES[self.quality.index()],
            match (albedo.is_some(), normal.is_some()) {
                (true, true) => "albedo + normal",
                (true, false) => "albedo",
                (false, true) => "normal",
                (false, false) => "no auxiliary images",
            },
            self.scratch.mb(),
            if self.scratch == Scratch::default() {
                ""
            } else {
                " (lowered to fit the memory limit)"
            }
        ));
        Ok(image)
    }

    #[cfg(not(feature = "oidn"))]
    fn compute(&mut self, _frame: &Frame, _report: &mut Report, _: &Progress) -> Result<&Image> {
        let _ = (&self.context, self.quality, self.width, self.height);
        Err(crate::Error::Unsupported(
            "this method needs a prior: give the frame a 'prior' layer, or build gdrecon with \
             the 'oidn' feature (Intel Open Image Denoise, loaded at run time)"
                .into(),
        ))
    }
}

/// Copies a planar 3-channel image into an interleaved buffer, clamped to `[lo, hi]` (OIDN
/// expects non-negative colour, albedo in [0, 1] and normals in [-1, 1]).
#[cfg(feature = "oidn")]
fn interleave(image: &Image, out: &mut [f32], lo: f32, hi: f32) {
    use rayon::prelude::*;
    let (w, h) = image.size();
    let plane = w * h;
    let src = image.as_slice();
    debug_assert_eq!(out.len(), 3 * plane);
    out.par_chunks_mut(3 * w).enumerate().for_each(|(y, row)| {
        for (x, px) in row.chunks_exact_mut(3).enumerate() {
            for (c, v) in px.iter_mut().enumerate() {
                *v = src[c * plane + y * w + x].clamp(lo, hi);
            }
        }
    });
}

/// Keeps OIDN's output within what a denoiser of `colour` can mean: in `[0, max colour]`, with
/// non-finite values replaced by the base colour (returns how many). The network can
/// overshoot a little, and on a black frame it answers 3e-4, not 0; a prior above the
/// brightest input would also void the bounds the screened solves keep (tests/stress.rs).
#[cfg(feature = "oidn")]
fn confine(image: &mut Image, colour: &Image) -> u64 {
    use rayon::prelude::*;
    let peak = colour
        .as_slice()
        .par_iter()
        .copied()
        .reduce(|| 0.0, f32::max);
    image
        .as_mut_slice()
        .par_iter_mut()
        .zip(colour.as_slice().par_iter())
        .map(|(p, &c)| {
            if p.is_finite() {
                *p = p.clamp(0.0, peak);
                0
            } else {
                *p = c;
                1
            }
        })
        .sum()
}

/// The inverse of [`interleave`] (no clamping; non-finite output is repaired by the plan).
#[cfg(feature = "oidn")]
fn deinterleave(src: &[f32], image: &mut Image) {
    let (w, h) = image.size();
    for (c, mut plane) in image.planes_mut().outer_iter_mut().enumerate() {
        for y in 0..h {
            for x in 0..w {
                plane[[y, x]] = src[3 * (y * w + x) + c];
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recon::MIB;

    /// Below the cap the estimate is the measured slope (640 B a pixel); above it OIDN's share
    /// stops growing, so a 3840 x 2160 prior path fits a 4 GB `max_memory_mb` (it needed
    /// 5.3 GB before the cap; measured peak now 2.4 GB with the frame, docs/benchmarks.md).
    #[test]
    fn oidn_scratch_is_capped_in_the_estimate() {
        let scratch = Scratch::default();
        assert_eq!(
            prior_memory(1280, 720, scratch),
            1280 * 720 * 640 + 64 * MIB
        );
        let four_k = prior_memory(3840, 2160, scratch);
        assert_eq!(
            four_k,
            3840 * 2160 * 60 + 64 * MIB + OIDN_MAX_MEMORY_MB * MIB
        );
        let l1 = crate::MethodConfig::PoissonL1(crate::recon::PoissonL1Config::prior());
        assert!(l1.memory_estimate(3840, 2160) < 4000 * MIB);
    }
}
