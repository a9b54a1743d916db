//! Intel Open Image Denoise, opened at run time: the dozen C functions the prior needs.
//!
//! gdrecon links nothing of OIDN. The library is searched like ONNX Runtime ([`crate::dylib`]):
//! an explicit path (Rust [`crate::ContextOptions::oidn`], the CLI's `--oidn`, the C context's
//! `"oidn_path"`), `OIDN_DYLIB_PATH`, a `libOpenImageDenoise.so*` next to the gdrecon library,
//! then the project's Python environment (PyPI `pyoidn` carries OIDN 2.5 with its TBB and CPU
//! device module beside it, found through the library's own rpath). An explicit path is the
//! only one tried when given: a caller who names a library means that one.
//!
//! The library is opened once per process and never closed (OIDN's TBB threads do not survive
//! an unload): the first one loaded serves every later context, whatever path it names (the
//! report names the file in use); one [`Device`] per [`crate::Context`] (its thread count, no affinity: hosts own
//! their threads), one [`Filter`] per plan, reused frame after frame.
//!
//! This file and `capi/` are the only `unsafe` code: calling into a C library cannot be
//! anything else. Every call is on a handle this file created and still owns, with buffers
//! whose sizes it checked.
#![allow(unsafe_code)]

use std::ffi::{c_char, c_int, c_void, CStr, CString};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

use libloading::Library;

use crate::dylib::{first_that_opens, numbered, Search};
use crate::error::{Error, Result};
use crate::image::try_vec;
use crate::progress::Progress;

/// `OIDN_DEVICE_TYPE_CPU`.
const DEVICE_CPU: c_int = 1;
/// `OIDN_FORMAT_FLOAT3`.
const FORMAT_FLOAT3: c_int = 3;
/// `OIDN_QUALITY_HIGH` (final-frame quality).
pub(crate) const QUALITY_HIGH: c_int = 6;
/// `OIDN_QUALITY_BALANCED`.
pub(crate) const QUALITY_BALANCED: c_int = 5;
/// `OIDN_QUALITY_FAST`.
pub(crate) const QUALITY_FAST: c_int = 4;
/// The major version the functions below are declared for.
const MAJOR: c_int = 2;

type Handle = *mut c_void;

/// `OIDNProgressMonitorFunction`: returns false to cancel the running filter.
type Monitor = unsafe extern "C" fn(*mut c_void, f64) -> bool;

/// The progress monitor: continues while the filter's stop flag is clear (OIDN calls it
/// between its operations, which is how a cancel stops a second-long denoise early).
unsafe extern "C" fn keep_going(user: *mut c_void, _done: f64) -> bool {
    // SAFETY: `user` is the filter's boxed stop flag, set as the monitor's argument when the
    // filter was made; the box lives (at a fixed address) as long as the filter handle.
    let stop = unsafe { &*user.cast::<AtomicBool>() };
    !stop.load(Ordering::Relaxed)
}

/// The functions used, resolved once.
struct Api {
    new_device: unsafe extern "C" fn(c_int) -> Handle,
    set_device_int: unsafe extern "C" fn(Handle, *const c_char, c_int),
    set_device_bool: unsafe extern "C" fn(Handle, *const c_char, bool),
    get_device_int: unsafe extern "C" fn(Handle, *const c_char) -> c_int,
    commit_device: unsafe extern "C" fn(Handle),
    release_device: unsafe extern "C" fn(Handle),
    get_device_error: unsafe extern "C" fn(Handle, *mut *const c_char) -> c_int,
    new_filter: unsafe extern "C" fn(Handle, *const c_char) -> Handle,
    #[allow(clippy::type_complexity)]
    set_shared_filter_image: unsafe extern "C" fn(
        Handle,
        *const c_char,
        *mut c_void,
        c_int,
        usize,
        usize,
        usize,
        usize,
        usize,
    ),
    unset_filter_image: unsafe extern "C" fn(Handle, *const c_char),
    set_filter_bool: unsafe extern "C" fn(Handle, *const c_char, bool),
    set_filter_int: unsafe extern "C" fn(Handle, *const c_char, c_int),
    commit_filter: unsafe extern "C" fn(Handle),
    execute_filter: unsafe extern "C" fn(Handle),
    set_filter_progress: unsafe extern "C" fn(Handle, Option<Monitor>, *mut c_void),
    release_filter: unsafe extern "C" fn(Handle),
}

