//! `prior`: the prior alone (the frame's `prior` layer, or Open Image Denoise on the base
//! image), the yardstick every prior path must beat, registered so that it is timed and
//! plotted by `gdrecon bench` beside them.

use super::{Prior, Quality, Scratch};
use crate::context::Context;
use crate::error::Result;
use crate::frame::Frame;
use crate::image::Image;
use crate::progress::Progress;
use crate::recon::param::{Param, Params, Preset};
use crate::recon::{Method, Reconstructor, Register};
use crate::report::Report;

/// Settings of `prior`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub struct PriorConfig {
    /// OIDN's quality when the prior is computed.
    pub quality: Quality,
    /// OIDN's scratch memory when it computes the prior: lowered by a memory limit
    /// ([`Register::fit_memory`]), not a parameter.
    pub(crate) scratch: Scratch,
}

impl Default for PriorConfig {
    fn default() -> Self {
        PriorConfig {
            quality: Quality::High,
            scratch: Scratch::default(),
        }
    }
}

impl Params for PriorConfig {
    const TABLE: &'static [Param<Self>] = &[Param::choice(
        "quality",
        Quality::NAMES,
        "Open Image Denoise's quality when it computes the prior (ignored for a given prior)",
        |c| c.quality.index(),
        |c, v| c.quality = Quality::ALL[v],
    )];

    const PRESETS: &'static [Preset<Self>] = &[];
}

impl Register for PriorConfig {
    const SWEEP: &'static [&'static str] = &["", "quality=balanced"];

    /// Without the `oidn` feature the method runs only on frames that carry a `prior` layer.
    const BUILT: bool = cfg!(feature = "oidn");

    fn plan(
        &self,
        context: &Context,
        width: usize,
        height: usize,
    ) -> Result<Box<dyn Reconstructor>> {
        Ok(Box::new(PriorOnly(Prior::new(
            context,
            width,
            height,
            self.quality,
            self.scratch,
        )?)))
    }

    fn memory_estimate(&self, width: usize, height: usize) -> u64 {
        // OIDN's share and the output.
        super::prior_memory(width, height, self.scratch).saturating_add(output(width, height))
    }

    fn fit_memory(&mut self, width: usize, height: usize, limit: u64) {
        self.scratch
            .fit(width, height, limit, output(width, height));
    }
}

/// The output image's bytes.
fn output(width: usize, height: usize) -> u64 {
    super::super::bytes_for(width, height, 12, 0)
}

/// `prior` planned.
struct PriorOnly(Prior);

impl Reconstructor for PriorOnly {
    fn method(&self) -> Method {
        Method::Prior
    }

    fn reconstruct_into(
        &mut self,
        frame: &Frame,
        out: &mut Image,
        report: &mut Report,
        progress: &Progress,
    ) -> Result<()> {
        let prior = self.0.get(frame, report, progress)?;
        out.as_mut_slice().copy_from_slice(prior.as_slice());
        progress.update(1.0)
    }
}
