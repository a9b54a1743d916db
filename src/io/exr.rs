//! Frame bundles and output images as OpenEXR files (the `exr` crate).
//!
//! Reading follows the bundle format of the project's conventions: channels named
//! `layer.component`, in one part with dotted names (what pbrt, Mitsuba and Blender write) or in
//! parts named after the layer; any compression, scan lines or tiles, f16, f32 or u32 samples;
//! components matched case-insensitively; layer aliases seen in the wild accepted
//! ([`LAYER_ALIASES`]); unknown channels ignored and listed. The data window is the image: a
//! window offset from the display window is read as is, and parts whose windows disagree are
//! an error. Blocks are decoded and encoded by `super::blocks`: in parallel inside a rayon pool
//! (the CLI reads and writes inside its [`crate::Context::install`]), on the calling thread
//! otherwise, since callers own the threads.

use std::collections::BTreeMap;
use std::io::{BufReader, Cursor, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use exr::meta::MetaData;
use exr::prelude as x;
use exr::prelude::AttributeValue;

use super::blocks::{self, Fault, Target};
use super::chunks::{self, Offsets};
use crate::error::{Error, Result};
use crate::frame::{Frame, FrameBuilder, Layer};
use crate::image::Image;
use crate::validate::{Policy, Summary};

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
        self.into_frame_known(policy, &BTreeMap::new())
    }

    /// [`RawBundle::into_frame`] with the summaries of layers as they were decoded.
    fn into_frame_known(self, policy: Policy, known: &BTreeMap<Layer, Summary>) -> Result<Frame> {
        let path = self.path.clone();
        let mut builder = FrameBuilder::new().spp(self.spp);
        for (layer, img) in self.layers {
            builder = builder.image(layer, img);
        }
        builder.build_known(policy, known).map_err(|e| match e {
            Error::InvalidInput(m) => Error::InvalidInput(format!("{}: {m}", path.display())),
            other => other,
        })
    }
}

/// Reads and validates a frame bundle. Layers whose values were found clean while they were
/// decoded are not passed over again; the frame is the one [`RawBundle::into_frame`] builds.
pub fn read_bundle(path: impl AsRef<Path>, policy: Policy) -> Result<Frame> {
    let (raw, known) = parse_bundle(open(path.as_ref())?, path.as_ref())?;
    raw.into_frame_known(policy, &known)
}

/// Reads a frame bundle without validating it (for inspection: `gdrecon info`).
pub fn read_bundle_raw(path: impl AsRef<Path>) -> Result<RawBundle> {
    Ok(parse_bundle(open(path.as_ref())?, path.as_ref())?.0)
}

/// Reads a frame bundle from memory without validating it.
pub fn read_bundle_from_bytes(bytes: &[u8]) -> Result<RawBundle> {
    Ok(parse_bundle(Cursor::new(bytes), Path::new("<memory>"))?.0)
}

