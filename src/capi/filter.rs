//! `gdr_filter`: one reconstruction method with its parameters, image views and plan.

use std::collections::BTreeMap;
use std::ffi::{c_char, c_void, CString};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, TryLockError};

use super::context::{context_arc, gdr_context, same_process};
use super::gdr_error::*;
use super::gdr_log_level::*;
use super::param::{lookup, Setter};
use super::view::{Layout, View};
use super::{
    c_str, catch, err, gdr_error, gdr_progress_fn, guard, out_ptr, CResult, CapiError, UserPtr,
};
use crate::context::Context;
use crate::frame::{FrameBuilder, Layer};
use crate::image::Image;
use crate::progress::Progress;
use crate::recon::{Kind, Method, MethodConfig, Plan, Value};
use crate::validate::Policy;

/// A reconstruction filter: one method, its parameters, image views and plan (opaque).
pub struct gdr_filter {
    context: Arc<gdr_context>,
    pool: Context,
    /// The process that committed the context (`std::process::id`).
    pid: u32,
    cancel: AtomicBool,
    state: Mutex<State>,
}

struct State {
    config: MethodConfig,
    strict: bool,
    spp: f32,
    inputs: BTreeMap<Layer, View>,
    output: Option<View>,
    progress: Option<(unsafe extern "C" fn(*mut c_void, f64) -> bool, UserPtr)>,
    /// Changed since the last successful commit.
    dirty: bool,
    plan: Option<Plan>,
    planned: Option<(MethodConfig, usize, usize)>,
    out: Image,
    report: CString,
}

/// Deliberately panics when set to true (cargo feature `testing` only): lets tests check that
/// no panic crosses the ABI.
#[cfg(feature = "testing")]
const TEST_PANIC: &str = "internal_test_panic";
/// Like `internal_test_panic`, on one of the context's pool threads (feature `testing` only).
#[cfg(feature = "testing")]
const TEST_PANIC_IN_POOL: &str = "internal_test_panic_in_pool";

/// Filter `"guide"`: RDFC's first pass, as the authors' release (the default).
pub const GDR_FRGR_GUIDE_RDFC: i32 = 0;
/// Filter `"guide"`: the screened Poisson L1 reconstruction.
pub const GDR_FRGR_GUIDE_L1: i32 = 1;
/// Filter `"guide"`: no pre-denoiser, the noisy colour itself (an ablation).
pub const GDR_FRGR_GUIDE_NONE: i32 = 2;
/// Filter `"guide"`: the prior (image `"prior"` if set, else Open Image Denoise on `"color"`).
pub const GDR_FRGR_GUIDE_PRIOR: i32 = 3;
/// Screened Poisson `"data"`: the data term is the base image `"color"` (the default).
pub const GDR_DATA_COLOR: i32 = 0;
/// Screened Poisson `"data"`: the data term is the prior, weighted by `"prior_alpha"`.
pub const GDR_DATA_PRIOR: i32 = 1;

// The C constants are the indices of the choices in the methods' parameter tables.
const _: () = {
    use crate::recon::{DataTerm, FrgrGuide};
    assert!(GDR_FRGR_GUIDE_RDFC == 0 && GDR_FRGR_GUIDE_L1 == 1 && GDR_FRGR_GUIDE_NONE == 2);
    assert!(GDR_FRGR_GUIDE_PRIOR == 3 && FrgrGuide::ALL.len() == 4);
    assert!(GDR_DATA_COLOR == 0 && GDR_DATA_PRIOR == 1 && DataTerm::ALL.len() == 2);
};

impl State {
    fn set(&mut self, name: &str, setter: Setter, value: Value) -> CResult {
        #[cfg(feature = "testing")]
        if name == TEST_PANIC && setter == Setter::Bool {
            if value == Value::Bool(true) {
                panic!("deliberate panic ({TEST_PANIC})");
            }
            return Ok(());
        }
        let info = lookup(self.config.method(), name, setter)?;
        let value = info.check(value).map_err(|e| {
            let mut e = CapiError::from(e);
            if info.kind == Kind::Choice {
                e.message += &format!(
                    " (from C: its index, 0 to {})",
                    info.choices.len().saturating_sub(1)
                );
            }
            e
        })?;
        match (name, value) {
            ("spp", Value::Float(s)) => self.spp = s,
            ("strict", Value::Bool(b)) => self.strict = b,
            _ => self.config.set(name, value)?,
        }
        self.dirty = true;
        Ok(())
    }

