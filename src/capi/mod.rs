//! The stable C ABI: a thin layer over the Rust API, and the only module with `unsafe` code.
//!
//! `include/gdrecon.h` is generated from this module by cbindgen (see `cbindgen.toml`, whose
//! header comment states the rules every C caller relies on: handles, errors, threads, ABI
//! evolution). Every exported function
//! - returns a [`gdr_error`] status (or a plain value for the few that cannot fail);
//! - runs inside `guard`, which catches panics (a panic never unwinds into C) and records the
//!   thread's last error message;
//! - checks every pointer it is given for NULL before use.
//!
//! Objects are opaque handles: `gdr_context` (a thread pool and global settings),
//! `gdr_filter` (one reconstruction method with its parameters, image views and plan) and
//! `gdr_frame` (a bundle read from disk). Parameters are string-keyed typed setters, so new
//! parameters never change the ABI.
#![deny(missing_docs)]
#![allow(non_camel_case_types, clippy::missing_safety_doc)]

mod context;
mod filter;
mod frame;
mod param;
mod view;

use std::cell::{Cell, RefCell};
use std::ffi::{c_char, c_void, CStr, CString};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Once, OnceLock};

pub use context::*;
pub use filter::*;
pub use frame::*;
pub use param::*;

use crate::error::Error;
use crate::recon::Method;

/// Major version of the library; matches `Cargo.toml`.
pub const GDR_VERSION_MAJOR: u32 = 0;
/// Minor version of the library; matches `Cargo.toml`.
pub const GDR_VERSION_MINOR: u32 = 1;
/// Patch version of the library; matches `Cargo.toml`.
pub const GDR_VERSION_PATCH: u32 = 0;
/// The version as one number, `MAJOR * 10000 + MINOR * 100 + PATCH` (what `gdr_version` returns).
pub const GDR_VERSION: u32 = 100;

const fn parse_u32(s: &str) -> u32 {
    let b = s.as_bytes();
    let mut i = 0;
    let mut v = 0;
    while i < b.len() {
        v = v * 10 + (b[i] - b'0') as u32;
        i += 1;
    }
    v
}

// The header's version macros must follow Cargo.toml: a mismatch fails the build.
const _: () = {
    assert!(GDR_VERSION_MAJOR == parse_u32(env!("CARGO_PKG_VERSION_MAJOR")));
    assert!(GDR_VERSION_MINOR == parse_u32(env!("CARGO_PKG_VERSION_MINOR")));
    assert!(GDR_VERSION_PATCH == parse_u32(env!("CARGO_PKG_VERSION_PATCH")));
    assert!(GDR_VERSION == GDR_VERSION_MAJOR * 10000 + GDR_VERSION_MINOR * 100 + GDR_VERSION_PATCH);
};

/// Status codes returned by every fallible function (`GDR_ERROR_NONE` is success).
#[repr(u32)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum gdr_error {
    /// Success.
    GDR_ERROR_NONE = 0,
    /// An internal error, e.g. a bug caught at the boundary (the message says where).
    GDR_ERROR_UNKNOWN = 1,
    /// A parameter value is out of range, a name is unknown, a type or enum value is wrong.
    GDR_ERROR_INVALID_ARGUMENT = 2,
    /// A call in the wrong order or on a busy object: execute before commit, commit without
    /// a required image, a setter on a committed context, a call on a filter while another
    /// call on it runs.
    GDR_ERROR_INVALID_OPERATION = 3,
    /// An allocation size that cannot be represented.
    GDR_ERROR_OUT_OF_MEMORY = 4,
    /// Valid, but this build or machine cannot do it (threads refused, method not built).
    GDR_ERROR_UNSUPPORTED = 5,
    /// The progress callback returned false or `gdr_filter_cancel` was called.
    GDR_ERROR_CANCELLED = 6,
    /// A file could not be read or is not a valid frame bundle.
    GDR_ERROR_IO = 7,
    /// The frame's values are unusable (strict mode: NaN, Inf or negative colour).
    GDR_ERROR_INVALID_INPUT = 8,
    /// A required pointer argument is NULL.
    GDR_ERROR_NULL_POINTER = 9,
    /// An image view is unusable: zero or mismatched size, wrong channel count, a stride that
    /// is not a multiple of 4 or makes elements overlap, a pointer not aligned to 4 bytes.
    GDR_ERROR_INVALID_IMAGE = 10,
    /// The output view shares memory with an input view without being the same view.
    GDR_ERROR_OVERLAP = 11,
    /// The GradNet model file is damaged, not the exported one (SHA-256 mismatch) or rejected
    /// by ONNX Runtime.
    GDR_ERROR_INVALID_MODEL = 12,
    /// A library loaded at run time failed while running: ONNX Runtime (configuring a session,
    /// running the network) or Open Image Denoise (computing a prior).
    GDR_ERROR_RUNTIME = 13,
}

use gdr_error::*;

