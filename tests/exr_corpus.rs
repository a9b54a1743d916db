//! The corpus of unusual and broken bundles (tests/fixtures/exr/corpus, written by the OpenEXR
//! library through `make_corpus.py`; `corpus.tsv` says what each must give), and mutants of its
//! offset tables and chunk headers generated here. The rule: a file is either read as exactly
//! the frame it describes or refused with one line naming the file and the fault; never
//! accepted as a different image.

use std::path::{Path, PathBuf};

use assert_cmd::Command;
use gdrecon::{io, Frame, Layer, Policy};

fn corpus() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/exr/corpus")
}

struct Case {
    file: String,
    expect: String,
    fault: String,
    why: String,
}

fn cases() -> Vec<Case> {
    let text = std::fs::read_to_string(corpus().join("corpus.tsv")).unwrap();
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.is_empty())
        .map(|l| {
            let f: Vec<&str> = l.split('\t').collect();
            assert_eq!(f.len(), 4, "corpus.tsv line: {l}");
            Case {
                file: f[0].into(),
                expect: f[1].into(),
                fault: f[2].into(),
                why: f[3].into(),
            }
        })
        .collect()
}

fn clean() -> Frame {
    io::read_bundle(corpus().join("clean.exr"), Policy::Strict).unwrap()
}

fn assert_same(frame: &Frame, clean: &Frame, what: &str) {
    assert_eq!(frame.size(), clean.size(), "{what}");
    assert_eq!(frame.present_layers(), clean.present_layers(), "{what}");
    for layer in clean.present_layers() {
        assert_eq!(
            frame.layer(layer),
            clean.layer(layer),
            "{what}: layer {layer}"
        );
    }
    assert_eq!(frame.spp(), clean.spp(), "{what}");
}

/// The clean frame is what the generator wrote (so "same" means the right image, not merely
/// the same wrong one).
#[test]
fn the_clean_bundle_holds_the_generated_values() {
    let frame = clean();
    assert_eq!(frame.size(), (8, 6));
    let color = frame.layer(Layer::Color).unwrap();
    // plane(layer 0, component c) = 0.25 + x / 8 + y / 2 + c / 16
    for (x, y, c) in [(0, 0, 0), (7, 5, 2), (3, 2, 1)] {
        let want = 0.25 + x as f32 / 8.0 + y as f32 / 2.0 + c as f32 / 16.0;
        assert_eq!(color.at(c, x, y), want, "color ({x}, {y}) channel {c}");
    }
    let depth = frame.layer(Layer::Depth).unwrap();
    assert_eq!(depth.at(0, 1, 1), 5.0 + 0.25 + 1.0 / 8.0 + 0.5);
}

#[test]
fn every_corpus_file_is_read_exactly_or_refused_naming_file_and_fault() {
    let clean = clean();
    let cases = cases();
    assert!(cases.len() >= 33, "the corpus lost files: {}", cases.len());
    // Inside a pool the blocks are decompressed in parallel: the outcome must not change.
    let context = gdrecon::Context::new(gdrecon::ContextOptions::with_threads(Some(2))).unwrap();
    for case in &cases {
        let path = corpus().join(&case.file);
        let result = io::read_bundle(&path, Policy::Strict);
        let parallel = context.install(|| io::read_bundle(&path, Policy::Strict));
        match (&result, &parallel) {
            (Ok(a), Ok(b)) => assert_same(b, a, &case.file),
            (Err(a), Err(b)) => assert_eq!(a.to_string(), b.to_string(), "{}", case.file),
            _ => panic!(
                "{}: {result:?} single-threaded, {parallel:?} in a pool",
                case.file
            ),
        }
        match case.expect.as_str() {
            "same" => {
                let frame = result.unwrap_or_else(|e| panic!("{} ({}): {e}", case.file, case.why));
                assert_same(&frame, &clean, &case.file);
            }
            "refuse" => {
                let e = match result {
                    Err(e) => e.to_string(),
                    Ok(_) => panic!("{} was accepted ({})", case.file, case.why),
                };
                assert!(!e.contains('\n'), "{}: not one line: {e}", case.file);
                assert!(
                    e.contains(&case.file),
                    "{}: the file is not named: {e}",
                    case.file
                );
                assert!(
                    e.to_lowercase().contains(&case.fault.to_lowercase()),
                    "{}: '{}' is not named: {e}",
                    case.file,
                    case.fault
                );
            }
            "as" => {
                let frame = result.unwrap_or_else(|e| panic!("{} ({}): {e}", case.file, case.why));
                let reference = io::read_bundle(corpus().join(&case.fault), Policy::Strict)
                    .unwrap_or_else(|e| panic!("{}: {e}", case.fault));
                assert_same(&frame, &reference, &case.file);
            }
            other => panic!("corpus.tsv: unknown expectation {other}"),
        }
    }
}

