//! Finding ONNX Runtime and holding the process's one `ort` environment.
//!
//! gdrecon links nothing of ONNX Runtime: the library is opened on the first GradNet plan, so a
//! renderer that only uses the other methods never touches it. Candidates, in order (the error
//! lists each with why it failed):
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
    let mut tried = Vec::new();
    for (source, found) in candidates(explicit) {
        let path = match found {
            Ok(path) => path,
            Err(why) => {
                tried.push(format!("{source}: {why}"));
                continue;
            }
        };
        match load(&path) {
            Ok(env) => {
                return Ok(RUNTIME.get_or_init(|| Runtime { env, path }));
            }
            Err(why) => tried.push(format!("{source}: {}: {why}", path.display())),
        }
    }
    Err(Error::Unsupported(format!(
        "GradNet needs ONNX Runtime 1.31 (libonnxruntime.so.1.31.x) and none could be loaded. \
         Tried, in order:\n{}\nInstall it with `bash onnx/setup.sh` (the project's Python \
         environment, onnxruntime 1.31.1), or `pip install onnxruntime==1.31.1` and point \
         ORT_DYLIB_PATH at its onnxruntime/capi/libonnxruntime.so.1.31.1. The other methods \
         (l2, l1, frgr) do not need it.",
        tried
            .iter()
            .enumerate()
            .map(|(i, t)| format!("  {}. {t}", i + 1))
            .collect::<Vec<_>>()
            .join("\n")
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

/// Each discovery step with the file it found, or why it found none.
pub(crate) fn candidates(
    explicit: Option<&Path>,
) -> Vec<(String, std::result::Result<PathBuf, String>)> {
    let mut out = Vec::new();
    out.push((
        "explicit path (runtime setting, --onnxruntime, \"onnxruntime_path\")".to_owned(),
        match explicit {
            Some(p) if p.is_file() => Ok(p.to_owned()),
            Some(p) => Err(format!("{} does not exist", p.display())),
            None => Err("not given".to_owned()),
        },
    ));
    out.push((
        "ORT_DYLIB_PATH".to_owned(),
        match std::env::var_os("ORT_DYLIB_PATH") {
            Some(p) if Path::new(&p).is_file() => Ok(PathBuf::from(p)),
            Some(p) => Err(format!("{} does not exist", Path::new(&p).display())),
            None => Err("not set".to_owned()),
        },
    ));
    let beside = own_directory();
    out.push((
        format!(
            "next to the gdrecon library ({})",
            beside
                .as_deref()
                .map_or("unknown location".into(), |d| d.display().to_string())
        ),
        beside
            .as_deref()
            .and_then(library_in)
            .ok_or_else(|| format!("no {LIBRARY_PREFIX}* there")),
    ));
    let venv = std::env::var_os("GDRECON_VENV")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| Path::new(&h).join(".cache/gdrecon/venv")));
    out.push((
        format!(
            "the project's Python environment ({})",
            venv.as_deref()
                .map_or("HOME not set".into(), |d| d.display().to_string())
        ),
        venv.as_deref()
            .and_then(python_runtime)
            .ok_or_else(|| "no onnxruntime package there (run `bash onnx/setup.sh`)".to_owned()),
    ));
    out
}

#[cfg(target_os = "macos")]
const LIBRARY_PREFIX: &str = "libonnxruntime.";
#[cfg(not(target_os = "macos"))]
const LIBRARY_PREFIX: &str = "libonnxruntime.so";

/// Sorted paths of the entries of `dir` whose name starts with `prefix`.
fn entries_with_prefix(dir: &Path, prefix: &str) -> Option<Vec<PathBuf>> {
    let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
        .ok()?
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with(prefix))
        })
        .collect();
    found.sort();
    Some(found)
}

/// The ONNX Runtime library in `dir`: the unversioned name if present (it sorts first), else
/// the last versioned one (`libonnxruntime.so.1.31.1`).
fn library_in(dir: &Path) -> Option<PathBuf> {
    let found = entries_with_prefix(dir, LIBRARY_PREFIX)?;
    let unversioned = found
        .iter()
        .find(|p| p.file_name().and_then(|n| n.to_str()) == Some(LIBRARY_PREFIX));
    unversioned.or(found.last()).cloned()
}

/// The runtime in a Python environment: `lib/python3*/site-packages/onnxruntime/capi/`.
fn python_runtime(venv: &Path) -> Option<PathBuf> {
    entries_with_prefix(&venv.join("lib"), "python3")?
        .iter()
        .rev()
        .find_map(|p| library_in(&p.join("site-packages/onnxruntime/capi")))
}

/// The directory of the file this code was loaded from: the gdrecon shared library, or the
/// executable it is statically linked into. Found in `/proc/self/maps` (no `dladdr`, so no
/// `unsafe` outside the C API); elsewhere the executable's directory.
fn own_directory() -> Option<PathBuf> {
    let here = own_directory as fn() -> Option<PathBuf> as usize;
    if let Ok(maps) = std::fs::read_to_string("/proc/self/maps") {
        for line in maps.lines() {
            let mut fields = line.split_whitespace();
            let Some((lo, hi)) = fields.next().and_then(|r| r.split_once('-')) else {
                continue;
            };
            let (Ok(lo), Ok(hi)) = (usize::from_str_radix(lo, 16), usize::from_str_radix(hi, 16))
            else {
                continue;
            };
            if (lo..hi).contains(&here) {
                let path = fields.nth(4)?;
                return Path::new(path).parent().map(Path::to_owned);
            }
        }
    }
    std::env::current_exe().ok()?.parent().map(Path::to_owned)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn own_directory_is_where_this_test_binary_lives() {
        let exe = std::env::current_exe().unwrap();
        assert_eq!(own_directory().as_deref(), exe.parent());
    }

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