/// Log levels for the context's log callback (`log_level` parameter).
#[repr(u32)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum gdr_log_level {
    /// Nothing is logged.
    GDR_LOG_NONE = 0,
    /// Failed calls (a cancellation is logged at `GDR_LOG_INFO`: it is not a failure).
    GDR_LOG_ERROR = 1,
    /// Replaced input values and other suspicious input (the default level).
    GDR_LOG_WARNING = 2,
    /// One report per execution: method, stage times, notes; cancelled executions.
    GDR_LOG_INFO = 3,
    /// Planning decisions.
    GDR_LOG_DEBUG = 4,
}

/// Progress callback: `fraction` done in [0, 1]; return false to cancel.
pub type gdr_progress_fn = Option<unsafe extern "C" fn(user: *mut c_void, fraction: f64) -> bool>;

/// Log callback: a level (`gdr_log_level`) and a NUL-terminated message valid during the call.
pub type gdr_log_fn =
    Option<unsafe extern "C" fn(user: *mut c_void, level: u32, message: *const c_char)>;

/// A failure crossing the boundary: a status code and a message naming what is wrong.
#[derive(Debug)]
pub(crate) struct CapiError {
    pub(crate) code: gdr_error,
    pub(crate) message: String,
}

pub(crate) type CResult<T = ()> = Result<T, CapiError>;

impl CapiError {
    pub(crate) fn new(code: gdr_error, message: impl Into<String>) -> Self {
        CapiError {
            code,
            message: message.into(),
        }
    }
}

pub(crate) fn err<T>(code: gdr_error, message: impl Into<String>) -> CResult<T> {
    Err(CapiError::new(code, message))
}

impl From<Error> for CapiError {
    fn from(e: Error) -> Self {
        let code = match &e {
            Error::InvalidArgument(_) => GDR_ERROR_INVALID_ARGUMENT,
            Error::InvalidInput(_) => GDR_ERROR_INVALID_INPUT,
            Error::Unsupported(_) => GDR_ERROR_UNSUPPORTED,
            Error::Io { .. } | Error::Exr { .. } => GDR_ERROR_IO,
            Error::Cancelled => GDR_ERROR_CANCELLED,
            Error::OutOfMemory(_) => GDR_ERROR_OUT_OF_MEMORY,
            Error::Model(_) => GDR_ERROR_INVALID_MODEL,
            Error::Runtime(_) | Error::Denoiser(_) => GDR_ERROR_RUNTIME,
        };
        CapiError::new(code, e.to_string())
    }
}

thread_local! {
    /// The last failure on this thread, not yet queried.
    static LAST_ERROR: RefCell<Option<(gdr_error, String)>> = const { RefCell::new(None) };
    /// The message handed out by the last `gdr_get_error` on this thread.
    static SHOWN: RefCell<CString> = RefCell::new(CString::default());
}

fn record(code: gdr_error, message: String) {
    LAST_ERROR.with(|e| *e.borrow_mut() = Some((code, message)));
}

fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_owned()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "unknown panic payload".to_owned()
    }
}

thread_local! {
    /// How many exported functions this thread is inside (callbacks nest them).
    static IN_GUARD: Cell<u32> = const { Cell::new(0) };
    /// Where the last panic caught on this thread happened, from the panic hook.
    static PANIC_AT: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// True on a thread inside an exported function, or one of a context's pool threads (named
/// `gdrecon-N` by `Context::new`), whose panics reach an exported function through rayon.
fn in_library() -> bool {
    IN_GUARD.try_with(|d| d.get() > 0).unwrap_or(false)
        || std::thread::current()
            .name()
            .is_some_and(|n| n.starts_with("gdrecon-"))
}

/// Installs, once per process (at the first `gdr_context_new`), a panic hook that keeps the
/// library silent: a panic on a library thread is not printed (the caught panic becomes
/// `GDR_ERROR_UNKNOWN`, its message goes to `gdr_get_error` and the context's log callback);
/// any other panic goes to the hook that was installed before, so a host's own hook still runs.
pub(crate) fn install_panic_hook() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if in_library() {
                if let Some(at) = info.location() {
                    let at = format!("{}:{}", at.file(), at.line());
                    let _ = PANIC_AT.try_with(|p| *p.borrow_mut() = Some(at));
                }
                return;
            }
            previous(info)
        }));
    });
}

/// Runs `body`, turning a panic into `GDR_ERROR_UNKNOWN` with the panic's message (and
/// location, when the hook saw it on this thread).
pub(crate) fn catch<T>(body: impl FnOnce() -> CResult<T>) -> CResult<T> {
    catch_unwind(AssertUnwindSafe(body)).unwrap_or_else(|payload| {
        let at = PANIC_AT
            .try_with(|p| p.borrow_mut().take())
            .ok()
            .flatten()
            .map_or(String::new(), |at| format!(" at {at}"));
        err(
            GDR_ERROR_UNKNOWN,
            format!("internal error (panic{at}): {}", panic_message(&*payload)),
        )
    })
}

/// Counts this thread inside an exported function while alive.
struct Inside;

impl Inside {
    fn enter() -> Inside {
        let _ = IN_GUARD.try_with(|d| d.set(d.get() + 1));
        Inside
    }
}

impl Drop for Inside {
    fn drop(&mut self) {
        let _ = IN_GUARD.try_with(|d| d.set(d.get().saturating_sub(1)));
    }
}

