//! Where the networks' weights come from, and proof that they are the ones exported.
//!
//! The exported models (GradNet's `onnx/gradnet.onnx` with features,
//! `onnx/gradnet_nofeat.onnx` without, and `onnx/gradnet_int8_nhwc.onnx`, the feature model
//! quantised to int8 by `onnx/gdrecon_py/quantize.py` and its decoder rewritten channels-last
//! by `onnx/gdrecon_py/nhwc.py`; the combiner's `onnx/combiner.onnx`) are
//! embedded in the library by the `embed-model` feature (on by default), or read from a file.
//! Either way the SHA-256 of the bytes is checked before ONNX Runtime sees them: against the
//! `.sha256` file `export.py` / `quantize.py` / `combiner.py` write beside each model (recorded
//! at export), or, for a file without one, against the hashes of the models this build knows.

use std::borrow::Cow;
use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};

use crate::error::{Error, Result};

/// Which exported model: GradNet with the feature branch (8 data channels) or without (1),
/// and in which precision; or the combiner's network.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum ModelVariant {
    /// `gradnet.onnx`: colour, albedo, normal and depth in the data branch.
    Full,
    /// `gradnet_nofeat.onnx`: colour only, for frames without feature layers.
    NoFeatures,
    /// `gradnet_int8_nhwc.onnx`: [`ModelVariant::Full`] quantised to int8 (QDQ: int8 weights
    /// per output channel, uint8 activations; the first two convolutions kept in fp32, and the
    /// output convolution too, outside the graph, which ends at its quantised input:
    /// `output_layer.rs`), calibrated on the training split (`docs/gradnet.md`, "Reduced
    /// precision"), its decoder channels-last (`onnx/gdrecon_py/nhwc.py`: `gradnet_int8.onnx`,
    /// the form fine-tuning reads and writes, rewritten for ONNX Runtime's int8 kernels).
    FullInt8,
    /// `combiner.onnx`: the combiner's network (`onnx/gdrecon_py/combiner.py`), not a GradNet.
    Combiner,
    /// `combiner_int8.onnx`: [`ModelVariant::Combiner`] quantised to int8 (QDQ; its first and
    /// last convolutions kept in fp32), calibrated on the training split.
    CombinerInt8,
}

impl ModelVariant {
    /// Every model this build knows.
    pub const ALL: [ModelVariant; 5] = [
        ModelVariant::Full,
        ModelVariant::NoFeatures,
        ModelVariant::FullInt8,
        ModelVariant::Combiner,
        ModelVariant::CombinerInt8,
    ];
}

impl ModelVariant {
    /// The exported file's name.
    pub fn file_name(self) -> &'static str {
        match self {
            ModelVariant::Full => "gradnet.onnx",
            ModelVariant::NoFeatures => "gradnet_nofeat.onnx",
            ModelVariant::FullInt8 => "gradnet_int8_nhwc.onnx",
            ModelVariant::Combiner => "combiner.onnx",
            ModelVariant::CombinerInt8 => "combiner_int8.onnx",
        }
    }

    /// Channels of the first input: GradNet's data branch, the combiner's features.
    pub fn data_channels(self) -> usize {
        match self {
            ModelVariant::Full | ModelVariant::FullInt8 => 8,
            ModelVariant::NoFeatures => 1,
            ModelVariant::Combiner | ModelVariant::CombinerInt8 => 21,
        }
    }

    /// The SHA-256 recorded at export (lower-case hex).
    pub fn recorded_sha256(self) -> &'static str {
        let line = match self {
            ModelVariant::Full => include_str!("../../../onnx/gradnet.onnx.sha256"),
            ModelVariant::NoFeatures => include_str!("../../../onnx/gradnet_nofeat.onnx.sha256"),
            ModelVariant::FullInt8 => include_str!("../../../onnx/gradnet_int8_nhwc.onnx.sha256"),
            ModelVariant::Combiner => include_str!("../../../onnx/combiner.onnx.sha256"),
            ModelVariant::CombinerInt8 => {
                include_str!("../../../onnx/combiner_int8.onnx.sha256")
            }
        };
        line.split_whitespace().next().unwrap_or_default()
    }
}

/// Model bytes whose hash has been checked.
#[derive(Clone)]
pub(crate) struct ModelBytes {
    pub bytes: Cow<'static, [u8]>,
    pub sha256: String,
    /// Where they came from, for messages and reports.
    pub origin: String,
}

impl std::fmt::Debug for ModelBytes {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ModelBytes")
            .field("origin", &self.origin)
            .field("sha256", &self.sha256)
            .field("len", &self.bytes.len())
            .finish()
    }
}