/// The loaded library.
pub(crate) struct Oidn {
    api: Api,
    /// The file that was loaded.
    pub path: PathBuf,
    /// Never dropped: the function pointers above point into it.
    _library: Library,
}

static LOADED: OnceLock<Oidn> = OnceLock::new();
static LOADING: Mutex<()> = Mutex::new(());

#[cfg(target_os = "macos")]
const LIBRARY_PREFIX: &str = "libOpenImageDenoise.";
#[cfg(not(target_os = "macos"))]
const LIBRARY_PREFIX: &str = "libOpenImageDenoise.so";

fn search(explicit: Option<&Path>) -> Search<'_> {
    Search {
        explicit_name: "ContextOptions::oidn, --oidn, \"oidn_path\"",
        explicit,
        env: "OIDN_DYLIB_PATH",
        prefix: LIBRARY_PREFIX,
        package_dir: "pyoidn/oidn/lib",
        package: "pyoidn",
    }
}

/// The process's OIDN library, opened on first call.
pub(crate) fn library(explicit: Option<&Path>) -> Result<&'static Oidn> {
    if let Some(lib) = LOADED.get() {
        return Ok(lib);
    }
    let _serialised = LOADING.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(lib) = LOADED.get() {
        return Ok(lib);
    }
    let mut candidates = search(explicit).candidates();
    if explicit.is_some() {
        candidates.truncate(1);
    }
    let tried = match first_that_opens(candidates, open) {
        Ok((lib, _)) => return Ok(LOADED.get_or_init(|| lib)),
        Err(tried) => tried,
    };
    Err(Error::Unsupported(format!(
        "this method needs Intel Open Image Denoise 2 (libOpenImageDenoise.so.2) for its prior, \
         and none could be loaded. Tried, in order:\n{}\nInstall it with `bash onnx/setup.sh` \
         (the project's Python environment, pyoidn 2.5.1), or point OIDN_DYLIB_PATH at a \
         libOpenImageDenoise.so.2; or give the frame a 'prior' layer. Methods without a prior \
         do not need it.",
        numbered(&tried)
    )))
}

/// Opens `path` and resolves every function, or says what is wrong with the file.
fn open(path: &Path) -> std::result::Result<Oidn, String> {
    // SAFETY: loading runs the library's initialisers; OIDN's are the ones its own loaders
    // (pyoidn, renderers) run too.
    let library = unsafe { Library::new(path) }
        .map_err(|e| format!("cannot be loaded as a shared library ({e})"))?;
    macro_rules! symbol {
        ($name:literal) => {
            // SAFETY: the declared type is the function's signature in OIDN 2's C header
            // (include/OpenImageDenoise/oidn.h), checked against the version below.
            *unsafe { library.get(concat!($name, "\0").as_bytes()) }
                .map_err(|e| format!("is not Open Image Denoise 2: it lacks {} ({e})", $name))?
        };
    }
    let api = Api {
        new_device: symbol!("oidnNewDevice"),
        set_device_int: symbol!("oidnSetDeviceInt"),
        set_device_bool: symbol!("oidnSetDeviceBool"),
        get_device_int: symbol!("oidnGetDeviceInt"),
        commit_device: symbol!("oidnCommitDevice"),
        release_device: symbol!("oidnReleaseDevice"),
        get_device_error: symbol!("oidnGetDeviceError"),
        new_filter: symbol!("oidnNewFilter"),
        set_shared_filter_image: symbol!("oidnSetSharedFilterImage"),
        unset_filter_image: symbol!("oidnUnsetFilterImage"),
        set_filter_bool: symbol!("oidnSetFilterBool"),
        set_filter_int: symbol!("oidnSetFilterInt"),
        commit_filter: symbol!("oidnCommitFilter"),
        execute_filter: symbol!("oidnExecuteFilter"),
        set_filter_progress: symbol!("oidnSetFilterProgressMonitorFunction"),
        release_filter: symbol!("oidnReleaseFilter"),
    };
    Ok(Oidn {
        api,
        path: path.to_owned(),
        _library: library,
    })
}

