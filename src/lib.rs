//! # gdrecon: reconstruction for gradient-domain Monte Carlo rendering
//!
//! A gradient-domain renderer outputs a noisy base image `I_b`, gradient images `dx` and `dy`,
//! and cheap feature buffers. gdrecon turns them into a clean image with one of several
//! methods behind one interface.
//!
//! The pipeline is visible in the module list:
//! 1. [`io`]: read a frame bundle (multi-layer OpenEXR), write results and previews;
//! 2. [`frame`] and [`validate`]: build a validated, sanitised [`Frame`] (conventions are
//!    stated once, in [`frame`]);
//! 3. [`recon`]: plan a [`Method`] for a size on a [`Context`] and execute it per frame;
//! 4. [`metrics`]: compare with a reference (relMSE, MSE, PSNR).
//!
//! ```no_run
//! use gdrecon::{io, recon, validate::Policy, Method, MethodConfig};
//!
//! let frame = io::read_bundle("frame.exr", Policy::Replace)?;
//! let (image, report) = recon::reconstruct(&frame, &MethodConfig::default_for(Method::PoissonL2))?;
//! io::write_rgb("out.exr", &image)?;
//! println!("{report}");
//! # Ok::<(), gdrecon::Error>(())
//! ```
#![deny(unsafe_code)]
#![warn(missing_docs)]

#[allow(unsafe_code)]
pub mod capi;
pub mod context;
#[cfg(any(feature = "gradnet", feature = "oidn"))]
mod dylib;
pub mod error;
pub mod frame;
pub mod image;
pub mod io;
pub mod metrics;
pub mod progress;
pub mod recon;
pub mod report;
pub mod synth;
pub mod validate;

pub use context::{Context, ContextOptions};
pub use error::{Error, Result};
pub use frame::{Frame, FrameBuilder, Layer};
pub use image::Image;
pub use metrics::Metrics;
pub use progress::Progress;
pub use recon::{Method, MethodConfig, Plan};
pub use report::Report;
pub use validate::Policy;

// What a renderer may share between threads or move to a worker, checked at compile time: a
// context, frames, images, configurations and reports are `Send + Sync`; a plan is `Send` (one
// thread executes it at a time, as `execute` takes `&mut self`).
const _: () = {
    const fn send_sync<T: Send + Sync>() {}
    const fn send<T: Send>() {}
    send_sync::<Context>();
    send_sync::<Frame>();
    send_sync::<Image>();
    send_sync::<MethodConfig>();
    send_sync::<Report>();
    send_sync::<Error>();
    send::<Plan>();
};
