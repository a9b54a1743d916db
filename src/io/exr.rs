//! Frame bundles and output images as OpenEXR files (the `exr` crate).
//!
//! Reading follows the bundle format of the project's conventions: channels named
//! `layer.component`, in one part with dotted names (what pbrt, Mitsuba and Blender write) or in
//! parts named after the layer; any compression, scan lines or tiles, f16, f32 or u32 samples;
//! components matched case-insensitively; layer aliases seen in the wild accepted
//! ([`LAYER_ALIASES`]); unknown channels ignored and listed. The data window is the image: a
//! window offset from the display window is read as is, and parts whose windows disagree are
//! an error. Decoding runs single-threaded (`non_parallel`): the crate would otherwise build a
//! thread pool per call, and callers own the threads.

use std::collections::BTreeMap;
use std::io::{BufReader, Cursor, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use exr::prelude as x;
use exr::prelude::{AttributeValue, FlatSamples, ReadChannels, ReadLayers};
use smallvec::SmallVec;

use super::chunks;
use crate::error::{Error, Result};
use crate::frame::{Frame, FrameBuilder, Layer};
use crate::image::Image;
use crate::validate::Policy;

/// Alternative layer names accepted on reading, besides the canonical (case-insensitive) one:
/// pbrt's `Albedo`, `N`, `Ns`, `Variance`; Mitsuba's AOV names `nn`, `sh_normal`, `dd`.
pub const LAYER_ALIASES: &[(&str, Layer)] = &[
    ("n", Layer::Normal),
    ("ns", Layer::Normal),
    ("nn", Layer::Normal),
    ("sh_normal", Layer::Normal),
    ("dd", Layer::Depth),
];

/// What a bundle file holds before validation, as [`read_bundle_raw`] returns it.
#[derive(Clone, Debug)]
pub struct RawBundle {
    /// Where it came from (`<memory>` for buffers).
    pub path: PathBuf,
    /// Width and height of the data window.
    pub size: (usize, usize),
    /// The recognised layers, as stored (nothing replaced yet).
    pub layers: BTreeMap<Layer, Image>,
    /// For each recognised layer, the channel names it was read from.
    pub sources: BTreeMap<Layer, Vec<String>>,
    /// Channels that belong to no recognised layer (ignored).
    pub ignored: Vec<String>,
    /// The `spp` attribute, when present and positive.
    pub spp: Option<f32>,
    /// Things worth telling that are not errors (a bad `spp` attribute, ...).
    pub warnings: Vec<String>,
}

impl RawBundle {
    /// Validates and sanitises the layers into a [`Frame`]; errors name the file.
    pub fn into_frame(self, policy: Policy) -> Result<Frame> {
        let path = self.path.clone();
        let mut builder = FrameBuilder::new().spp(self.spp);
        for (layer, img) in self.layers {
            builder = builder.image(layer, img);
        }
        builder.build(policy).map_err(|e| match e {
            Error::InvalidInput(m) => Error::InvalidInput(format!("{}: {m}", path.display())),
            other => other,
        })
    }
}

/// Reads and validates a frame bundle.
pub fn read_bundle(path: impl AsRef<Path>, policy: Policy) -> Result<Frame> {
    read_bundle_raw(path)?.into_frame(policy)
}

/// Reads a frame bundle without validating it (for inspection: `gdrecon info`).
pub fn read_bundle_raw(path: impl AsRef<Path>) -> Result<RawBundle> {
    let path = path.as_ref();
    let file = std::fs::File::open(path).map_err(|source| Error::Io {
        path: path.to_owned(),
        source,
    })?;
    parse_bundle(BufReader::new(file), path)
}

/// Reads a frame bundle from memory without validating it.
pub fn read_bundle_from_bytes(bytes: &[u8]) -> Result<RawBundle> {
    parse_bundle(Cursor::new(bytes), Path::new("<memory>"))
}

type AnyImage = x::Image<x::Layers<x::AnyChannels<FlatSamples>>>;

fn decode(reader: impl Read + Seek, path: &Path) -> Result<AnyImage> {
    x::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .all_layers()
        .all_attributes()
        .non_parallel()
        .from_buffered(reader)
        .map_err(|e| exr_error(e, path))
}

fn exr_error(e: exr::error::Error, path: &Path) -> Error {
    use exr::error::Error as E;
    let message = match e {
        E::Io(source) if source.kind() == std::io::ErrorKind::UnexpectedEof => {
            "truncated or not an OpenEXR file (unexpected end of data)".to_owned()
        }
        E::Io(source) => {
            return Error::Io {
                path: path.to_owned(),
                source,
            }
        }
        E::Invalid(m) if m.contains("identifier") => format!("not an OpenEXR file ({m})"),
        E::Invalid(m) => format!("damaged OpenEXR file: {m}"),
        E::NotSupported(m) => format!("OpenEXR feature not supported: {m}"),
        E::Aborted => "reading was aborted".to_owned(),
    };
    Error::Exr {
        path: path.to_owned(),
        message,
    }
}

/// Decoded bytes a header may declare per byte of file (plus [`SIZE_SLACK`]). Frame bundles
/// hold noisy floats, which no EXR compression shrinks more than a few times; a header that
/// declares far more is damaged or hostile, and decoding it would allocate whatever it says
/// (found by fuzzing: a 4 KB file asking for gigabytes).
const MAX_EXPANSION: u64 = 64;
/// Allowance on top of the expansion bound, so small files are never refused for it.
const SIZE_SLACK: u64 = 64 << 20;

/// Reads the headers and refuses what cannot be decoded into the image the file describes:
/// features the decoder lacks (named), sizes the file cannot plausibly hold, and a chunk layout
/// that does not store every block exactly once where it belongs ([`chunks::check`]). Rewinds
/// the reader.
fn check_layout(mut reader: impl Read + Seek, path: &Path) -> Result<()> {
    let file_len = reader
        .seek(SeekFrom::End(0))
        .and_then(|len| reader.seek(SeekFrom::Start(0)).map(|_| len))
        .map_err(|source| Error::Io {
            path: path.to_owned(),
            source,
        })?;
    let meta = match exr::meta::MetaData::read_from_buffered(&mut reader, false) {
        Ok(meta) => meta,
        Err(e) => {
            let message = match chunks::unsupported(&mut reader) {
                Some(what) => format!("OpenEXR feature not supported: {what}"),
                None => return Err(exr_error(e, path)),
            };
            return Err(Error::Exr {
                path: path.to_owned(),
                message,
            });
        }
    };
    reader
        .seek(SeekFrom::Start(0))
        .map_err(|source| Error::Io {
            path: path.to_owned(),
            source,
        })?;
    // HTJ2K (new in OpenEXR 3.4) is refused: exr 1.74's decoder took 2 GB for a 1 KB file
    // declaring 46 MB of samples (found by fuzzing), and no renderer writes bundles with it.
    if let Some(h) = meta.headers.iter().find(|h| {
        matches!(
            h.compression,
            exr::compression::Compression::HTJ2K32 | exr::compression::Compression::HTJ2K256
        )
    }) {
        return Err(Error::Exr {
            path: path.to_owned(),
            message: format!(
                "OpenEXR feature not supported: {} (its decoder's memory is not \
                 bounded); write the bundle with ZIP, PIZ, RLE, PXR24, B44 or DWA",
                h.compression
            ),
        });
    }
    // The decoder supports no subsampled channel, not even one gdrecon would ignore.
    if let Some(c) = meta
        .headers
        .iter()
        .flat_map(|h| &h.channels.list)
        .find(|c| c.sampling != exr::math::Vec2(1, 1))
    {
        return Err(Error::Exr {
            path: path.to_owned(),
            message: format!(
                "OpenEXR feature not supported: channel '{}' is subsampled {} x {}: subsampled \
                 channels are not supported, not even in layers gdrecon ignores; write every \
                 channel at full resolution",
                c.name, c.sampling.0, c.sampling.1
            ),
        });
    }
    // Every chunk has an 8-byte entry in the offset tables, which the file itself holds: more
    // chunks than that is a damaged header, and the decoder would allocate the tables first
    // (found by fuzzing: a 1 KB file declaring 2^28 chunks took 2 GB).
    let tables = meta.headers.iter().fold(0u64, |n, h| {
        n.saturating_add((h.chunk_count as u64).saturating_mul(8))
    });
    if tables > file_len {
        return Err(Error::Exr {
            path: path.to_owned(),
            message: format!(
                "the header declares {} chunks, whose offset tables alone need {tables} bytes, in \
                 a file of {file_len} bytes: damaged or not a frame bundle",
                tables / 8
            ),
        });
    }
    let mut declared: u64 = 0;
    for header in &meta.headers {
        let (w, h) = (header.layer_size.0 as u64, header.layer_size.1 as u64);
        for channel in &header.channels.list {
            let (sx, sy) = (
                channel.sampling.0.max(1) as u64,
                channel.sampling.1.max(1) as u64,
            );
            declared = declared.saturating_add((w / sx).saturating_mul(h / sy).saturating_mul(4));
        }
    }
    let allowed = file_len
        .saturating_mul(MAX_EXPANSION)
        .saturating_add(SIZE_SLACK);
    if declared > allowed {
        let first = meta.headers.first().map(|h| h.layer_size);
        return Err(Error::Exr {
            path: path.to_owned(),
            message: format!(
                "the header declares {declared} bytes of samples ({} x {} per part) in a file \
                 of {file_len} bytes: damaged or not a frame bundle (refusing to allocate it)",
                first.map_or(0, |s| s.0),
                first.map_or(0, |s| s.1)
            ),
        });
    }
    chunks::check(&mut reader, &meta.headers, file_len).map_err(|message| Error::Exr {
        path: path.to_owned(),
        message,
    })
}

fn parse_bundle(mut reader: impl Read + Seek, path: &Path) -> Result<RawBundle> {
    check_layout(&mut reader, path)?;
    let image = decode(reader, path)?;
    let err = |message: String| Error::Exr {
        path: path.to_owned(),
        message,
    };
    let first = image
        .layer_data
        .first()
        .ok_or_else(|| err("the file has no image parts".into()))?;
    let (w, h) = (first.size.0, first.size.1);
    let origin = first.attributes.layer_position;
    // (layer, component upper-case) -> (full channel name, samples)
    let mut found: BTreeMap<Layer, Vec<(String, String, Vec<f32>)>> = BTreeMap::new();
    let mut ignored = Vec::new();
    let mut warnings = Vec::new();
    let mut spp_attr = attribute_spp(&image.attributes.other);
    for part in &image.layer_data {
        let part_name = part.attributes.layer_name.as_ref().map(|t| t.to_string());
        if (part.size.0, part.size.1) != (w, h) || part.attributes.layer_position != origin {
            return Err(err(format!(
                "part '{}' is {} x {} at {:?}, but the first part is {w} x {h} at {:?}: all \
                 layers of a bundle must share one data window",
                part_name.as_deref().unwrap_or(""),
                part.size.0,
                part.size.1,
                part.attributes.layer_position,
                origin
            )));
        }
        spp_attr = spp_attr.or(attribute_spp(&part.attributes.other));
        for channel in &part.channel_data.list {
            // A channel's own name is used as it is when it names a layer ("color.R" in a part
            // of any name, the single part's name attribute included); a part named after the
            // layer supplies it otherwise ("R" in part "color").
            let own = channel.name.to_string();
            let prefixed = match &part_name {
                Some(p) if !p.is_empty() => format!("{p}.{own}"),
                _ => own.clone(),
            };
            let named = split_name(&own)
                .map(|found| (own.clone(), found))
                .or_else(|| split_name(&prefixed).map(|found| (prefixed.clone(), found)));
            let Some((full, (layer, component))) = named else {
                ignored.push(prefixed);
                continue;
            };
            let entries = found.entry(layer).or_default();
            if let Some((other, _, _)) = entries.iter().find(|(_, c, _)| *c == component) {
                return Err(err(format!(
                    "channel {layer}.{component} is stored more than once ('{other}' and \
                     '{full}'{}): which one is the frame is ambiguous",
                    part_name
                        .as_deref()
                        .map(|p| format!(" in part '{p}'"))
                        .unwrap_or_default()
                )));
            }
            entries.push((full, component, to_f32(&channel.sample_data)));
        }
    }
    let spp = match spp_attr {
        Some(s) if s.is_finite() && s > 0.0 => Some(s),
        Some(s) => {
            warnings.push(format!(
                "attribute spp = {s} is not a positive number; treated as unknown"
            ));
            None
        }
        None => None,
    };
    let mut layers = BTreeMap::new();
    let mut sources = BTreeMap::new();
    for (layer, channels) in found {
        match assemble(layer, channels, w, h) {
            Ok((img, names, extra)) => {
                layers.insert(layer, img);
                sources.insert(layer, names);
                ignored.extend(extra);
            }
            Err(message) => return Err(err(message)),
        }
    }
    Ok(RawBundle {
        path: path.to_owned(),
        size: (w, h),
        layers,
        sources,
        ignored,
        spp,
        warnings,
    })
}

fn attribute_spp(attrs: &std::collections::HashMap<x::Text, AttributeValue>) -> Option<f32> {
    attrs.iter().find_map(|(k, v)| {
        if !k.to_string().eq_ignore_ascii_case("spp") {
            return None;
        }
        match v {
            AttributeValue::F32(f) => Some(*f),
            AttributeValue::F64(f) => Some(*f as f32),
            AttributeValue::I32(i) => Some(*i as f32),
            _ => Some(f32::NAN),
        }
    })
}

/// `"color.R"` -> `(Color, "R")`; the layer part is matched case-insensitively against the
/// canonical names, then the aliases. Splits on the last dot.
fn split_name(full: &str) -> Option<(Layer, String)> {
    let (layer, component) = full.rsplit_once('.')?;
    let layer = Layer::from_name(layer).or_else(|| {
        LAYER_ALIASES
            .iter()
            .find(|(alias, _)| alias.eq_ignore_ascii_case(layer))
            .map(|(_, l)| *l)
    })?;
    Some((layer, component.to_ascii_uppercase()))
}

fn to_f32(samples: &FlatSamples) -> Vec<f32> {
    match samples {
        FlatSamples::F16(v) => v.iter().map(|h| h.to_f32()).collect(),
        FlatSamples::F32(v) => v.clone(),
        FlatSamples::U32(v) => v.iter().map(|&u| u as f32).collect(),
    }
}

type Assembled = (Image, Vec<String>, Vec<String>);

/// Picks the layer's components out of the channels found for it. A 3-channel layer may be
/// stored as RGB or XYZ; depth as `Z`, `Y`, `T` or its only channel.
fn assemble(
    layer: Layer,
    mut channels: Vec<(String, String, Vec<f32>)>,
    w: usize,
    h: usize,
) -> Result<Assembled, String> {
    let wanted: Vec<Vec<&str>> = match layer {
        Layer::Depth => vec![vec!["Z"], vec!["Y"], vec!["T"], vec!["R"]],
        Layer::Normal => vec![vec!["X", "Y", "Z"], vec!["R", "G", "B"]],
        _ => vec![vec!["R", "G", "B"], vec!["X", "Y", "Z"]],
    };
    let pick = |set: &Vec<&str>, chans: &Vec<(String, String, Vec<f32>)>| -> Option<Vec<usize>> {
        set.iter()
            .map(|c| chans.iter().position(|(_, comp, _)| comp == c))
            .collect()
    };
    let mut chosen = wanted.iter().find_map(|set| pick(set, &channels));
    if chosen.is_none() && layer == Layer::Depth && channels.len() == 1 {
        chosen = Some(vec![0]);
    }
    let Some(indices) = chosen else {
        let have: Vec<&str> = channels.iter().map(|(n, _, _)| n.as_str()).collect();
        return Err(format!(
            "layer '{layer}' needs channels {} but the file has only {}",
            layer
                .components()
                .iter()
                .map(|c| format!("{layer}.{c}"))
                .collect::<Vec<_>>()
                .join(", "),
            have.join(", ")
        ));
    };
    let mut img = Image::zeros(indices.len(), w, h);
    let mut names = Vec::new();
    for (c, &i) in indices.iter().enumerate() {
        let (name, _, samples) = &channels[i];
        img.plane_mut(c)
            .as_slice_mut()
            .expect("planes are contiguous")
            .copy_from_slice(samples);
        names.push(name.clone());
    }
    let mut sorted = indices.clone();
    sorted.sort_unstable_by(|a, b| b.cmp(a));
    for i in sorted {
        channels.remove(i);
    }
    let extra = channels.into_iter().map(|(n, _, _)| n).collect();
    Ok((img, names, extra))
}

/// Reads an RGB image to evaluate: the plain `R`, `G`, `B` channels of an output file, or else
/// the `color` layer (the base image) of a bundle. Non-finite values are kept (metrics refuse
/// them).
pub fn read_rgb(path: impl AsRef<Path>) -> Result<Image> {
    read_rgb_or_layer(path.as_ref(), "color")
}

/// Reads a reference image: the plain `R`, `G`, `B` channels of an image file, or else the
/// `reference` layer of a bundle (never its colour: a reference that is missing is an error).
pub fn read_reference(path: impl AsRef<Path>) -> Result<Image> {
    read_rgb_or_layer(path.as_ref(), "reference")
}

fn read_rgb_or_layer(path: &Path, layer: &str) -> Result<Image> {
    let file = std::fs::File::open(path).map_err(|source| Error::Io {
        path: path.to_owned(),
        source,
    })?;
    let mut reader = BufReader::new(file);
    check_layout(&mut reader, path)?;
    let image = decode(reader, path)?;
    let part = image.layer_data.first().ok_or_else(|| Error::Exr {
        path: path.to_owned(),
        message: "the file has no image parts".into(),
    })?;
    let (w, h) = (part.size.0, part.size.1);
    let find = |prefix: &str| -> Option<Image> {
        let planes: Option<Vec<Vec<f32>>> = ["R", "G", "B"]
            .iter()
            .map(|c| {
                let want = if prefix.is_empty() {
                    c.to_string()
                } else {
                    format!("{prefix}.{c}")
                };
                part.channel_data
                    .list
                    .iter()
                    .find(|ch| ch.name.to_string().eq_ignore_ascii_case(&want))
                    .map(|ch| to_f32(&ch.sample_data))
            })
            .collect();
        planes.map(|p| Image::from_fn(3, w, h, |(c, x, y)| p[c][y * w + x]))
    };
    find("").or_else(|| find(layer)).ok_or_else(|| Error::Exr {
        path: path.to_owned(),
        message: format!(
            "no RGB image: expected channels R, G, B or {layer}.R, {layer}.G, {layer}.B"
        ),
    })
}

fn write_channels(
    path: &Path,
    size: (usize, usize),
    channels: SmallVec<[x::AnyChannel<FlatSamples>; 4]>,
    spp: Option<f32>,
) -> Result<()> {
    let layer = x::Layer::new(
        size,
        x::LayerAttributes::default(),
        x::Encoding::SMALL_LOSSLESS,
        x::AnyChannels::sort(channels),
    );
    let mut image = x::Image::from_layer(layer);
    if let Some(s) = spp {
        image
            .attributes
            .other
            .insert(x::Text::from("spp"), AttributeValue::F32(s));
    }
    use exr::prelude::WritableImage;
    image
        .write()
        .non_parallel()
        .to_file(path)
        .map_err(|e| exr_error(e, path))
}

/// Writes a reconstruction: plain `R`, `G`, `B` f32 channels, ZIP compression.
pub fn write_rgb(path: impl AsRef<Path>, image: &Image) -> Result<()> {
    if image.channels() != 3 {
        return Err(Error::arg(format!(
            "write_rgb needs 3 channels, got {}",
            image.channels()
        )));
    }
    let channels = ["R", "G", "B"]
        .iter()
        .enumerate()
        .map(|(c, name)| {
            x::AnyChannel::new(
                *name,
                FlatSamples::F32(image.plane(c).iter().copied().collect()),
            )
        })
        .collect();
    write_channels(path.as_ref(), image.size(), channels, None)
}

/// Writes every layer of `frame` as a bundle (f32, ZIP, `spp` attribute when known).
pub fn write_bundle(path: impl AsRef<Path>, frame: &Frame) -> Result<()> {
    let mut channels = SmallVec::new();
    for layer in frame.present_layers() {
        let img = frame.layer(layer).expect("present");
        for (c, comp) in layer.components().iter().enumerate() {
            channels.push(x::AnyChannel::new(
                format!("{layer}.{comp}").as_str(),
                FlatSamples::F32(img.plane(c).iter().copied().collect()),
            ));
        }
    }
    write_channels(path.as_ref(), frame.size(), channels, frame.spp())
}