/// A C string for a parameter name (all are static ASCII).
fn c(name: &str) -> CString {
    CString::new(name).expect("OIDN parameter names hold no NUL")
}

/// An OIDN CPU device.
pub(crate) struct Device {
    lib: &'static Oidn,
    handle: Handle,
    /// OIDN's version as `major * 10000 + minor * 100 + patch`.
    pub version: i32,
}

// SAFETY: OIDN's API is thread-safe ("all API calls are thread-safe; operations that use the
// same device are serialised"), and the handle is only released on drop.
unsafe impl Send for Device {}
// SAFETY: as above.
unsafe impl Sync for Device {}

impl Device {
    /// A committed CPU device running on `threads` threads, without setting thread affinity.
    pub(crate) fn new(lib: &'static Oidn, threads: usize) -> Result<Self> {
        let api = &lib.api;
        // SAFETY: `new_device` takes a device type and returns a handle or null.
        let handle = unsafe { (api.new_device)(DEVICE_CPU) };
        if handle.is_null() {
            return Err(Error::Unsupported(format!(
                "Open Image Denoise ({}) could not create a CPU device",
                lib.path.display()
            )));
        }
        let mut device = Device {
            lib,
            handle,
            version: 0,
        };
        let threads = c_int::try_from(threads).unwrap_or(c_int::MAX);
        // SAFETY: `handle` is a live device; names are NUL-terminated.
        unsafe {
            (api.set_device_int)(handle, c("numThreads").as_ptr(), threads);
            (api.set_device_bool)(handle, c("setAffinity").as_ptr(), false);
            (api.commit_device)(handle);
        }
        device.check("creating the device")?;
        // SAFETY: as above.
        let version = unsafe { (api.get_device_int)(handle, c("version").as_ptr()) };
        device.version = version;
        if version / 10000 != MAJOR {
            return Err(Error::Unsupported(format!(
                "{} is Open Image Denoise {}.{}.{}; gdrecon needs version 2",
                lib.path.display(),
                version / 10000,
                version / 100 % 100,
                version % 100
            )));
        }
        Ok(device)
    }

    /// The loaded library's path.
    pub(crate) fn path(&self) -> &Path {
        &self.lib.path
    }

    /// The device's pending error, if any, as an [`Error`] naming `what` was being done.
    fn check(&self, what: &str) -> Result<()> {
        let mut message: *const c_char = std::ptr::null();
        // SAFETY: `handle` is live; OIDN writes a pointer to its own message (or null), valid
        // until the next call on this device, and we copy it at once.
        let code = unsafe { (self.lib.api.get_device_error)(self.handle, &mut message) };
        if code == 0 {
            return Ok(());
        }
        let text = if message.is_null() {
            String::from("no message")
        } else {
            // SAFETY: non-null messages are NUL-terminated C strings.
            unsafe { CStr::from_ptr(message) }
                .to_string_lossy()
                .into_owned()
        };
        Err(Error::Denoiser(format!(
            "{what}: {text} (error code {code})"
        )))
    }
}

impl Drop for Device {
    fn drop(&mut self) {
        // SAFETY: the handle is live and released once; filters hold their own reference.
        unsafe { (self.lib.api.release_device)(self.handle) }
    }
}

/// A [`Filter`]'s interleaved RGB buffers for `width` x `height` images (48 bytes a pixel):
/// made by a plan, before OIDN is loaded, so that their 44 MB at 1280 x 720 are written (20-30
/// ms, in some runs 140-190 ms) while planning, not in a first execute that a cancel cannot stop.
pub(crate) struct Buffers {
    width: usize,
    height: usize,
    colour: Vec<f32>,
    albedo: Vec<f32>,
    normal: Vec<f32>,
    output: Vec<f32>,
}