/// Through the CLI, a refusal is exactly one line on stderr, exit status 1.
#[test]
fn the_cli_refuses_each_broken_file_in_one_line() {
    for case in cases().iter().filter(|c| c.expect == "refuse") {
        let out = Command::cargo_bin("gdrecon")
            .unwrap()
            .arg("info")
            .arg(corpus().join(&case.file))
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{}: {stderr}", case.file);
        assert_eq!(
            stderr.trim_end().lines().count(),
            1,
            "{}: {stderr}",
            case.file
        );
        assert!(out.stdout.is_empty(), "{}", case.file);
    }
}

/// Offsets of the first part's chunks and where its table starts, from a single-part file with
/// the given chunk count (the table ends where the first chunk starts).
fn table(bytes: &[u8], chunks: usize) -> (usize, Vec<u64>) {
    let first = (0..bytes.len() - 8)
        .find(|&at| {
            let offsets: Vec<u64> = (0..chunks)
                .map(|i| {
                    let b = &bytes[at + 8 * i..at + 8 * i + 8];
                    u64::from_le_bytes(b.try_into().unwrap())
                })
                .collect();
            offsets[0] as usize == at + 8 * chunks
                && offsets.iter().all(|&o| o < bytes.len() as u64)
        })
        .expect("offset table");
    let offsets = (0..chunks)
        .map(|i| u64::from_le_bytes(bytes[first + 8 * i..first + 8 * i + 8].try_into().unwrap()))
        .collect();
    (first, offsets)
}

fn must_refuse(bytes: &[u8], what: &str) {
    let read = || io::read_bundle_from_bytes(bytes).and_then(|raw| raw.into_frame(Policy::Strict));
    match read() {
        Err(e) => assert!(!e.to_string().contains('\n'), "{what}: {e}"),
        Ok(_) => panic!("{what}: accepted"),
    }
    // Blocks decompressed in parallel are refused alike.
    thread_local! {
        static POOL: gdrecon::Context =
            gdrecon::Context::new(gdrecon::ContextOptions::with_threads(Some(2))).unwrap();
    }
    assert!(
        POOL.with(|pool| pool.install(read)).is_err(),
        "{what}: accepted in a pool"
    );
}

/// Every way of pointing one table entry at another chunk, and every chunk's coordinates
/// moved by one, in the uncompressed scan-line file (6 chunks) and the tiled one (6 tiles of
/// 3 x 4): all refused.
#[test]
fn every_misplaced_chunk_is_refused() {
    for (file, chunks, coords) in [("uncompressed.exr", 6, 1), ("tiled.exr", 6, 4)] {
        let bytes = std::fs::read(corpus().join(file)).unwrap();
        let (at, offsets) = table(&bytes, chunks);
        let mut tried = 0;
        for i in 0..chunks {
            for (j, other) in offsets.iter().enumerate() {
                if i == j {
                    continue;
                }
                let mut m = bytes.clone();
                m[at + 8 * i..at + 8 * i + 8].copy_from_slice(&other.to_le_bytes());
                must_refuse(&m, &format!("{file}: entry {i} -> chunk {j}"));
                tried += 1;
            }
            for k in 0..coords {
                for delta in [-1i32, 1] {
                    let mut m = bytes.clone();
                    let o = offsets[i] as usize + 4 * k;
                    let v = i32::from_le_bytes(m[o..o + 4].try_into().unwrap());
                    m[o..o + 4].copy_from_slice(&(v + delta).to_le_bytes());
                    must_refuse(&m, &format!("{file}: chunk {i} coordinate {k} {delta:+}"));
                    tried += 1;
                }
            }
        }
        assert!(tried >= 40, "{file}: {tried}");
        // The unmutated file is read (the mutation is what gets it refused).
        io::read_bundle_from_bytes(&bytes).unwrap();
    }
}