    fn get(&self, name: &str, setter: Setter) -> CResult<Value> {
        lookup(self.config.method(), name, setter)?;
        Ok(match name {
            "spp" => Value::Float(self.spp),
            "strict" => Value::Bool(self.strict),
            _ => self.config.get(name)?,
        })
    }

    /// Validates the views and (re)plans when the method settings or the size changed.
    fn commit(&mut self, pool: &Context) -> CResult<String> {
        for layer in [Layer::Color, Layer::Dx, Layer::Dy] {
            if !self.inputs.contains_key(&layer) {
                return err(
                    GDR_ERROR_INVALID_OPERATION,
                    format!("image '{layer}' is not set: color, dx, dy and output are required before commit"),
                );
            }
        }
        let Some(output) = self.output else {
            return err(
                GDR_ERROR_INVALID_OPERATION,
                "image 'output' is not set: color, dx, dy and output are required before commit",
            );
        };
        let color = self.inputs[&Layer::Color];
        let (w, h) = (color.width, color.height);
        let all = self.inputs.iter().map(|(l, v)| (l.name(), v));
        for (name, v) in all.chain([("output", &output)]) {
            if (v.width, v.height) != (w, h) {
                return err(
                    GDR_ERROR_INVALID_IMAGE,
                    format!(
                        "image '{name}' is {} x {}, expected {w} x {h} like 'color'",
                        v.width, v.height
                    ),
                );
            }
        }
        for (layer, v) in &self.inputs {
            if output.partially_overlaps(v) {
                return err(
                    GDR_ERROR_OVERLAP,
                    format!(
                        "image 'output' shares memory with image '{layer}' without being the same view: \
                         write in place with exactly that image's pointer and strides, or use separate memory"
                    ),
                );
            }
        }
        if w.checked_mul(h)
            .and_then(|n| n.checked_mul(12))
            .is_none_or(|b| b > isize::MAX as usize)
        {
            return err(
                GDR_ERROR_OUT_OF_MEMORY,
                format!("{w} x {h} x 3 floats cannot be allocated"),
            );
        }
        if self.config.method() == Method::Frgr && self.spp <= 0.0 {
            // Its weights depend on the sample count: refused here, not at execute.
            return err(
                GDR_ERROR_INVALID_OPERATION,
                "method 'frgr' needs the samples per pixel: set \"spp\" \
                 (gdr_filter_set_float(filter, \"spp\", N)) before gdr_filter_commit",
            );
        }
        // With a prior image set, every execution until the next commit has one: no OIDN run,
        // so its scratch is not held against the memory limit (unsetting it dirties the filter).
        let config = if self.inputs.contains_key(&Layer::Prior) {
            self.config.given_prior()
        } else {
            self.config.clone()
        };
        let mut note = String::new();
        if self.planned.as_ref() != Some(&(config.clone(), w, h)) {
            self.plan = None;
            self.planned = None;
            self.out = Image::zeros(3, 0, 0);
            let plan = Plan::new(pool, &config, w, h)?;
            self.out = Image::try_zeros(3, w, h)?;
            self.plan = Some(plan);
            self.planned = Some((config, w, h));
            note = format!("planned method {} for {w} x {h}", self.config.method());
        }
        self.dirty = false;
        Ok(note)
    }
}

/// Takes a reference to a filter handle for one call (a callback may release the caller's:
/// the filter lives until the call returns) and locks it; failures are logged on its context.
unsafe fn with_filter(
    function: &'static str,
    filter: *const gdr_filter,
    body: impl FnOnce(&gdr_filter, &mut State) -> CResult,
) -> gdr_error {
    guard(function, || {
        if filter.is_null() {
            return err(GDR_ERROR_NULL_POINTER, "filter is NULL");
        }
        Arc::increment_strong_count(filter);
        let f = Arc::from_raw(filter);
        // A panic unwinds through the lock guard, which poisons the state (see `lock`).
        let result = catch(|| body(&f, &mut *lock(&f)?));
        if let Err(e) = &result {
            f.context.log_failure(function, e);
        }
        result
    })
}