impl Buffers {
    /// Zeroed buffers for `width` x `height` images.
    pub(crate) fn new(width: usize, height: usize) -> Result<Self> {
        let n = 3 * width * height;
        Ok(Buffers {
            width,
            height,
            colour: try_vec(n, 0.0)?,
            albedo: try_vec(n, 0.0)?,
            normal: try_vec(n, 0.0)?,
            output: try_vec(n, 0.0)?,
        })
    }
}

/// An RT filter (HDR, the given quality) for one image size, with the interleaved buffers its
/// images are read from and written to. OIDN's filter object is made by the first
/// [`Filter::execute`], on the thread that runs it: a call on a device waits while another
/// filter of the device runs, and that wait must not keep a cancel from returning.
pub(crate) struct Filter {
    device: std::sync::Arc<Device>,
    /// Null until the first run.
    handle: Handle,
    quality: c_int,
    /// `maxMemoryMB`: the scratch memory OIDN may use before it denoises in tiles.
    max_memory_mb: u64,
    /// Interleaved RGB: colour, albedo, normal, output.
    buffers: Buffers,
    /// Which auxiliary images the filter was last committed with.
    committed: Option<(bool, bool)>,
    /// Read by the progress monitor: set to stop the run in flight (shared with the thread
    /// that waits on a [`Runner`]'s run).
    stop: Arc<AtomicBool>,
}

// SAFETY: the filter handle is used by one thread at a time (`&mut self` to execute); OIDN
// allows moving it between threads.
unsafe impl Send for Filter {}

impl Filter {
    /// A filter on `device` for the images `buffers` were made for (OIDN is not called).
    pub(crate) fn new(
        device: std::sync::Arc<Device>,
        buffers: Buffers,
        quality: c_int,
        max_memory_mb: u64,
    ) -> Self {
        Filter {
            device,
            handle: std::ptr::null_mut(),
            quality,
            max_memory_mb,
            buffers,
            committed: None,
            stop: Arc::new(AtomicBool::new(false)),
        }
    }

    /// Makes OIDN's filter object: RT, HDR, the quality, its scratch memory bounded (the
    /// plan's [`super::Scratch`]), the stop flag as progress monitor.
    fn create(&mut self) -> Result<()> {
        let api = &self.device.lib.api;
        // SAFETY: the device is live; "RT" is a NUL-terminated filter type.
        let handle = unsafe { (api.new_filter)(self.device.handle, c("RT").as_ptr()) };
        self.device.check("creating the RT filter")?;
        if handle.is_null() {
            return Err(Error::Denoiser("the RT filter could not be created".into()));
        }
        self.handle = handle;
        let user = Arc::as_ptr(&self.stop).cast_mut().cast::<c_void>();
        // SAFETY: `handle` is a live filter; the flag outlives it (the handle is released in
        // `drop`, before the `Arc` field is dropped).
        unsafe {
            (api.set_filter_bool)(handle, c("hdr").as_ptr(), true);
            (api.set_filter_int)(handle, c("quality").as_ptr(), self.quality);
            let max_memory = c_int::try_from(self.max_memory_mb).unwrap_or(c_int::MAX);
            (api.set_filter_int)(handle, c("maxMemoryMB").as_ptr(), max_memory);
            (api.set_filter_progress)(handle, Some(keep_going), user);
        }
        self.device.check("configuring the RT filter")
    }

    /// OIDN's version (`major * 10000 + minor * 100 + patch`).
    pub(crate) fn version(&self) -> i32 {
        self.device.version
    }

    /// The loaded library's path.
    pub(crate) fn path(&self) -> &Path {
        self.device.path()
    }

