//! `copy` (cargo feature `testing` only): the base image times a gain.
//!
//! It exists to show, and test, what registering a method takes: this file (a configuration
//! with its parameter table, a planned type implementing `Reconstructor`) and one line in
//! `registry!` in `recon/mod.rs`. `tests/registry.rs` then finds it in `gdrecon params`,
//! `reconstruct`, `bench` and the C API without any of them naming it.

use super::param::{Param, Params, Preset, Range};
use super::{Method, Reconstructor, Register};
use crate::context::Context;
use crate::error::Result;
use crate::frame::Frame;
use crate::image::Image;
use crate::progress::Progress;
use crate::report::Report;

/// Settings of `copy`.
#[derive(Clone, Copy, Debug, PartialEq)]
#[non_exhaustive]
pub struct CopyConfig {
    /// Factor applied to the base image.
    pub gain: f32,
}

impl Default for CopyConfig {
    fn default() -> Self {
        CopyConfig { gain: 1.0 }
    }
}

impl Params for CopyConfig {
    const TABLE: &'static [Param<Self>] = &[Param::float(
        "gain",
        Range::closed(0.0, 100.0),
        "Factor applied to the base image",
        |c| c.gain,
        |c, v| c.gain = v,
    )];

    const PRESETS: &'static [Preset<Self>] = &[Preset {
        name: "double",
        doc: "a gain of 2",
        config: || CopyConfig { gain: 2.0 },
    }];
}

impl Register for CopyConfig {
    const SWEEP: &'static [&'static str] = &["", "gain=0.5"];

    fn plan(
        &self,
        _context: &Context,
        _width: usize,
        _height: usize,
    ) -> Result<Box<dyn Reconstructor>> {
        Ok(Box::new(Copy { gain: self.gain }))
    }

    fn memory_estimate(&self, width: usize, height: usize) -> u64 {
        // The output alone.
        super::bytes_for(width, height, 12, 0)
    }
}

/// `copy` planned (it needs no buffers).
struct Copy {
    gain: f32,
}

impl Reconstructor for Copy {
    fn method(&self) -> Method {
        Method::Copy
    }

    fn reconstruct_into(
        &mut self,
        frame: &Frame,
        out: &mut Image,
        report: &mut Report,
        progress: &Progress,
    ) -> Result<()> {
        let gain = self.gain;
        report.time("copy", || {
            for (o, &b) in out.as_mut_slice().iter_mut().zip(frame.color().as_slice()) {
                *o = gain * b;
            }
        });
        progress.update(1.0)
    }
}
