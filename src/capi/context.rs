//! `gdr_context`: the thread pool and global settings, reference counted.

use std::ffi::{c_char, CString};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use super::gdr_error::*;
use super::{c_str, err, gdr_error, gdr_log_fn, gdr_log_level, guard, out_ptr, CResult, UserPtr};
use crate::context::{Context, ContextOptions};

/// A context: thread count, log settings, ONNX Runtime and model locations (opaque).
pub struct gdr_context {
    settings: Mutex<Settings>,
    log_level: AtomicU32,
    log: Mutex<
        Option<(
            unsafe extern "C" fn(*mut std::ffi::c_void, u32, *const c_char),
            UserPtr,
        )>,
    >,
}

#[derive(Default)]
struct Settings {
    threads: Option<usize>,
    onnxruntime_path: Option<String>,
    model_path: Option<String>,
    oidn_path: Option<String>,
    committed: Option<Context>,
}

impl gdr_context {
    fn settings(&self) -> MutexGuard<'_, Settings> {
        self.settings.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The committed thread pool, or an error telling the caller to commit first.
    pub(crate) fn pool(&self) -> CResult<Context> {
        match &self.settings().committed {
            Some(c) => Ok(c.clone()),
            None => err(
                GDR_ERROR_INVALID_OPERATION,
                "the context is not committed: call gdr_context_commit first",
            ),
        }
    }

    /// The GradNet paths set on the context: `(onnxruntime_path, model_path)`.
    pub(crate) fn gradnet_paths(&self) -> (Option<String>, Option<String>) {
        let s = self.settings();
        (s.onnxruntime_path.clone(), s.model_path.clone())
    }

    /// Sends `message` to the log callback if `level` is enabled.
    pub(crate) fn log(&self, level: gdr_log_level, message: &str) {
        if level as u32 > self.log_level.load(Ordering::Relaxed) {
            return;
        }
        let callback = *self.log.lock().unwrap_or_else(|p| p.into_inner());
        if let Some((f, user)) = callback {
            let text = CString::new(message.replace('\0', " ")).unwrap_or_default();
            // SAFETY: the caller registered `f` with `user` for exactly this use.
            unsafe { f(user.0, level as u32, text.as_ptr()) };
        }
    }
}

/// Borrows a handle argument.
pub(crate) unsafe fn context_ref<'a>(ctx: *const gdr_context) -> CResult<&'a gdr_context> {
    ctx.as_ref()
        .ok_or_else(|| super::CapiError::new(GDR_ERROR_NULL_POINTER, "context is NULL"))
}

/// Clones a handle argument into an owned reference.
pub(crate) unsafe fn context_arc(ctx: *const gdr_context) -> CResult<Arc<gdr_context>> {
    context_ref(ctx)?;
    Arc::increment_strong_count(ctx);
    Ok(Arc::from_raw(ctx))
}

/// Create a context with default settings (all cores, log level WARNING) into `*out`; NULL on failure.
#[no_mangle]
pub unsafe extern "C" fn gdr_context_new(out: *mut *mut gdr_context) -> gdr_error {
    guard("gdr_context_new", || {
        let out = out_ptr(out, "out")?;
        *out = std::ptr::null_mut();
        let ctx = gdr_context {
            settings: Mutex::new(Settings::default()),
            log_level: AtomicU32::new(gdr_log_level::GDR_LOG_WARNING as u32),
            log: Mutex::new(None),
        };
        *out = Arc::into_raw(Arc::new(ctx)).cast_mut();
        Ok(())
    })
}

/// Add a reference to `ctx`; each reference is dropped by one `gdr_context_release`.
#[no_mangle]
pub unsafe extern "C" fn gdr_context_retain(ctx: *mut gdr_context) -> gdr_error {
    guard("gdr_context_retain", || {
        context_ref(ctx)?;
        Arc::increment_strong_count(ctx.cast_const());
        Ok(())
    })
}

/// Drop the reference `*ctx` and set `*ctx` to NULL (no-op when `*ctx` is NULL); the last one frees the context.
///
/// Filters keep their context alive: releasing a context that filters still use is fine.
#[no_mangle]
pub unsafe extern "C" fn gdr_context_release(ctx: *mut *mut gdr_context) -> gdr_error {
    guard("gdr_context_release", || {
        let slot = out_ptr(ctx, "ctx")?;
        let raw = std::mem::replace(slot, std::ptr::null_mut());
        if !raw.is_null() {
            drop(Arc::from_raw(raw.cast_const()));
        }
        Ok(())
    })
}