    /// The interleaved input buffers to fill (colour, albedo, normal), each `3 * w * h`.
    pub(crate) fn inputs(&mut self) -> (&mut [f32], &mut [f32], &mut [f32]) {
        let b = &mut self.buffers;
        (&mut b.colour, &mut b.albedo, &mut b.normal)
    }

    /// Denoises the colour buffer (with the albedo and normal buffers when asked) into the
    /// output buffer, on the calling thread; stops early when the stop flag is set, with
    /// `Error::Cancelled`.
    fn execute(&mut self, albedo: bool, normal: bool) -> Result<()> {
        if self.handle.is_null() {
            self.create()?;
        }
        let api = &self.device.lib.api;
        let (w, h) = (self.buffers.width, self.buffers.height);
        let stride = 3 * std::mem::size_of::<f32>();
        if self.committed != Some((albedo, normal)) {
            let handle = self.handle;
            let set = |name: &str, buffer: *mut f32| {
                // SAFETY: `buffer` holds `3 * w * h` floats, packed (pixel stride 12 bytes, row
                // stride 12 w), and lives, never reallocated, as long as the filter.
                unsafe {
                    (api.set_shared_filter_image)(
                        handle,
                        c(name).as_ptr(),
                        buffer.cast(),
                        FORMAT_FLOAT3,
                        w,
                        h,
                        0,
                        stride,
                        stride * w,
                    )
                }
            };
            set("color", self.buffers.colour.as_mut_ptr());
            set("output", self.buffers.output.as_mut_ptr());
            for (name, wanted, buffer) in [
                ("albedo", albedo, self.buffers.albedo.as_mut_ptr()),
                ("normal", normal, self.buffers.normal.as_mut_ptr()),
            ] {
                if wanted {
                    set(name, buffer);
                } else {
                    // SAFETY: unsetting an image that was never set is allowed.
                    unsafe { (api.unset_filter_image)(handle, c(name).as_ptr()) }
                }
            }
            // SAFETY: every image the filter reads is set above.
            unsafe { (api.commit_filter)(self.handle) };
            self.device.check("committing the RT filter")?;
            self.committed = Some((albedo, normal));
        }
        // SAFETY: committed with live, correctly sized buffers; `&mut self` keeps them
        // unaliased while OIDN reads and writes them.
        unsafe { (api.execute_filter)(self.handle) };
        // OIDN keeps errors per thread: they are read here, on the thread that ran the filter.
        if self.stop.load(Ordering::Relaxed) {
            // OIDN's error for the cancelled run (OIDN_ERROR_CANCELLED) is read and dropped.
            let _ = self.device.check("running the RT filter");
            return Err(Error::Cancelled);
        }
        self.device.check("running the RT filter")
    }
}

/// How often a waiting [`Runner::run`] looks at the plan's cancel flag.
const POLL: Duration = Duration::from_millis(2);

/// Runs a [`Filter`] so that a cancel returns at once.
///
/// OIDN checks its progress monitor only between operations, and one operation can take a
/// third of a run (0.35 s of a 1.2 s denoise at 1280 x 720 on two cores). A run that can be
/// cancelled therefore goes to a thread of its own, with the filter and the buffers it owns,
/// while the caller waits for it or for the cancel flag. On a cancel the caller returns at
/// once; the run stops at OIDN's next operation on that thread, which then drops the result,
/// and the next run, or the plan's release, waits for the filter to come back. No caller memory is touched after the return: OIDN reads and writes only the
/// filter's own buffers. Runs that cannot be cancelled stay on the calling thread.
pub(crate) struct Runner {
    /// The filter, when no run holds it.
    idle: Option<Filter>,
    /// The way back of the filter from a cancelled run still finishing its operation.
    returning: Option<Receiver<Finished>>,
}

/// A run's filter and result, as its thread hands them back.
type Finished = (Filter, Result<()>);

impl Runner {
    /// A runner for `filter`.
    pub(crate) fn new(filter: Filter) -> Self {
        Runner {
            idle: Some(filter),
            returning: None,
        }
    }