/// Runs the body of an exported function: catches panics, records failures for
/// `gdr_get_error` (prefixed with the function's name) and returns the status.
pub(crate) fn guard(function: &'static str, body: impl FnOnce() -> CResult) -> gdr_error {
    let _inside = Inside::enter();
    let (code, message) = match catch(body) {
        Ok(()) => return GDR_ERROR_NONE,
        Err(e) => (e.code, e.message),
    };
    // Recording must not unwind either (it only allocates).
    let _ = catch_unwind(AssertUnwindSafe(|| {
        record(code, format!("{function}: {message}"))
    }));
    code
}

/// Reads a NUL-terminated UTF-8 string argument.
pub(crate) unsafe fn c_str<'a>(ptr: *const c_char, what: &str) -> CResult<&'a str> {
    if ptr.is_null() {
        return err(GDR_ERROR_NULL_POINTER, format!("{what} is NULL"));
    }
    CStr::from_ptr(ptr)
        .to_str()
        .map_err(|_| CapiError::new(GDR_ERROR_INVALID_ARGUMENT, format!("{what} is not UTF-8")))
}

/// Checks an output pointer argument.
pub(crate) fn out_ptr<T>(ptr: *mut T, what: &str) -> CResult<&'static mut T> {
    // SAFETY: the caller of the exported function guarantees a non-NULL `ptr` is writable.
    unsafe { ptr.as_mut() }
        .ok_or_else(|| CapiError::new(GDR_ERROR_NULL_POINTER, format!("{what} is NULL")))
}

/// A caller's `void* user` pointer, handed back to its callbacks on any thread.
#[derive(Clone, Copy, Debug)]
pub(crate) struct UserPtr(pub(crate) *mut c_void);
// SAFETY: the header states that callbacks may be called from the library's threads; the
// caller vouches that its user data tolerates that.
unsafe impl Send for UserPtr {}
unsafe impl Sync for UserPtr {}

/// Return the library's version as `MAJOR * 10000 + MINOR * 100 + PATCH` (compare with `GDR_VERSION`).
#[no_mangle]
pub extern "C" fn gdr_version() -> u32 {
    GDR_VERSION
}

/// Return and clear the status of the last failed call on this thread (`GDR_ERROR_NONE` if none).
///
/// If `message` is not NULL it receives a NUL-terminated description naming the function, the
/// object (layer, parameter) and the problem, or "" when there is no error. The string is owned
/// by the library and stays valid until the next `gdr_get_error` call on the same thread.
#[no_mangle]
pub unsafe extern "C" fn gdr_get_error(message: *mut *const c_char) -> gdr_error {
    let result = catch_unwind(AssertUnwindSafe(|| {
        let (code, text) = LAST_ERROR
            .with(|e| e.borrow_mut().take())
            .unwrap_or((GDR_ERROR_NONE, String::new()));
        let text = CString::new(text.replace('\0', " ")).unwrap_or_default();
        SHOWN.with(|s| {
            let mut s = s.borrow_mut();
            *s = text;
            if let Some(m) = message.as_mut() {
                *m = s.as_ptr();
            }
        });
        code
    }));
    result.unwrap_or(GDR_ERROR_UNKNOWN)
}

/// Return the name of a status code (`"GDR_ERROR_CANCELLED"`), a static string; unknown codes give `"GDR_ERROR_?"`.
#[no_mangle]
pub extern "C" fn gdr_error_name(code: u32) -> *const c_char {
    let name: &'static CStr = match code {
        0 => c"GDR_ERROR_NONE",
        1 => c"GDR_ERROR_UNKNOWN",
        2 => c"GDR_ERROR_INVALID_ARGUMENT",
        3 => c"GDR_ERROR_INVALID_OPERATION",
        4 => c"GDR_ERROR_OUT_OF_MEMORY",
        5 => c"GDR_ERROR_UNSUPPORTED",
        6 => c"GDR_ERROR_CANCELLED",
        7 => c"GDR_ERROR_IO",
        8 => c"GDR_ERROR_INVALID_INPUT",
        9 => c"GDR_ERROR_NULL_POINTER",
        10 => c"GDR_ERROR_INVALID_IMAGE",
        11 => c"GDR_ERROR_OVERLAP",
        12 => c"GDR_ERROR_INVALID_MODEL",
        13 => c"GDR_ERROR_RUNTIME",
        _ => c"GDR_ERROR_?",
    };
    name.as_ptr()
}

/// Return the name of method `index` (`"l2"`, `"l1"`, ...) for `gdr_filter_new`, or NULL past the last one.
#[no_mangle]
pub extern "C" fn gdr_method_name(index: u32) -> *const c_char {
    static NAMES: OnceLock<Vec<CString>> = OnceLock::new();
    catch_unwind(|| {
        let names = NAMES.get_or_init(|| {
            Method::ALL
                .iter()
                .map(|m| CString::new(m.name()).unwrap_or_default())
                .collect()
        });
        names
            .get(index as usize)
            .map_or(std::ptr::null(), |n| n.as_ptr())
    })
    .unwrap_or(std::ptr::null())
}
