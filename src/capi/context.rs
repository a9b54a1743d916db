//! `gdr_context`: the thread pool and global settings, reference counted.

use std::cell::RefCell;
use std::ffi::{c_char, CString};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use super::gdr_error::*;
use super::{
    c_str, catch, err, gdr_error, gdr_log_fn, gdr_log_level, guard, install_panic_hook, out_ptr,
    CResult, CapiError, UserPtr,
};
use crate::context::{Context, ContextOptions};

/// A context: thread count, log settings, ONNX Runtime and model locations (opaque).
pub struct gdr_context {
    settings: Mutex<Settings>,
    log_level: AtomicU32,
    /// The log callback; the lock is held while it runs, so calls never overlap and
    /// replacing it waits for a running call.
    log: Mutex<Option<(LogFn, UserPtr)>>,
}

type LogFn = unsafe extern "C" fn(*mut std::ffi::c_void, u32, *const c_char);

thread_local! {
    /// The contexts whose log callback this thread is running (callbacks may nest).
    static LOGGING: RefCell<Vec<usize>> = const { RefCell::new(Vec::new()) };
}

/// True when this thread is inside `ctx`'s log callback.
fn logging(ctx: &gdr_context) -> bool {
    let key = std::ptr::from_ref(ctx) as usize;
    LOGGING
        .try_with(|l| l.borrow().contains(&key))
        .unwrap_or(false)
}

/// Marks this thread inside `ctx`'s log callback while alive.
struct InCallback(usize);

impl InCallback {
    fn enter(ctx: &gdr_context) -> InCallback {
        let key = std::ptr::from_ref(ctx) as usize;
        let _ = LOGGING.try_with(|l| l.borrow_mut().push(key));
        InCallback(key)
    }
}

impl Drop for InCallback {
    fn drop(&mut self) {
        let _ = LOGGING.try_with(|l| {
            let mut l = l.borrow_mut();
            if let Some(i) = l.iter().rposition(|&k| k == self.0) {
                l.remove(i);
            }
        });
    }
}

#[derive(Default)]
struct Settings {
    threads: Option<usize>,
    max_memory_mb: u64,
    onnxruntime_path: Option<String>,
    model_path: Option<String>,
    oidn_path: Option<String>,
    /// The pool, and the process that started it (`std::process::id`).
    committed: Option<(Context, u32)>,
}

impl gdr_context {
    fn settings(&self) -> MutexGuard<'_, Settings> {
        self.settings.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The committed thread pool and the process that committed it, or an error telling the
    /// caller to commit first.
    pub(crate) fn pool(&self) -> CResult<(Context, u32)> {
        match &self.settings().committed {
            Some((c, pid)) => {
                same_process(*pid)?;
                Ok((c.clone(), *pid))
            }
            None => err(
                GDR_ERROR_INVALID_OPERATION,
                "the context is not committed: call gdr_context_commit first",
            ),
        }
    }

    /// Points `config` at the paths set on the context: `onnxruntime_path` for any method that
    /// runs a network, `model_path` for GradNet's model.
    pub(crate) fn apply_paths(&self, config: &mut crate::recon::MethodConfig) {
        let s = self.settings();
        if let Some(runtime) = config.runtime_mut() {
            *runtime = s.onnxruntime_path.clone().map(Into::into);
        }
        if let Some(c) = config.gradnet_mut() {
            c.model = s.model_path.clone().map(Into::into);
        }
    }

    /// Sends `message` to the log callback if `level` is enabled, one call at a time.
    ///
    /// A message logged from inside this context's own callback on the same thread (the
    /// callback called a function that logs) is dropped: delivering it would nest a call in
    /// the running one, and waiting for the running one would never end.
    pub(crate) fn log(&self, level: gdr_log_level, message: &str) {
        if level as u32 > self.log_level.load(Ordering::Relaxed) || logging(self) {
            return;
        }
        let slot = self.log.lock().unwrap_or_else(|p| p.into_inner());
        if let Some((f, user)) = *slot {
            let text = CString::new(message.replace('\0', " ")).unwrap_or_default();
            let _inside = InCallback::enter(self);
            // SAFETY: the caller registered `f` with `user` for exactly this use; the lock
            // held in `slot` keeps calls from overlapping.
            unsafe { f(user.0, level as u32, text.as_ptr()) };
        }
    }

    /// Logs a failed call: at `GDR_LOG_ERROR`, or `GDR_LOG_INFO` for a cancellation (the
    /// answer to the caller's request, not a failure).
    pub(crate) fn log_failure(&self, function: &str, e: &CapiError) {
        let level = if e.code == GDR_ERROR_CANCELLED {
            gdr_log_level::GDR_LOG_INFO
        } else {
            gdr_log_level::GDR_LOG_ERROR
        };
        self.log(level, &format!("{function}: {}", e.message));
    }
}

/// Fails in a process forked from the one that committed the context: the pool's threads
/// were not copied into the child, so work handed to them would wait forever.
pub(crate) fn same_process(committed_by: u32) -> CResult {
    let now = std::process::id();
    if now == committed_by {
        return Ok(());
    }
    err(
        GDR_ERROR_INVALID_OPERATION,
        format!(
            "the context was committed in process {committed_by} and this is process {now} \
             (forked after the commit): its threads do not exist here; create and commit a new \
             context in this process (objects from before the fork may only be released)"
        ),
    )
}

