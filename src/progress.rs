//! Progress reporting and cancellation.
//!
//! Methods call [`Progress::update`] between units of work (a CG iteration, a tile) with the
//! fraction done; the caller's callback returns `false` to cancel, and the method returns
//! [`Error::Cancelled`] promptly, leaving the output unspecified.

use crate::error::{Error, Result};

/// The progress callback: receives the fraction done in [0, 1], returns `false` to cancel.
pub type ProgressFn<'a> = dyn Fn(f64) -> bool + Sync + 'a;

/// A progress sink handed to every method.
#[derive(Clone, Copy, Default)]
pub struct Progress<'a> {
    callback: Option<&'a ProgressFn<'a>>,
}

impl<'a> Progress<'a> {
    /// A sink that reports nowhere and never cancels.
    pub fn none() -> Self {
        Progress { callback: None }
    }

    /// A sink that forwards to `callback`.
    pub fn new(callback: &'a ProgressFn<'a>) -> Self {
        Progress {
            callback: Some(callback),
        }
    }

    /// Reports `fraction` done; `Err(Cancelled)` when the caller asked to stop.
    pub fn update(&self, fraction: f64) -> Result<()> {
        match self.callback {
            Some(cb) if !cb(fraction.clamp(0.0, 1.0)) => Err(Error::Cancelled),
            _ => Ok(()),
        }
    }
}

impl std::fmt::Debug for Progress<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Progress")
            .field("callback", &self.callback.is_some())
            .finish()
    }
}