fn lock(f: &gdr_filter) -> CResult<MutexGuard<'_, State>> {
    match f.state.try_lock() {
        Ok(g) => Ok(g),
        Err(TryLockError::WouldBlock) => err(
            GDR_ERROR_INVALID_OPERATION,
            "the filter is busy: another call on it is running (on another thread, or this is its own progress callback)",
        ),
        Err(TryLockError::Poisoned(p)) => {
            // A previous call panicked half-way: keep the settings, drop the plan.
            f.state.clear_poison();
            let mut g = p.into_inner();
            g.plan = None;
            g.planned = None;
            g.dirty = true;
            Ok(g)
        }
    }
}

/// Create a filter running `method` (`"l2"`, `"l1"`, `"frgr"`, `"gradnet"`, `"prior"`, `"combiner"`, `"auto"`; see `gdr_method_name`) on a committed context into `*out`; NULL on failure.
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_new(
    ctx: *mut gdr_context,
    method: *const c_char,
    out: *mut *mut gdr_filter,
) -> gdr_error {
    guard("gdr_filter_new", || {
        let out = out_ptr(out, "out")?;
        *out = std::ptr::null_mut();
        let context = context_arc(ctx)?;
        let made = catch(|| {
            let method: Method = c_str(method, "method")?.parse()?;
            let (pool, pid) = context.pool()?;
            Ok((method, pool, pid))
        });
        let (method, pool, pid) = match made {
            Ok(m) => m,
            Err(e) => {
                context.log_failure("gdr_filter_new", &e);
                return Err(e);
            }
        };
        let mut config = MethodConfig::default_for(method);
        context.apply_paths(&mut config);
        let filter = gdr_filter {
            context,
            pool,
            pid,
            cancel: AtomicBool::new(false),
            state: Mutex::new(State {
                config,
                strict: false,
                spp: 0.0,
                inputs: BTreeMap::new(),
                output: None,
                progress: None,
                dirty: true,
                plan: None,
                planned: None,
                out: Image::zeros(3, 0, 0),
                report: CString::default(),
            }),
        };
        *out = Arc::into_raw(Arc::new(filter)).cast_mut();
        Ok(())
    })
}

/// Add a reference to `filter`; each reference is dropped by one `gdr_filter_release`.
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_retain(filter: *mut gdr_filter) -> gdr_error {
    guard("gdr_filter_retain", || {
        if filter.is_null() {
            return err(GDR_ERROR_NULL_POINTER, "filter is NULL");
        }
        Arc::increment_strong_count(filter.cast_const());
        Ok(())
    })
}

/// Drop the reference `*filter` and set `*filter` to NULL (no-op when `*filter` is NULL); the last one frees the filter.
///
/// After a cancelled execute of a prior path, the last release waits for Open Image Denoise's
/// operation in flight to end (at most 0.35 s at 1280 x 720 on two cores; see
/// `gdr_filter_cancel`).
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_release(filter: *mut *mut gdr_filter) -> gdr_error {
    guard("gdr_filter_release", || {
        let slot = out_ptr(filter, "filter")?;
        let raw = std::mem::replace(slot, std::ptr::null_mut());
        if !raw.is_null() {
            drop(Arc::from_raw(raw.cast_const()));
        }
        Ok(())
    })
}

/// Reset every parameter of the filter's method to one of its presets (`"prior"`, `"fast"`, `"published"` for `"l1"`; `"fast"`, `"reference"` for `"frgr"`; docs/PARAMETERS.md and `gdrecon params` list them); `"spp"` and `"strict"` are kept.
///
/// An unknown preset is `GDR_ERROR_INVALID_ARGUMENT`, with a message that lists the method's presets.
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_set_preset(
    filter: *mut gdr_filter,
    name: *const c_char,
) -> gdr_error {
    with_filter("gdr_filter_set_preset", filter, |f, st| {
        let mut config = MethodConfig::preset(st.config.method(), c_str(name, "name")?)?;
        f.context.apply_paths(&mut config);
        st.config = config;
        st.dirty = true;
        Ok(())
    })
}

