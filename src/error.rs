//! The one error type of the library.
//!
//! Categories follow Intel Open Image Denoise's error codes (and the C ABI maps them one to
//! one): a caller can branch on the category and show the message, which always names the
//! offending value and what was expected.

use std::path::PathBuf;

/// Everything that can go wrong in gdrecon.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// A parameter is out of range or inconsistent (alpha < 0, zero threads, ...).
    #[error("invalid argument: {0}")]
    InvalidArgument(String),

    /// The input frame is unusable: missing required layer, sizes that disagree, zero size,
    /// or non-finite / negative values in strict mode.
    #[error("invalid input: {0}")]
    InvalidInput(String),

    /// The request is valid but this build or machine cannot serve it.
    #[error("unsupported: {0}")]
    Unsupported(String),

    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file concerned.
        path: PathBuf,
        /// The operating system's error.
        source: std::io::Error,
    },

    /// An OpenEXR file is damaged, is not EXR, or does not hold a frame bundle.
    #[error("{path}: {message}")]
    Exr {
        /// The file concerned.
        path: PathBuf,
        /// What is wrong with it.
        message: String,
    },

    /// A GradNet model is missing its recorded hash, has another one, or is rejected by ONNX
    /// Runtime.
    #[error("GradNet model: {0}")]
    Model(String),

    /// ONNX Runtime failed while configuring a session or running the network.
    #[error("ONNX Runtime: {0}")]
    Runtime(String),

    /// Intel Open Image Denoise failed while computing a prior.
    #[error("Open Image Denoise: {0}")]
    Denoiser(String),

    /// A plan would need more memory than the context's `max_memory_mb` or the process's
    /// address-space limit leaves, or a large allocation failed.
    #[error("out of memory: {0}")]
    OutOfMemory(String),

    /// The caller's progress callback asked to stop.
    #[error("cancelled by the caller")]
    Cancelled,
}

/// Shorthand used throughout the crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    /// An [`Error::InvalidArgument`] from anything printable.
    pub(crate) fn arg(msg: impl Into<String>) -> Self {
        Error::InvalidArgument(msg.into())
    }

    /// An [`Error::InvalidInput`] from anything printable.
    pub(crate) fn input(msg: impl Into<String>) -> Self {
        Error::InvalidInput(msg.into())
    }
}