    /// The filter, to fill its inputs ([`Filter::inputs`]) before [`Runner::run`]; waits for
    /// a cancelled run to give it back first (at most the rest of one OIDN operation), unless
    /// `progress` is cancelled meanwhile.
    pub(crate) fn filter(&mut self, progress: &Progress) -> Result<&mut Filter> {
        if let Some(back) = self.returning.take() {
            let (filter, _cancelled) = wait(&back, progress).inspect_err(|e| {
                if matches!(e, Error::Cancelled) {
                    self.returning = Some(back);
                }
            })?;
            self.idle = Some(filter);
        }
        self.idle.as_mut().ok_or_else(lost)
    }

    /// Denoises what was filled (with the albedo and normal buffers when asked) and returns
    /// the interleaved output. A cancel of `progress` returns `Error::Cancelled` within
    /// [`POLL`] of the flag.
    pub(crate) fn run(
        &mut self,
        albedo: bool,
        normal: bool,
        progress: &Progress,
    ) -> Result<&[f32]> {
        self.filter(progress)?.stop.store(false, Ordering::Relaxed);
        if !progress.can_stop() {
            let filter = self.idle.as_mut().ok_or_else(lost)?;
            filter.execute(albedo, normal)?;
            return Ok(&filter.buffers.output);
        }
        progress.check()?;
        let mut filter = self.idle.take().ok_or_else(lost)?;
        let stop = Arc::clone(&filter.stop);
        let (give, back) = mpsc::channel::<Finished>();
        let started = std::thread::Builder::new()
            .name("gdrecon-oidn".into())
            .spawn(move || {
                let result = filter.execute(albedo, normal);
                // Received by the next run or by the runner's `Drop`, which wait for it.
                let _ = give.send((filter, result));
            });
        if let Err(e) = started {
            // The closure, and the filter with it, is gone: the next run makes a new one.
            return Err(Error::OutOfMemory(format!(
                "could not start a thread to run Open Image Denoise: {e}"
            )));
        }
        match wait(&back, progress) {
            Ok((filter, result)) => {
                let filter = self.idle.insert(filter);
                result?;
                Ok(&filter.buffers.output)
            }
            Err(Error::Cancelled) => {
                stop.store(true, Ordering::Relaxed);
                self.returning = Some(back);
                Err(Error::Cancelled)
            }
            Err(e) => Err(e),
        }
    }

    /// Whether the runner has no filter any more (a run's thread could not start or died):
    /// the caller makes a new one.
    pub(crate) fn is_lost(&self) -> bool {
        self.idle.is_none() && self.returning.is_none()
    }
}

/// A plan released after a cancel waits here for its run's last operation (its stop flag is
/// set: OIDN stops at the operation's end, at most 0.35 s at 1280 x 720 on two cores), so
/// that nothing of it goes on once the release returns: a cancelled run left to finish on its
/// own kept both cores busy into whatever the caller did next (the next plan's cancel took
/// 365 ms to return on a CI machine, 30-60 ms alone).
impl Drop for Runner {
    fn drop(&mut self) {
        if let Some(back) = self.returning.take() {
            // Err: the thread is gone already (it dropped the filter itself).
            let _ = back.recv();
        }
    }
}

/// What comes back through `back`, or `Error::Cancelled` within [`POLL`] of a cancel of
/// `progress`.
fn wait(back: &Receiver<Finished>, progress: &Progress) -> Result<Finished> {
    loop {
        match back.recv_timeout(POLL) {
            Ok(finished) => return Ok(finished),
            Err(RecvTimeoutError::Timeout) => progress.check()?,
            Err(RecvTimeoutError::Disconnected) => return Err(lost()),
        }
    }
}

fn lost() -> Error {
    Error::Denoiser(
        "the thread running Open Image Denoise stopped without returning its filter".into(),
    )
}

impl Drop for Filter {
    fn drop(&mut self) {
        if !self.handle.is_null() {
            // SAFETY: the handle is live and released once, before the device it came from.
            unsafe { (self.device.lib.api.release_filter)(self.handle) }
        }
    }
}