/// Set a float parameter of the filter's method (see `gdr_method_param`, or docs/PARAMETERS.md), or `"spp"` (0 = unknown).
///
/// An unknown name, a parameter of another type or a value out of its range is
/// `GDR_ERROR_INVALID_ARGUMENT`, with a message that lists the names or states the range.
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_set_float(
    filter: *mut gdr_filter,
    name: *const c_char,
    value: f32,
) -> gdr_error {
    with_filter("gdr_filter_set_float", filter, |_, st| {
        st.set(c_str(name, "name")?, Setter::Float, Value::Float(value))
    })
}

/// Set an integer parameter of the filter's method, or a choice by its index (filter `"guide"`: a `GDR_FRGR_GUIDE_*` value; l2 and l1 `"data"`: a `GDR_DATA_*` value).
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_set_int(
    filter: *mut gdr_filter,
    name: *const c_char,
    value: i32,
) -> gdr_error {
    with_filter("gdr_filter_set_int", filter, |_, st| {
        st.set(c_str(name, "name")?, Setter::Int, Value::Int(value.into()))
    })
}

/// Set a boolean parameter of the filter's method, or `"strict"` (NaN/Inf/negative input is an error instead of replaced).
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_set_bool(
    filter: *mut gdr_filter,
    name: *const c_char,
    value: bool,
) -> gdr_error {
    with_filter("gdr_filter_set_bool", filter, |_f, st| {
        let name = c_str(name, "name")?;
        #[cfg(feature = "testing")]
        if name == TEST_PANIC_IN_POOL {
            _f.pool.install(|| {
                if value {
                    panic!("deliberate panic ({name})");
                }
            });
            return Ok(());
        }
        st.set(name, Setter::Bool, Value::Bool(value))
    })
}

/// Read a float parameter into `*value`.
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_get_float(
    filter: *mut gdr_filter,
    name: *const c_char,
    value: *mut f32,
) -> gdr_error {
    with_filter("gdr_filter_get_float", filter, |_, st| {
        let out = out_ptr(value, "value")?;
        if let Value::Float(v) = st.get(c_str(name, "name")?, Setter::Float)? {
            *out = v;
        }
        Ok(())
    })
}

/// Read an integer (or choice index) parameter into `*value`.
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_get_int(
    filter: *mut gdr_filter,
    name: *const c_char,
    value: *mut i32,
) -> gdr_error {
    with_filter("gdr_filter_get_int", filter, |_, st| {
        let out = out_ptr(value, "value")?;
        if let Value::Int(v) = st.get(c_str(name, "name")?, Setter::Int)? {
            // Every int parameter's range lies within i32 (the tables' ranges say so).
            *out = i32::try_from(v).unwrap_or(i32::MAX);
        }
        Ok(())
    })
}

/// Read a boolean parameter into `*value`.
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_get_bool(
    filter: *mut gdr_filter,
    name: *const c_char,
    value: *mut bool,
) -> gdr_error {
    with_filter("gdr_filter_get_bool", filter, |_, st| {
        let out = out_ptr(value, "value")?;
        if let Value::Bool(v) = st.get(c_str(name, "name")?, Setter::Bool)? {
            *out = v;
        }
        Ok(())
    })
}

/// Look an image name up: an input layer, or `None` for `"output"`.
fn image_slot(name: &str) -> CResult<Option<Layer>> {
    if name.eq_ignore_ascii_case("output") {
        return Ok(None);
    }
    match Layer::from_name(name) {
        Some(l) if l != Layer::Reference => Ok(Some(l)),
        _ => err(
            GDR_ERROR_INVALID_ARGUMENT,
            format!(
                "unknown image '{name}', expected one of: color, dx, dy, variance, albedo, normal, depth, prior, output"
            ),
        ),
    }
}

unsafe fn set_view(
    function: &'static str,
    filter: *mut gdr_filter,
    name: *const c_char,
    make: impl FnOnce(&str, usize) -> CResult<View>,
) -> gdr_error {
    with_filter(function, filter, |_, st| {
        let name = c_str(name, "name")?;
        let slot = image_slot(name)?;
        let view = make(name, slot.map_or(3, Layer::channels))?;
        match slot {
            Some(layer) => {
                st.inputs.insert(layer, view);
            }
            None => st.output = Some(view),
        }
        st.dirty = true;
        Ok(())
    })
}