/// Lower-case hex SHA-256.
pub(crate) fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// The embedded model of `variant`, hash-checked.
pub(crate) fn embedded(variant: ModelVariant) -> Result<ModelBytes> {
    #[cfg(feature = "embed-model")]
    {
        let bytes: &'static [u8] = match variant {
            ModelVariant::Full => include_bytes!("../../../onnx/gradnet.onnx"),
            ModelVariant::NoFeatures => include_bytes!("../../../onnx/gradnet_nofeat.onnx"),
            ModelVariant::FullInt8 => include_bytes!("../../../onnx/gradnet_int8_nhwc.onnx"),
            ModelVariant::Combiner => include_bytes!("../../../onnx/combiner.onnx"),
            ModelVariant::CombinerInt8 => include_bytes!("../../../onnx/combiner_int8.onnx"),
        };
        let origin = format!("embedded {}", variant.file_name());
        checked(Cow::Borrowed(bytes), variant.recorded_sha256(), origin)
    }
    #[cfg(not(feature = "embed-model"))]
    {
        Err(Error::Unsupported(format!(
            "this build has no embedded models (cargo feature `embed-model` is off): \
             give the path of {} as the model",
            variant.file_name()
        )))
    }
}

/// The model in `path`, hash-checked against `path.sha256` if present, else against the
/// models this build knows.
pub(crate) fn from_file(path: &Path) -> Result<ModelBytes> {
    let bytes = std::fs::read(path).map_err(|source| Error::Io {
        path: path.to_owned(),
        source: std::io::Error::new(
            source.kind(),
            format!("cannot read the GradNet model: {source}"),
        ),
    })?;
    let sidecar = sidecar_path(path);
    let origin = path.display().to_string();
    match std::fs::read_to_string(&sidecar) {
        Ok(text) => {
            let expected = text
                .split_whitespace()
                .next()
                .unwrap_or_default()
                .to_owned();
            checked(Cow::Owned(bytes), &expected, origin)
        }
        Err(_) => {
            let actual = sha256_hex(&bytes);
            if ModelVariant::ALL
                .iter()
                .any(|v| v.recorded_sha256() == actual)
            {
                Ok(ModelBytes {
                    bytes: Cow::Owned(bytes),
                    sha256: actual,
                    origin,
                })
            } else {
                let known: Vec<&str> = ModelVariant::ALL
                    .iter()
                    .map(|v| v.recorded_sha256())
                    .collect();
                Err(Error::Model(format!(
                    "{origin}: SHA-256 {actual} is not that of an exported model \
                     (expected one of {}, or a {} file beside the model as \
                     onnx/gdrecon_py/export.py writes): the file is damaged or is another model",
                    known.join(", "),
                    sidecar.display()
                )))
            }
        }
    }
}

fn sidecar_path(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(".sha256");
    PathBuf::from(name)
}

fn checked(bytes: Cow<'static, [u8]>, expected: &str, origin: String) -> Result<ModelBytes> {
    let actual = sha256_hex(&bytes);
    if !actual.eq_ignore_ascii_case(expected) {
        return Err(Error::Model(format!(
            "{origin}: SHA-256 is {actual}, but {expected} was recorded at export: the model \
             is damaged or not the exported one"
        )));
    }
    Ok(ModelBytes {
        bytes,
        sha256: actual,
        origin,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sha256_of_known_vectors() {
        assert_eq!(
            sha256_hex(b"abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
    }

    #[test]
    fn recorded_hashes_are_those_of_models_json() {
        let json = include_str!("../../../onnx/models.json");
        for v in ModelVariant::ALL {
            let h = v.recorded_sha256();
            assert_eq!(h.len(), 64);
            assert!(json.contains(&format!("\"sha256\": \"{h}\"")), "{v:?}");
        }
    }

    #[cfg(feature = "embed-model")]
    #[test]
    fn embedded_models_pass_their_check() {
        for v in ModelVariant::ALL {
            let m = embedded(v).unwrap();
            assert_eq!(m.sha256, v.recorded_sha256());
        }
    }

    #[test]
    fn file_errors_are_distinct() {
        let dir = std::env::temp_dir().join(format!("gdrecon-model-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let missing = from_file(&dir.join("none.onnx")).unwrap_err();
        assert!(matches!(missing, Error::Io { .. }), "{missing}");
        let other = dir.join("other.onnx");
        std::fs::write(&other, b"not a model").unwrap();
        let unknown = from_file(&other).unwrap_err().to_string();
        assert!(
            unknown.contains("not that of an exported model"),
            "{unknown}"
        );
        std::fs::write(sidecar_path(&other), "00  other.onnx\n").unwrap();
        let mismatch = from_file(&other).unwrap_err().to_string();
        assert!(mismatch.contains("was recorded at export"), "{mismatch}");
        std::fs::write(sidecar_path(&other), sha256_hex(b"not a model")).unwrap();
        assert!(from_file(&other).is_ok(), "a matching sidecar is accepted");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
