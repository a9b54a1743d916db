//! Finding ONNX Runtime and holding the process's one `ort` environment.
//!
//! gdrecon links nothing of ONNX Runtime: the library is opened on the first GradNet or
//! combiner plan, so a
//! renderer that only uses the other methods never touches it. Candidates, in order
//! ([`crate::dylib`]'s search; the error lists each with why it failed):
//! 1. an explicit path (the method's `runtime` setting, the CLI's `--onnxruntime`, the C
//!    context's `"onnxruntime_path"`);
//! 2. the `ORT_DYLIB_PATH` environment variable;
//! 3. a `libonnxruntime.so*` next to the gdrecon library (or the executable it is linked
//!    into);
//! 4. the project's Python environment (`$GDRECON_VENV`, default `~/.cache/gdrecon/venv`, made
//!    by `onnx/setup.sh`): `lib/python3*/site-packages/onnxruntime/capi/`.
//!
//! ONNX Runtime allows one environment per process, ever (building a second fails even after
//! the first is dropped), and `ort` keeps the first library it loaded: both live in a
//! process-wide `OnceLock` and are never dropped.

use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use ort::environment::Environment;

use crate::dylib::{first_that_opens, numbered, Candidate, Search};
use crate::error::{Error, Result};

/// The loaded runtime.
pub(crate) struct Runtime {
    pub env: Environment,
    /// The library file that was loaded.
    pub path: PathBuf,
}

static RUNTIME: OnceLock<Runtime> = OnceLock::new();
static LOADING: Mutex<()> = Mutex::new(());

/// The process's runtime, loading it on first call.
pub(crate) fn runtime(explicit: Option<&Path>) -> Result<&'static Runtime> {
    if let Some(rt) = RUNTIME.get() {
        return Ok(rt);
    }
    let _serialised = LOADING.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(rt) = RUNTIME.get() {
        return Ok(rt);
    }
    let tried = match first_that_opens(candidates(explicit), load) {
        Ok((env, path)) => return Ok(RUNTIME.get_or_init(|| Runtime { env, path })),
        Err(tried) => tried,
    };
    Err(Error::Unsupported(format!(
        "GradNet and the combiner need ONNX Runtime 1.31 (libonnxruntime.so.1.31.x) and none could be loaded. \
         Tried, in order:\n{}\nInstall it with `bash onnx/setup.sh` (the project's Python \
         environment, onnxruntime 1.31.1), or `pip install onnxruntime==1.31.1` and point \
         ORT_DYLIB_PATH at its onnxruntime/capi/libonnxruntime.so.1.31.1. The other methods \
         (l2, l1, frgr, prior) do not need it.",
        numbered(&tried)
    )))
}

fn load(path: &Path) -> std::result::Result<Environment, String> {
    let builder = ort::init_from(path).map_err(|e| e.to_string())?;
    builder
        .with_name("gdrecon")
        .with_telemetry(false)
        .build()
        .map_err(|e| format!("the library loaded but its environment failed: {e}"))
}

/// Where ONNX Runtime is searched ([`crate::dylib`]'s steps).
pub(crate) fn candidates(explicit: Option<&Path>) -> Vec<Candidate> {
    Search {
        explicit_name: "runtime setting, --onnxruntime, \"onnxruntime_path\"",
        explicit,
        env: "ORT_DYLIB_PATH",
        prefix: LIBRARY_PREFIX,
        package_dir: "onnxruntime/capi",
        package: "onnxruntime",
    }
    .candidates()
}

#[cfg(target_os = "macos")]
const LIBRARY_PREFIX: &str = "libonnxruntime.";
#[cfg(not(target_os = "macos"))]
const LIBRARY_PREFIX: &str = "libonnxruntime.so";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn candidates_report_every_step_in_order() {
        let c = candidates(Some(Path::new("/nonexistent/libonnxruntime.so")));
        assert_eq!(c.len(), 4);
        assert!(c[0].0.starts_with("explicit path"));
        assert!(c[0].1.as_ref().unwrap_err().contains("does not exist"));
        assert_eq!(c[1].0, "ORT_DYLIB_PATH");
        assert!(c[2].0.starts_with("next to the gdrecon library"));
        assert!(c[3].0.starts_with("the project's Python environment"));
    }
}