/// Set image `name` to an interleaved view: pixel (x, y) channel c at `ptr + y*row_stride + x*pixel_stride + 4*c` bytes.
///
/// Names: `"color"`, `"dx"`, `"dy"` (required), `"variance"`, `"albedo"`, `"normal"` (3 channels),
/// `"depth"` (1 channel) and `"output"` (required, 3 channels, written by `gdr_filter_execute`,
/// so its memory must be writable). Strides are in bytes; 0 means packed (`pixel_stride =
/// 4 * channels`, `row_stride = width * pixel_stride`). For RGBA buffers pass 3 channels and a
/// pixel stride of 16. The memory is borrowed, not copied: it must stay valid until the next
/// execute returns.
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_set_image(
    filter: *mut gdr_filter,
    name: *const c_char,
    ptr: *const f32,
    width: usize,
    height: usize,
    channels: usize,
    pixel_stride: usize,
    row_stride: usize,
) -> gdr_error {
    set_view("gdr_filter_set_image", filter, name, |n, expected| {
        let layout = Layout::Interleaved {
            pixel: pixel_stride,
            row: row_stride,
        };
        View::new(n, ptr, width, height, channels, expected, layout)
    })
}

/// Set image `name` to a planar view: pixel (x, y) channel c at `ptr + c*plane_stride + y*row_stride + 4*x` bytes.
///
/// Same names and rules as `gdr_filter_set_image`; 0 strides mean packed (`row_stride = 4 *
/// width`, `plane_stride = height * row_stride`).
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_set_image_planar(
    filter: *mut gdr_filter,
    name: *const c_char,
    ptr: *const f32,
    width: usize,
    height: usize,
    channels: usize,
    row_stride: usize,
    plane_stride: usize,
) -> gdr_error {
    set_view(
        "gdr_filter_set_image_planar",
        filter,
        name,
        |n, expected| {
            let layout = Layout::Planar {
                row: row_stride,
                plane: plane_stride,
            };
            View::new(n, ptr, width, height, channels, expected, layout)
        },
    )
}

/// Remove image `name` (an optional layer the method should not use); removing an unset image is not an error.
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_unset_image(
    filter: *mut gdr_filter,
    name: *const c_char,
) -> gdr_error {
    with_filter("gdr_filter_unset_image", filter, |_, st| {
        match image_slot(c_str(name, "name")?)? {
            Some(layer) => st.inputs.remove(&layer),
            None => st.output.take(),
        };
        st.dirty = true;
        Ok(())
    })
}

/// Set (or with NULL remove) the progress callback; it runs on a library thread during execute, never concurrently with itself.
///
/// It receives the fraction done in [0, 1] and returns false to cancel. It must not throw.
/// Calls on the same filter from it fail with `GDR_ERROR_INVALID_OPERATION`, except
/// `gdr_filter_cancel`, `gdr_filter_retain` and `gdr_filter_release` (releasing the last
/// reference is safe: execute holds its own until it returns).
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_set_progress_callback(
    filter: *mut gdr_filter,
    callback: gdr_progress_fn,
    user: *mut c_void,
) -> gdr_error {
    with_filter("gdr_filter_set_progress_callback", filter, |_, st| {
        st.progress = callback.map(|f| (f, UserPtr(user)));
        Ok(())
    })
}

/// Validate the images and parameters and plan the method for the image size (expensive the first time; cheap when only pointers changed).
///
/// Errors: a required image missing, or method `"frgr"` without `"spp"` (its weights depend on
/// the sample count) (`GDR_ERROR_INVALID_OPERATION`), sizes that disagree
/// (`GDR_ERROR_INVALID_IMAGE`), an output partially overlapping an input (`GDR_ERROR_OVERLAP`;
/// the output may be exactly an input view, i.e. in place), a parameter out of range
/// (`GDR_ERROR_INVALID_ARGUMENT`), a plan over the context's `"max_memory_mb"`
/// (`GDR_ERROR_OUT_OF_MEMORY`). With image `"prior"` set, the plan does not count Open Image
/// Denoise's scratch memory, which it then never needs.
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_commit(filter: *mut gdr_filter) -> gdr_error {
    with_filter("gdr_filter_commit", filter, |f, st| {
        same_process(f.pid)?;
        let note = st.commit(&f.pool)?;
        if !note.is_empty() {
            f.context.log(GDR_LOG_DEBUG, &note);
        }
        Ok(())
    })
}