/// Runs the body of an exported function on a context: holds a reference for the call (a
/// callback may release the caller's), catches panics, and logs failures on the context.
unsafe fn with_context(
    function: &'static str,
    ctx: *const gdr_context,
    body: impl FnOnce(&gdr_context) -> CResult,
) -> gdr_error {
    guard(function, || {
        let ctx = context_arc(ctx)?;
        let result = catch(|| body(&ctx));
        if let Err(e) = &result {
            ctx.log_failure(function, e);
        }
        result
    })
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
        install_panic_hook();
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

/// Set an integer parameter: `"threads"` (0 = all cores; before commit), `"max_memory_mb"` (before commit) or `"log_level"` (a `gdr_log_level`, any time).
///
/// `"max_memory_mb"`: the most memory, in MiB, one filter's plan may need beyond its images.
/// As OIDN's `maxMemoryMB`, it sizes tiles: GradNet and the combiner (down to tiles of four
/// margins a side) and OIDN's scratch (down to 512 MiB) run in smaller tiles to fit, the same
/// image up to rounding in more time; `"auto"` leaves out the paths that do not fit.
/// `gdr_filter_commit` refuses a method and size whose estimate (buffers, scratch, output,
/// OIDN's or ONNX Runtime's share) is over it even so with `GDR_ERROR_OUT_OF_MEMORY` and a
/// message giving the estimate and the limit. 0 (the default) is no limit. On Linux the address space left under
/// the process's limit (`ulimit -v`) bounds a commit the same way.
#[no_mangle]
pub unsafe extern "C" fn gdr_context_set_int(
    ctx: *mut gdr_context,
    name: *const c_char,
    value: i32,
) -> gdr_error {
    with_context("gdr_context_set_int", ctx, |ctx| {
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
            "max_memory_mb" => {
                let mb = u64::try_from(value).map_err(|_| {
                    CapiError::new(
                        GDR_ERROR_INVALID_ARGUMENT,
                        format!("max_memory_mb is {value}, expected 0 (no limit) or a positive count of MiB"),
                    )
                })?;
                let mut s = ctx.settings();
                frozen(&s, name)?;
                s.max_memory_mb = mb;
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

/// Read an integer parameter into `*value`: `"threads"` (the pool's thread count once committed, else the setting), `"max_memory_mb"` or `"log_level"`.
#[no_mangle]
pub unsafe extern "C" fn gdr_context_get_int(
    ctx: *const gdr_context,
    name: *const c_char,
    value: *mut i32,
) -> gdr_error {
    with_context("gdr_context_get_int", ctx, |ctx| {
        let name = c_str(name, "name")?;
        let out = out_ptr(value, "value")?;
        *out = match name {
            "threads" => {
                let s = ctx.settings();
                let n = match &s.committed {
                    Some((c, _)) => c.threads(),
                    None => s.threads.unwrap_or(0),
                };
                i32::try_from(n).unwrap_or(i32::MAX)
            }
            "max_memory_mb" => i32::try_from(ctx.settings().max_memory_mb).unwrap_or(i32::MAX),
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
    with_context("gdr_context_set_string", ctx, |ctx| {
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
///
/// Calls for one context are serialised (a lock is held while the callback runs). Replacing or
/// removing the callback waits for a running call to return: afterwards the old callback is
/// never called again. The callback may call any gdr_ function except this one on the same
/// context (`GDR_ERROR_INVALID_OPERATION`); what those calls would log on the same context is
/// dropped, not delivered. It must not wait for a thread that is replacing the callback.
#[no_mangle]
pub unsafe extern "C" fn gdr_context_set_log_callback(
    ctx: *mut gdr_context,
    callback: gdr_log_fn,
    user: *mut std::ffi::c_void,
) -> gdr_error {
    with_context("gdr_context_set_log_callback", ctx, |ctx| {
        if logging(ctx) {
            return err(
                GDR_ERROR_INVALID_OPERATION,
                "the log callback cannot be replaced from inside itself (it would wait for its own return)",
            );
        }
        *ctx.log.lock().unwrap_or_else(|p| p.into_inner()) = callback.map(|f| (f, UserPtr(user)));
        Ok(())
    })
}

/// Apply the settings and start the thread pool; filters can be created afterwards.
///
/// Committing twice is an error (`GDR_ERROR_INVALID_OPERATION`); so is setting `threads` or a path afterwards.
#[no_mangle]
pub unsafe extern "C" fn gdr_context_commit(ctx: *mut gdr_context) -> gdr_error {
    with_context("gdr_context_commit", ctx, |ctx| {
        let mut s = ctx.settings();
        frozen(&s, "the context")?;
        let mut options =
            ContextOptions::with_threads(s.threads).with_max_memory_mb(s.max_memory_mb);
        if let Some(path) = &s.oidn_path {
            options = options.with_oidn(path);
        }
        let pool = Context::new(options)?;
        let threads = pool.threads();
        s.committed = Some((pool, std::process::id()));
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
        _ => "threads, max_memory_mb, log_level",
    };
    err(
        GDR_ERROR_INVALID_ARGUMENT,
        format!("unknown context parameter '{name}' for {function}, expected one of: {valid}"),
    )
}