fn open(path: &Path) -> Result<BufReader<std::fs::File>> {
    let file = std::fs::File::open(path).map_err(|source| Error::Io {
        path: path.to_owned(),
        source,
    })?;
    Ok(BufReader::new(file))
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
/// that does not store every block exactly once where it belongs ([`chunks::check`]). Returns
/// the headers and rewinds the reader.
fn check_layout(mut reader: impl Read + Seek, path: &Path) -> Result<(MetaData, Offsets)> {
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
    // Subsampled channels are decoded here (`blocks`) for scan-line parts compressed with a
    // byte-stream codec: the `exr` crate sizes their blocks wrongly. The frame's own layers
    // must be full resolution ([`parse_bundle`]); other layers may be subsampled.
    for header in &meta.headers {
        let Some(c) = header
            .channels
            .list
            .iter()
            .find(|c| c.sampling != exr::math::Vec2(1, 1))
        else {
            continue;
        };
        use exr::compression::Compression as C;
        // OpenEXR requires the data window's origin and size to be multiples of the sampling
        // (each line then holds `width / sx` samples): anything else is a damaged header.
        let origin = header.own_attributes.layer_position;
        let size = header.layer_size;
        let uneven = |s: usize, at: i32, len: usize| match i32::try_from(s) {
            Ok(si) if si > 0 => at.rem_euclid(si) != 0 || len % s != 0,
            _ => true,
        };
        if let Some(bad) = header.channels.list.iter().find(|c| {
            uneven(c.sampling.0, origin.0, size.0) || uneven(c.sampling.1, origin.1, size.1)
        }) {
            return Err(Error::Exr {
                path: path.to_owned(),
                message: format!(
                    "damaged OpenEXR file: channel '{}' is sampled {} x {}, which does not \
                     divide the data window ({} x {} at {:?})",
                    bad.name, bad.sampling.0, bad.sampling.1, size.0, size.1, origin
                ),
            });
        }
        let why = if header.blocks != exr::meta::BlockDescription::ScanLines || header.deep {
            Some("in a tiled or deep part (OpenEXR allows them in scan-line parts only)".to_owned())
        } else if !matches!(
            header.compression,
            C::Uncompressed | C::RLE | C::ZIP1 | C::ZIP16
        ) {
            Some(format!(
                "in a part compressed with {}: gdrecon reads subsampled channels only with \
                 NONE, RLE, ZIPS or ZIP",
                header.compression
            ))
        } else {
            None
        };
        if let Some(why) = why {
            return Err(Error::Exr {
                path: path.to_owned(),
                message: format!(
                    "OpenEXR feature not supported: channel '{}' is subsampled {} x {} {why}",
                    c.name, c.sampling.0, c.sampling.1
                ),
            });
        }
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
    let offsets =
        chunks::check(&mut reader, &meta.headers, file_len).map_err(|message| Error::Exr {
            path: path.to_owned(),
            message,
        })?;
    reader
        .seek(SeekFrom::Start(0))
        .map_err(|source| Error::Io {
            path: path.to_owned(),
            source,
        })?;
    Ok((meta, offsets))
}

/// The bundle, and a summary of each layer's values (see [`Summary`]).
fn parse_bundle(
    mut reader: impl Read + Seek + Send,
    path: &Path,
) -> Result<(RawBundle, BTreeMap<Layer, Summary>)> {
    let (meta, offsets) = check_layout(&mut reader, path)?;
    let err = |message: String| Error::Exr {
        path: path.to_owned(),
        message,
    };
    let first = meta
        .headers
        .first()
        .ok_or_else(|| err("the file has no image parts".into()))?;
    let (w, h) = (first.layer_size.0, first.layer_size.1);
    let origin = first.own_attributes.layer_position;
    let mut found: BTreeMap<Layer, Vec<Stored>> = BTreeMap::new();
    let mut ignored = Vec::new();
    let mut warnings = Vec::new();
    let mut spp_attr = attribute_spp(&first.shared_attributes.other);
    for (p, part) in meta.headers.iter().enumerate() {
        let part_name = part
            .own_attributes
            .layer_name
            .as_ref()
            .map(|t| t.to_string());
        let position = part.own_attributes.layer_position;
        if (part.layer_size.0, part.layer_size.1) != (w, h) || position != origin {
            return Err(err(format!(
                "part '{}' is {} x {} at {:?}, but the first part is {w} x {h} at {:?}: all \
                 layers of a bundle must share one data window",
                part_name.as_deref().unwrap_or(""),
                part.layer_size.0,
                part.layer_size.1,
                position,
                origin
            )));
        }
        spp_attr = spp_attr.or(attribute_spp(&part.own_attributes.other));
        for (c, channel) in part.channels.list.iter().enumerate() {
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
            if channel.sampling != exr::math::Vec2(1, 1) {
                return Err(err(format!(
                    "channel '{full}' of layer {layer} is subsampled {} x {}: the frame's \
                     layers must be stored at full resolution (other layers may be subsampled)",
                    channel.sampling.0, channel.sampling.1
                )));
            }
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
            entries.push((full, component, (p, c)));
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
    let mut targets = channel_slots(&meta);
    let mut images = Vec::new();
    let mut order = Vec::new();
    let mut sources = BTreeMap::new();
    for (layer, channels) in found {
        let (chosen, names, extra) = assemble(layer, channels).map_err(err)?;
        for (plane, &(p, c)) in chosen.iter().enumerate() {
            targets[p][c] = Some(Target {
                image: images.len(),
                plane,
            });
        }
        images.push(Image::try_zeros(chosen.len(), w, h)?);
        order.push(layer);
        sources.insert(layer, names);
        ignored.extend(extra);
    }
    let summaries = blocks::decode(reader, (&meta, &offsets), &targets, &mut images)
        .map_err(|f| fault(f, path))?;
    let raw = RawBundle {
        path: path.to_owned(),
        size: (w, h),
        layers: order.iter().copied().zip(images).collect(),
        sources,
        ignored,
        spp,
        warnings,
    };
    Ok((raw, order.into_iter().zip(summaries).collect()))
}

/// A channel found for a layer: its full name, its component (upper case), and where it is
/// stored (part, index in the part's channel list).
type Stored = (String, String, (usize, usize));

/// One empty slot per stored channel of every part.
fn channel_slots(meta: &MetaData) -> Vec<Vec<Option<Target>>> {
    meta.headers
        .iter()
        .map(|h| vec![None; h.channels.list.len()])
        .collect()
}

fn fault(f: Fault, path: &Path) -> Error {
    match f {
        Fault::Exr(e) => exr_error(e, path),
        Fault::Damaged(m) => Error::Exr {
            path: path.to_owned(),
            message: format!("damaged OpenEXR file: {m}"),
        },
    }
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

/// The chosen channels' payloads in component order, their names, the names left over.
type Assembled<T> = (Vec<T>, Vec<String>, Vec<String>);

/// Picks the layer's components out of the channels found for it. A 3-channel layer may be
/// stored as RGB or XYZ; depth as `Z`, `Y`, `T` or its only channel.
fn assemble<T: Copy>(
    layer: Layer,
    mut channels: Vec<(String, String, T)>,
) -> Result<Assembled<T>, String> {
    let wanted: Vec<Vec<&str>> = match layer {
        Layer::Depth => vec![vec!["Z"], vec!["Y"], vec!["T"], vec!["R"]],
        Layer::Normal => vec![vec!["X", "Y", "Z"], vec!["R", "G", "B"]],
        _ => vec![vec!["R", "G", "B"], vec!["X", "Y", "Z"]],
    };
    let pick = |set: &Vec<&str>, chans: &Vec<(String, String, T)>| -> Option<Vec<usize>> {
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
    let chosen = indices.iter().map(|&i| channels[i].2).collect();
    let names = indices.iter().map(|&i| channels[i].0.clone()).collect();
    let mut sorted = indices.clone();
    sorted.sort_unstable_by(|a, b| b.cmp(a));
    for i in sorted {
        channels.remove(i);
    }
    let extra = channels.into_iter().map(|(n, _, _)| n).collect();
    Ok((chosen, names, extra))
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
    let (meta, offsets) = check_layout(&mut reader, path)?;
    let part = meta.headers.first().ok_or_else(|| Error::Exr {
        path: path.to_owned(),
        message: "the file has no image parts".into(),
    })?;
    let find = |prefix: &str| -> Option<Vec<usize>> {
        ["R", "G", "B"]
            .iter()
            .map(|c| {
                let want = if prefix.is_empty() {
                    c.to_string()
                } else {
                    format!("{prefix}.{c}")
                };
                part.channels
                    .list
                    .iter()
                    .position(|ch| ch.name.to_string().eq_ignore_ascii_case(&want))
            })
            .collect()
    };
    let channels = find("").or_else(|| find(layer)).ok_or_else(|| Error::Exr {
        path: path.to_owned(),
        message: format!(
            "no RGB image: expected channels R, G, B or {layer}.R, {layer}.G, {layer}.B"
        ),
    })?;
    let mut targets = channel_slots(&meta);
    for (plane, c) in channels.into_iter().enumerate() {
        targets[0][c] = Some(Target { image: 0, plane });
    }
    let mut images = [Image::try_zeros(3, part.layer_size.0, part.layer_size.1)?];
    blocks::decode(reader, (&meta, &offsets), &targets, &mut images).map_err(|f| fault(f, path))?;
    let [image] = images;
    Ok(image)
}

/// Writes f32 planes as one scan-line part, ZIP compression, `spp` as an attribute when known.
fn write_planes(
    path: &Path,
    size: (usize, usize),
    mut channels: Vec<(String, &[f32])>,
    spp: Option<f32>,
) -> Result<()> {
    channels.sort_by(|a, b| a.0.cmp(&b.0));
    let names: Vec<&str> = channels.iter().map(|(n, _)| n.as_str()).collect();
    let planes: Vec<&[f32]> = channels.iter().map(|(_, p)| *p).collect();
    let mut header = blocks::f32_header(&names, size);
    if let Some(s) = spp {
        header
            .shared_attributes
            .other
            .insert(x::Text::from("spp"), AttributeValue::F32(s));
    }
    let io_error = |source| Error::Io {
        path: path.to_owned(),
        source,
    };
    let file = std::fs::File::create(path).map_err(io_error)?;
    let mut writer = std::io::BufWriter::new(file);
    let written = blocks::encode(&mut writer, header, &planes)
        .map_err(|f| fault(f, path))
        .and_then(|()| writer.flush().map_err(io_error));
    if written.is_err() {
        // Never leave a partial file behind under the name asked for.
        drop(writer);
        let _ = std::fs::remove_file(path);
    }
    written
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
        .map(|(c, name)| (name.to_string(), plane(image, c)))
        .collect();
    write_planes(path.as_ref(), image.size(), channels, None)
}

fn plane(image: &Image, c: usize) -> &[f32] {
    let len = image.width() * image.height();
    &image.as_slice()[c * len..(c + 1) * len]
}

/// Writes every layer of `frame` as a bundle (f32, ZIP, `spp` attribute when known).
pub fn write_bundle(path: impl AsRef<Path>, frame: &Frame) -> Result<()> {
    let mut channels = Vec::new();
    for layer in frame.present_layers() {
        let img = frame.layer(layer).expect("present");
        for (c, comp) in layer.components().iter().enumerate() {
            channels.push((format!("{layer}.{comp}"), plane(img, c)));
        }
    }
    write_planes(path.as_ref(), frame.size(), channels, frame.spp())
}