/// Run the committed filter: read the input views, reconstruct, write the output view; blocks until done.
///
/// Errors: not committed since the last change (`GDR_ERROR_INVALID_OPERATION`), bad values in
/// strict mode (`GDR_ERROR_INVALID_INPUT`), cancelled (`GDR_ERROR_CANCELLED`; the output is then
/// left untouched).
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_execute(filter: *mut gdr_filter) -> gdr_error {
    with_filter("gdr_filter_execute", filter, |f, st| {
        same_process(f.pid)?;
        if st.dirty || st.plan.is_none() {
            return err(
                GDR_ERROR_INVALID_OPERATION,
                "the filter changed since its last commit (or was never committed): call gdr_filter_commit",
            );
        }
        f.cancel.store(false, Ordering::SeqCst);
        let policy = if st.strict {
            Policy::Strict
        } else {
            Policy::Replace
        };
        let spp = (st.spp > 0.0).then_some(st.spp);
        let inputs = &st.inputs;
        let frame = f.pool.install(|| {
            let mut builder = FrameBuilder::new().spp(spp);
            for (layer, view) in inputs {
                // SAFETY: the caller keeps the memory valid until execute returns.
                builder = builder.view(*layer, unsafe { view.array() });
            }
            builder.build(policy)
        })?;
        let callback = st.progress;
        let cancel = &f.cancel;
        // `Progress::update` checks the cancel flag before calling this; the check after the
        // caller's callback catches a cancel made during it.
        let on_progress = move |fraction: f64| -> bool {
            match callback {
                Some((cb, user)) => {
                    // SAFETY: the caller registered `cb` with `user` for exactly this use.
                    let go_on = unsafe { cb(user.0, fraction) };
                    go_on && !cancel.load(Ordering::SeqCst)
                }
                None => true,
            }
        };
        // The flag is polled inside the methods' loops: a cancel lands within one band or tile.
        let progress = Progress::new(&on_progress).with_cancel(cancel);
        let State {
            plan, out, output, ..
        } = &mut *st;
        let plan = plan.as_mut().expect("a committed filter has a plan");
        let report = plan.execute_into(&frame, out, &progress)?;
        drop(frame);
        let output = (*output).expect("a committed filter has an output");
        // SAFETY: the caller keeps the output memory valid and writable until execute returns;
        // the inputs were copied into the frame above, so in-place views are fine.
        unsafe { output.write(out) };
        let text = report.to_string();
        if report.sanitized.total() > 0 {
            f.context.log(
                GDR_LOG_WARNING,
                &format!("input values replaced: {}", report.sanitized),
            );
        }
        f.context.log(GDR_LOG_INFO, text.trim_end());
        st.report = CString::new(text.replace('\0', " ")).unwrap_or_default();
        Ok(())
    })
}

/// Ask a running execute on `filter` to stop (it returns `GDR_ERROR_CANCELLED` promptly); callable from any thread, lock-free.
///
/// A cancel when no execute is running has no effect (each execute starts uncancelled).
/// Every method returns within about 60 ms of the cancel at 1280 x 720. Open Image Denoise
/// (the prior paths) stops only between its operations, up to 0.35 s apart: the execute
/// returns at once, OIDN finishes its operation in the background on buffers the filter owns
/// (none of the caller's); the filter's next execute waits for it (cancellably), and so does
/// its last release, so that nothing of a released filter goes on running.
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_cancel(filter: *mut gdr_filter) -> gdr_error {
    guard("gdr_filter_cancel", || {
        let Some(f) = filter.as_ref() else {
            return err(GDR_ERROR_NULL_POINTER, "filter is NULL");
        };
        f.cancel.store(true, Ordering::SeqCst);
        Ok(())
    })
}

/// Point `*text` at the report of the last successful execute ("" before the first); valid until the next execute or release.
#[no_mangle]
pub unsafe extern "C" fn gdr_filter_get_report(
    filter: *mut gdr_filter,
    text: *mut *const c_char,
) -> gdr_error {
    with_filter("gdr_filter_get_report", filter, |_, st| {
        *out_ptr(text, "text")? = st.report.as_ptr();
        Ok(())
    })
}
