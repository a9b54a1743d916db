//! Finding a shared library that gdrecon opens at run time (ONNX Runtime for GradNet, Open
//! Image Denoise for the prior), never at link time.
//!
//! Both follow one search, in order, and an error lists every step with why it failed:
//! 1. an explicit path (a method setting, a CLI flag, a C context string);
//! 2. an environment variable;
//! 3. the library next to the gdrecon library (or the executable it is linked into);
//! 4. the project's Python environment (`$GDRECON_VENV`, default `~/.cache/gdrecon/venv`, made
//!    by `onnx/setup.sh`), in the folder its pip package keeps the library.

use std::path::{Path, PathBuf};

/// One discovery step: what it looked at, and the file it found or why it found none.
pub(crate) type Candidate = (String, std::result::Result<PathBuf, String>);

/// Where a library is searched, for one library.
pub(crate) struct Search<'a> {
    /// The name of the explicit setting(s), for messages (`"--oidn, \"oidn_path\""`).
    pub explicit_name: &'a str,
    /// The explicit path, if given.
    pub explicit: Option<&'a Path>,
    /// The environment variable.
    pub env: &'a str,
    /// The file name's prefix (`libOpenImageDenoise.so`).
    pub prefix: &'a str,
    /// The library's folder inside `site-packages` (`pyoidn/oidn/lib`).
    pub package_dir: &'a str,
    /// The pip package, for the message when it is absent.
    pub package: &'a str,
}

impl Search<'_> {
    /// Each discovery step with the file it found, or why it found none.
    pub(crate) fn candidates(&self) -> Vec<Candidate> {
        let mut out = Vec::new();
        out.push((
            format!("explicit path ({})", self.explicit_name),
            match self.explicit {
                Some(p) if p.is_file() => Ok(p.to_owned()),
                Some(p) => Err(format!("{} does not exist", p.display())),
                None => Err("not given".to_owned()),
            },
        ));
        out.push((
            self.env.to_owned(),
            match std::env::var_os(self.env) {
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
                .and_then(|d| library_in(d, self.prefix))
                .ok_or_else(|| format!("no {}* there", self.prefix)),
        ));
        let venv = python_environment();
        out.push((
            format!(
                "the project's Python environment ({})",
                venv.as_deref()
                    .map_or("HOME not set".into(), |d| d.display().to_string())
            ),
            venv.as_deref()
                .and_then(|v| self.in_python(v))
                .ok_or_else(|| {
                    format!(
                        "no {} package there (run `bash onnx/setup.sh`)",
                        self.package
                    )
                }),
        ));
        out
    }

    /// The library in a Python environment: `lib/python3*/site-packages/<package_dir>/`.
    fn in_python(&self, venv: &Path) -> Option<PathBuf> {
        entries_with_prefix(&venv.join("lib"), "python3")?
            .iter()
            .rev()
            .find_map(|p| library_in(&p.join("site-packages").join(self.package_dir), self.prefix))
    }
}

/// Opens the first candidate that `open` accepts, in order, and returns it with its path; or,
/// when none does, every step with why it failed (for the caller's error message).
pub(crate) fn first_that_opens<T>(
    candidates: Vec<Candidate>,
    mut open: impl FnMut(&Path) -> std::result::Result<T, String>,
) -> std::result::Result<(T, PathBuf), Vec<String>> {
    let mut tried = Vec::new();
    for (source, found) in candidates {
        match found {
            Err(why) => tried.push(format!("{source}: {why}")),
            Ok(path) => match open(&path) {
                Ok(opened) => return Ok((opened, path)),
                Err(why) => tried.push(format!("{source}: {}: {why}", path.display())),
            },
        }
    }
    Err(tried)
}

/// The numbered list of steps an error message shows.
pub(crate) fn numbered(tried: &[String]) -> String {
    tried
        .iter()
        .enumerate()
        .map(|(i, t)| format!("  {}. {t}", i + 1))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The project's Python environment: `$GDRECON_VENV`, else `~/.cache/gdrecon/venv`.
fn python_environment() -> Option<PathBuf> {
    std::env::var_os("GDRECON_VENV")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| Path::new(&h).join(".cache/gdrecon/venv")))
}

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

/// The library in `dir`: the unversioned name if present (it sorts first), else the last
/// versioned one (`libonnxruntime.so.1.31.1`).
fn library_in(dir: &Path, prefix: &str) -> Option<PathBuf> {
    let found = entries_with_prefix(dir, prefix)?;
    let unversioned = found
        .iter()
        .find(|p| p.file_name().and_then(|n| n.to_str()) == Some(prefix));
    unversioned.or(found.last()).cloned()
}

/// The directory of the file this code was loaded from: the gdrecon shared library, or the
/// executable it is statically linked into. Found in `/proc/self/maps` (no `dladdr`, so no
/// `unsafe` here); elsewhere the executable's directory.
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
        let search = Search {
            explicit_name: "--lib",
            explicit: Some(Path::new("/nonexistent/libfoo.so")),
            env: "GDRECON_TEST_NO_SUCH_VARIABLE",
            prefix: "libfoo.so",
            package_dir: "foo/lib",
            package: "foo",
        };
        let c = search.candidates();
        assert_eq!(c.len(), 4);
        assert_eq!(c[0].0, "explicit path (--lib)");
        assert!(c[0].1.as_ref().unwrap_err().contains("does not exist"));
        assert_eq!(c[1].0, "GDRECON_TEST_NO_SUCH_VARIABLE");
        assert_eq!(c[1].1.as_ref().unwrap_err(), "not set");
        assert!(c[2].0.starts_with("next to the gdrecon library"));
        assert!(c[3].0.starts_with("the project's Python environment"));
    }

    #[test]
    fn a_versioned_library_is_found_when_no_unversioned_one_is_there() {
        let dir = tempfile::tempdir().unwrap();
        for name in ["libfoo.so.2.5.0", "libfoo.so.2.5.1", "libbar.so"] {
            std::fs::write(dir.path().join(name), b"").unwrap();
        }
        assert_eq!(
            library_in(dir.path(), "libfoo.so"),
            Some(dir.path().join("libfoo.so.2.5.1"))
        );
        std::fs::write(dir.path().join("libfoo.so"), b"").unwrap();
        assert_eq!(
            library_in(dir.path(), "libfoo.so"),
            Some(dir.path().join("libfoo.so"))
        );
    }
}