/// Set an integer parameter: `"threads"` (0 = all cores; before commit) or `"log_level"` (a `gdr_log_level`, any time).
#[no_mangle]
pub unsafe extern "C" fn gdr_context_set_int(
    ctx: *mut gdr_context,
    name: *const c_char,
    value: i32,
) -> gdr_error {
    guard("gdr_context_set_int", || {
        let ctx = context_ref(ctx)?;
        let name = c_str(name, "name")?;
        match name {
            "threads" => {
                let threads = usize::try_from(value).map_err(|_| {
                    super::CapiError::new(
                        GDR_ERROR_INVALID_ARGUMENT,
                        format!("threads is {value}, expected 0 (all cores) or a positive count"),
                    )
                })?;
                let mut s = ctx.settings();
                frozen(&s, name)?;
                s.threads = (threads > 0).then_some(threads);
                Ok(())
            }
            "log_level" => {
                if !(0..=gdr_log_level::GDR_LOG_DEBUG as i32).contains(&value) {
                    return err(
                        GDR_ERROR_INVALID_ARGUMENT,
                        format!(
                            "log_level is {value}, expected 0 (GDR_LOG_NONE) to 4 (GDR_LOG_DEBUG)"
                        ),
                    );
                }
                ctx.log_level.store(value as u32, Ordering::Relaxed);
                Ok(())
            }
            _ => unknown(name, "gdr_context_set_int"),
        }
    })
}

/// Read an integer parameter into `*value`: `"threads"` (the pool's thread count once committed, else the setting) or `"log_level"`.
#[no_mangle]
pub unsafe extern "C" fn gdr_context_get_int(
    ctx: *const gdr_context,
    name: *const c_char,
    value: *mut i32,
) -> gdr_error {
    guard("gdr_context_get_int", || {
        let ctx = context_ref(ctx)?;
        let name = c_str(name, "name")?;
        let out = out_ptr(value, "value")?;
        *out = match name {
            "threads" => {
                let s = ctx.settings();
                let n = match &s.committed {
                    Some(c) => c.threads(),
                    None => s.threads.unwrap_or(0),
                };
                i32::try_from(n).unwrap_or(i32::MAX)
            }
            "log_level" => ctx.log_level.load(Ordering::Relaxed) as i32,
            _ => return unknown(name, "gdr_context_get_int"),
        };
        Ok(())
    })
}

/// Set a string parameter before commit: `"onnxruntime_path"` (ONNX Runtime library), `"model_path"` (GradNet model) or `"oidn_path"` (Open Image Denoise library, for the prior); NULL clears it.
///
/// Paths are stored as given and only opened when a method needs them.
#[no_mangle]
pub unsafe extern "C" fn gdr_context_set_string(
    ctx: *mut gdr_context,
    name: *const c_char,
    value: *const c_char,
) -> gdr_error {
    guard("gdr_context_set_string", || {
        let ctx = context_ref(ctx)?;
        let name = c_str(name, "name")?;
        let value = if value.is_null() {
            None
        } else {
            Some(c_str(value, "value")?.to_owned())
        };
        let mut s = ctx.settings();
        match name {
            "onnxruntime_path" => {
                frozen(&s, name)?;
                s.onnxruntime_path = value;
            }
            "model_path" => {
                frozen(&s, name)?;
                s.model_path = value;
            }
            "oidn_path" => {
                frozen(&s, name)?;
                s.oidn_path = value;
            }
            _ => return unknown(name, "gdr_context_set_string"),
        }
        Ok(())
    })
}

/// Set (or with NULL remove) the log callback; it may be called from any thread, never concurrently for one context.
#[no_mangle]
pub unsafe extern "C" fn gdr_context_set_log_callback(
    ctx: *mut gdr_context,
    callback: gdr_log_fn,
    user: *mut std::ffi::c_void,
) -> gdr_error {
    guard("gdr_context_set_log_callback", || {
        let ctx = context_ref(ctx)?;
        *ctx.log.lock().unwrap_or_else(|p| p.into_inner()) = callback.map(|f| (f, UserPtr(user)));
        Ok(())
    })
}

/// Apply the settings and start the thread pool; filters can be created afterwards.
///
/// Committing twice is an error (`GDR_ERROR_INVALID_OPERATION`); so is setting `threads` or a path afterwards.
#[no_mangle]
pub unsafe extern "C" fn gdr_context_commit(ctx: *mut gdr_context) -> gdr_error {
    guard("gdr_context_commit", || {
        let ctx = context_ref(ctx)?;
        let mut s = ctx.settings();
        frozen(&s, "the context")?;
        let mut options = ContextOptions::with_threads(s.threads);
        if let Some(path) = &s.oidn_path {
            options = options.with_oidn(path);
        }
        let pool = Context::new(options)?;
        let threads = pool.threads();
        s.committed = Some(pool);
        drop(s);
        ctx.log(
            gdr_log_level::GDR_LOG_DEBUG,
            &format!("context committed with {threads} threads"),
        );
        Ok(())
    })
}

fn frozen(s: &Settings, what: &str) -> CResult {
    if s.committed.is_some() {
        err(
            GDR_ERROR_INVALID_OPERATION,
            format!("{what} cannot change: the context is already committed"),
        )
    } else {
        Ok(())
    }
}

fn unknown(name: &str, function: &str) -> CResult {
    let valid = match function {
        "gdr_context_set_string" => "onnxruntime_path, model_path, oidn_path",
        _ => "threads, log_level",
    };
    err(
        GDR_ERROR_INVALID_ARGUMENT,
        format!("unknown context parameter '{name}' for {function}, expected one of: {valid}"),
    )
}
