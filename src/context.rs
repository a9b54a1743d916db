//! The execution context: the thread pool every method runs on.
//!
//! Like an Open Image Denoise device, a context is created once and shared by the plans made
//! from it. It never pins threads (hosts own their affinity) and takes an explicit thread
//! count so a renderer can leave cores to its own pool. Results do not depend on the thread
//! count: every parallel reduction in gdrecon has a fixed order.

use std::any::Any;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use crate::error::{Error, Result};

/// Settings of a [`Context`].
#[derive(Clone, Debug, Default, PartialEq, Eq)]
#[non_exhaustive]
pub struct ContextOptions {
    /// Worker threads; `None` uses every available core.
    pub threads: Option<usize>,
    /// The Open Image Denoise library the prior paths load (`libOpenImageDenoise.so.2`); `None`
    /// searches `OIDN_DYLIB_PATH`, the gdrecon library's folder and the project's Python
    /// environment. Only a plan that must compute a prior loads it.
    pub oidn: Option<PathBuf>,
    /// The most memory, in MiB, a plan of this context may estimate it needs beyond the frame
    /// (buffers, scratch, the output, OIDN's or ONNX Runtime's share). As OIDN's
    /// `maxMemoryMB`, it sizes tiles: `Plan::new` lowers what GradNet and the combiner run at
    /// once (down to tiles of four margins a side, as OIDN's stop at three overlaps), and
    /// OIDN's scratch (down to 512 MiB), to fit (the same image up to rounding, in more
    /// time), and refuses with [`Error::OutOfMemory`] only a plan whose smallest tiles are
    /// still over it (`auto` leaves out the paths over it and is refused when none fits). 0
    /// means no limit (the default); the address space the process has left under its limit
    /// (`ulimit -v`) bounds plans the same way either way.
    pub max_memory_mb: u64,
}

impl ContextOptions {
    /// Options with `threads` worker threads (`None`: every available core).
    pub fn with_threads(threads: Option<usize>) -> Self {
        ContextOptions {
            threads,
            ..Self::default()
        }
    }

    /// These options with a memory limit for each plan, in MiB (0: none).
    pub fn with_max_memory_mb(self, max_memory_mb: u64) -> Self {
        ContextOptions {
            max_memory_mb,
            ..self
        }
    }

    /// These options with an explicit Open Image Denoise library.
    pub fn with_oidn(self, path: impl Into<PathBuf>) -> Self {
        ContextOptions {
            oidn: Some(path.into()),
            ..self
        }
    }
}

/// A thread pool shared by plans. Cheap to clone (reference counted).
#[derive(Clone, Debug)]
pub struct Context {
    pool: Arc<rayon::ThreadPool>,
    #[cfg_attr(not(any(feature = "gradnet", feature = "oidn")), allow(dead_code))]
    shared: Arc<Shared>,
    #[cfg_attr(not(feature = "oidn"), allow(dead_code))]
    oidn: Option<PathBuf>,
    max_memory_mb: u64,
}

/// Objects that plans of one context share (loaded models), by key. Type-erased so that the
/// core does not know what a method keeps here.
#[derive(Default)]
struct Shared(Mutex<Vec<(String, Arc<dyn Any + Send + Sync>)>>);

impl std::fmt::Debug for Shared {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let items = self.0.lock().unwrap_or_else(|p| p.into_inner());
        f.debug_list()
            .entries(items.iter().map(|(k, _)| k))
            .finish()
    }
}

/// The most worker threads a context starts.
pub const MAX_THREADS: usize = 1024;

impl Context {
    /// Creates a context; fails on a zero thread count or when the OS refuses threads.
    pub fn new(options: ContextOptions) -> Result<Self> {
        if options.threads == Some(0) {
            return Err(Error::arg(
                "threads is 0: use at least 1, or leave it unset for all cores",
            ));
        }
        if let Some(n) = options.threads.filter(|&n| n > MAX_THREADS) {
            // Checked before spawning: the OS took 83 s to refuse 100000 threads.
            return Err(Error::arg(format!(
                "threads is {n}: at most {MAX_THREADS} (leave it unset for all cores)"
            )));
        }
        let threads = options.threads.unwrap_or_else(|| {
            std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1)
        });
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("gdrecon-{i}"))
            .build()
            .map_err(|e| Error::Unsupported(format!("cannot start {threads} threads: {e}")))?;
        Ok(Context {
            pool: Arc::new(pool),
            shared: Arc::default(),
            oidn: options.oidn,
            max_memory_mb: options.max_memory_mb,
        })
    }

    /// The per-plan memory limit in MiB (0: none).
    pub fn max_memory_mb(&self) -> u64 {
        self.max_memory_mb
    }

    /// Number of worker threads.
    pub fn threads(&self) -> usize {
        self.pool.current_num_threads()
    }

    /// The object stored under `key`, made by `make` on first request and shared by every
    /// plan of this context (and its clones) afterwards. A failed `make` stores nothing.
    #[cfg_attr(not(any(feature = "gradnet", feature = "oidn")), allow(dead_code))]
    pub(crate) fn shared<T: Any + Send + Sync>(
        &self,
        key: &str,
        make: impl FnOnce() -> Result<T>,
    ) -> Result<Arc<T>> {
        let mut items = self.shared.0.lock().unwrap_or_else(|p| p.into_inner());
        if let Some((_, item)) = items.iter().find(|(k, _)| k == key) {
            if let Ok(item) = item.clone().downcast::<T>() {
                return Ok(item);
            }
        }
        let item = Arc::new(make()?);
        items.retain(|(k, _)| k != key);
        items.push((key.to_owned(), item.clone()));
        Ok(item)
    }

    /// This context's Open Image Denoise device (its thread count), opening the library and
    /// making the device on first request.
    #[cfg(feature = "oidn")]
    pub(crate) fn denoiser(&self) -> Result<Arc<crate::recon::prior::oidn::Device>> {
        use crate::recon::prior::oidn;
        self.shared("oidn device", || {
            oidn::Device::new(oidn::library(self.oidn.as_deref())?, self.threads())
        })
    }

    /// Runs `f` on this context's pool.
    pub fn install<T: Send>(&self, f: impl FnOnce() -> T + Send) -> T {
        self.pool.install(f)
    }
}
