//! Block-level OpenEXR decoding and encoding: the `exr` crate's chunk reader and writer, with
//! our own placement of samples.
//!
//! Decoding reads the chunks of the largest resolution level in file order, decompresses them
//! (in parallel when called inside a rayon pool, such as [`crate::Context::install`]; on the
//! calling thread otherwise, so that a library call never starts threads of its own) and
//! converts each wanted channel's samples to f32 straight into its destination plane: no
//! intermediate copy of the image, and channels nobody asked for are never converted. ZIP and
//! RLE blocks are converted from their split bytes ([`super::codec`]), and each image's values
//! are summarised as they are converted ([`Summary`]), so that no later pass reads them again
//! to find them clean. Encoding does the reverse for f32 planes, compressing ZIP blocks the
//! same way.
//!
//! The chunk layout was checked before ([`super::chunks::check`]): every block of the level
//! is stored exactly once. Decoding still counts the pixels each part received and refuses a
//! part that did not get all of them.

use std::io::{Read, Seek, Write};
use std::sync::Mutex;

use exr::block::chunk::{
    Chunk, CompressedBlock, CompressedScanLineBlock, CompressedTileBlock, TileCoordinates,
};
use exr::block::reader::ChunksReader;
use exr::block::writer::ChunksWriter;
use exr::block::{BlockIndex, UncompressedBlock};
use exr::meta::attribute::{ChannelDescription, SampleType};
use exr::meta::header::Header;
use exr::meta::MetaData;
use exr::prelude::f16;
use rayon::prelude::*;

use super::chunks::Offsets;
use super::codec;
use crate::image::Image;
use crate::validate::Summary;

/// Where one stored channel goes: image `image`, plane `plane` of the destinations.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Target {
    pub image: usize,
    pub plane: usize,
}

/// Decodes the largest level of every part into `images`: `targets[part][channel]` names the
/// plane of each stored channel (in the header's channel order), `None` skips it. Every image
/// must be as large as the parts' data window (all parts share one, checked by the caller).
/// `layout` is the file's headers and offset tables as [`super::chunks::check`] accepted
/// them. Returns what each image's values are, summarised as they were converted (see
/// [`Summary`]). Errors are the decoder's, or a part that is missing blocks.
pub(super) fn decode(
    mut reader: impl Read + Seek + Send,
    layout: (&MetaData, &Offsets),
    targets: &[Vec<Option<Target>>],
    images: &mut [Image],
) -> Result<Vec<Summary>, Fault> {
    let (meta, offsets) = layout;
    if meta.headers.iter().any(subsampled) {
        // The `exr` crate's reader refuses these headers: the chunks are read here.
        let chunks = read_chunks(&mut reader, meta, offsets)?;
        return place_all(chunks.into_iter().map(Ok), meta, targets, images);
    }
    let chunks = exr::block::read(reader, false)?.filter_chunks(false, |_, tile, _| {
        tile.level_index == exr::math::Vec2(0, 0)
    })?;
    let meta: MetaData = chunks.meta_data().clone();
    place_all(
        chunks.map(|c| c.map_err(Fault::from)),
        &meta,
        targets,
        images,
    )
}

/// Decompresses `chunks` and places them (see [`decode`]), checking that every part received
/// all its pixels.
fn place_all(
    chunks: impl Iterator<Item = Result<Chunk, Fault>> + Send,
    meta: &MetaData,
    targets: &[Vec<Option<Target>>],
    images: &mut [Image],
) -> Result<Vec<Summary>, Fault> {
    let mut received = vec![0usize; meta.headers.len()];
    let mut summaries = vec![Summary::default(); images.len()];
    let mut place = |block: Decoded, images: &mut [Image]| -> Result<(), Fault> {
        let part = block.index.layer;
        let header = meta.headers.get(part).ok_or("block of an unknown part")?;
        let none = Vec::new();
        let wanted = targets.get(part).unwrap_or(&none);
        scatter(&block, header, wanted, images, &mut summaries)?;
        received[part] += block.index.pixel_size.area();
        Ok(())
    };
    if rayon::current_thread_index().is_some() && rayon::current_num_threads() > 1 {
        // Decompression is nearly all the work; placing a block is a copy, done under the lock.
        let shared = Mutex::new((images, &mut place));
        chunks
            .par_bridge()
            .try_for_each(|chunk| -> Result<(), Fault> {
                let block = decompress(chunk?, meta)?;
                let mut guard = shared.lock().map_err(|_| "a decoding thread panicked")?;
                let (images, place) = &mut *guard;
                place(block, images)
            })?;
    } else {
        for chunk in chunks {
            let block = decompress(chunk?, meta)?;
            place(block, images)?;
        }
    }
    for (part, header) in meta.headers.iter().enumerate() {
        let (w, h) = (header.layer_size.0, header.layer_size.1);
        if received[part] != w * h {
            return Err(format!(
                "part {part} holds {} of its {} pixels: blocks are missing",
                received[part],
                w * h
            )
            .into());
        }
    }
    Ok(summaries)
}

/// Whether a part holds a subsampled channel.
fn subsampled(header: &Header) -> bool {
    header
        .channels
        .list
        .iter()
        .any(|c| c.sampling != exr::math::Vec2(1, 1))
}

/// The full-resolution chunks of every part, read where the checked offset tables say
/// (unwritten reduced levels, offset 0, are skipped; reduced levels are not read).
fn read_chunks(
    reader: &mut (impl Read + Seek),
    meta: &MetaData,
    offsets: &Offsets,
) -> Result<Vec<Chunk>, Fault> {
    let multipart = meta.headers.len() > 1;
    let mut chunks = Vec::new();
    let int = |reader: &mut dyn Read| -> Result<i32, Fault> {
        let mut b = [0u8; 4];
        reader.read_exact(&mut b).map_err(exr::error::Error::from)?;
        Ok(i32::from_le_bytes(b))
    };
    for (part, (header, table)) in meta.headers.iter().zip(offsets).enumerate() {
        if header.deep {
            return Err("deep data is not a frame bundle".into());
        }
        let tiled = header.blocks != exr::meta::BlockDescription::ScanLines;
        for &offset in table.iter().filter(|&&o| o != 0) {
            reader
                .seek(std::io::SeekFrom::Start(offset))
                .map_err(exr::error::Error::from)?;
            if multipart {
                int(reader)?; // the part number, checked by `chunks::check`
            }
            let coords: Vec<i32> = (0..if tiled { 4 } else { 1 })
                .map(|_| int(reader))
                .collect::<Result<_, _>>()?;
            let size = usize::try_from(int(reader)?).map_err(|_| "a chunk of negative size")?;
            if tiled && (coords[2], coords[3]) != (0, 0) {
                continue; // a reduced level: never decoded
            }
            let mut data = Vec::new();
            data.try_reserve_exact(size)
                .map_err(|_| "a chunk too large to allocate")?;
            data.resize(size, 0);
            reader
                .read_exact(&mut data)
                .map_err(exr::error::Error::from)?;
            let compressed_block = if tiled {
                let at = |v: i32| usize::try_from(v).map_err(|_| "a negative tile coordinate");
                CompressedBlock::Tile(CompressedTileBlock {
                    coordinates: TileCoordinates {
                        tile_index: exr::math::Vec2(at(coords[0])?, at(coords[1])?),
                        level_index: exr::math::Vec2(0, 0),
                    },
                    compressed_pixels_le: data,
                })
            } else {
                CompressedBlock::ScanLine(CompressedScanLineBlock {
                    y_coordinate: coords[0],
                    compressed_pixels_le: data,
                })
            };
            chunks.push(Chunk {
                layer_index: part,
                compressed_block,
            });
        }
    }
    Ok(chunks)
}

/// A decompressed block: its bytes as a block lays them out (for each of its rows, each
/// channel's samples of that row, in the header's channel order), or still `split` as ZIP and
/// RLE store them (the even-indexed bytes of that layout, then the odd ones): [`scatter`]
/// reads samples from the two halves directly rather than interleaving them first.
struct Decoded {
    data: Vec<u8>,
    split: bool,
    index: BlockIndex,
}

/// Converts the wanted lines of one block into their planes, adding their values to their
/// image's summary.
fn scatter(
    block: &Decoded,
    header: &Header,
    wanted: &[Option<Target>],
    images: &mut [Image],
    summaries: &mut [Summary],
) -> Result<(), Fault> {
    let BlockIndex {
        pixel_position: pos,
        pixel_size: size,
        ..
    } = block.index;
    // Every sample type has an even size, so a block's length and every line's offset are even.
    if block.split && block.data.len() % 2 != 0 {
        return Err("a block holds an odd number of bytes".into());
    }
    let (even, odd) = block.data.split_at(block.data.len() / 2);
    let mut offset = 0;
    let origin = header.own_attributes.layer_position;
    for row in 0..size.1 {
        let y = origin.1 + (pos.1 + row) as i32;
        for (c, channel) in header.channels.list.iter().enumerate() {
            let Some(samples) = line_samples(channel, y, size.0) else {
                continue; // a subsampled channel with no samples on this line
            };
            let len = samples * channel.sample_type.bytes_per_sample();
            let (start, end) = (offset, offset + len);
            offset = end;
            if end > block.data.len() {
                return Err("a block holds fewer bytes than its size needs".into());
            }
            let Some(Some(target)) = wanted.get(c) else {
                continue;
            };
            if samples != size.0 {
                return Err("a subsampled channel was asked for".into());
            }
            let image = images
                .get_mut(target.image)
                .ok_or("channel target out of range")?;
            let width = image.width();
            let plane = image
                .plane_mut(target.plane)
                .into_slice()
                .ok_or("planes are contiguous")?;
            let first = (pos.1 + row) * width + pos.0;
            let dst = plane
                .get_mut(first..first + size.0)
                .ok_or("a block lies outside the data window")?;
            let kind = channel.sample_type;
            if block.split {
                let halves = (&even[start / 2..end / 2], &odd[start / 2..end / 2]);
                convert_split(halves, kind, dst);
            } else {
                convert(&block.data[start..end], kind, dst);
            }
            summaries
                .get_mut(target.image)
                .ok_or("channel target out of range")?
                .add(dst);
        }
    }
    if offset != block.data.len() {
        return Err("a block holds more bytes than its size needs".into());
    }
    Ok(())
}

/// The samples of `channel` on absolute line `y` of a `width`-pixel line, `None` when the line
/// holds none. OpenEXR samples a channel subsampled `sx` x `sy` at the pixels whose absolute
/// coordinates are multiples of `sx` and `sy`; its headers require the data window's origin and
/// size to be multiples of them, so a line that has samples has `width / sx`.
fn line_samples(channel: &ChannelDescription, y: i32, width: usize) -> Option<usize> {
    let (sx, sy) = (channel.sampling.0.max(1), channel.sampling.1.max(1));
    (y.rem_euclid(sy as i32) == 0).then_some(width / sx)
}

/// Decompresses one chunk. Scan-line blocks stored raw or with a byte-stream codec (NONE,
/// RLE, ZIPS, ZIP: the usual output of renderers) are decoded here, ZIP and RLE left split;
/// the rest by the `exr` crate's decoders. Scan-line parts holding subsampled channels are
/// decoded here for those codecs (the crate sizes their blocks as if no channel were
/// subsampled) and refused naming the codec otherwise.
fn decompress(chunk: Chunk, meta: &MetaData) -> Result<Decoded, Fault> {
    let header = meta
        .headers
        .get(chunk.layer_index)
        .ok_or("chunk of an unknown part")?;
    use exr::compression::Compression as C;
    // On a big-endian machine only what the crate cannot decode is decoded here (and refused
    // below): `convert` reads native-endian samples, and the crate's are.
    let own = cfg!(target_endian = "little")
        && matches!(
            header.compression,
            C::Uncompressed | C::RLE | C::ZIP1 | C::ZIP16
        );
    // Subsampled channels are in scan-line parts only (others are refused by the header
    // checks, `exr::check_layout`).
    let layer = chunk.layer_index;
    let block = match chunk.compressed_block {
        CompressedBlock::ScanLine(block) if own || subsampled(header) => block,
        compressed_block => {
            let chunk = Chunk {
                layer_index: layer,
                compressed_block,
            };
            let block = UncompressedBlock::decompress_chunk(chunk, meta, false)?;
            return Ok(Decoded {
                data: block.data,
                split: false,
                index: block.index,
            });
        }
    };
    let (width, height) = (header.layer_size.0, header.layer_size.1);
    let origin = header.own_attributes.layer_position;
    let first = block
        .y_coordinate
        .checked_sub(origin.1)
        .and_then(|y| usize::try_from(y).ok())
        .filter(|&y| y < height)
        .ok_or("a chunk's y lies outside the data window")?;
    let rows = header
        .compression
        .scan_lines_per_block()
        .min(height - first);
    let raw_len: usize = (0..rows)
        .map(|row| {
            let y = block.y_coordinate + row as i32;
            header
                .channels
                .list
                .iter()
                .filter_map(|c| Some(line_samples(c, y, width)? * c.sample_type.bytes_per_sample()))
                .sum::<usize>()
        })
        .sum();
    if cfg!(target_endian = "big") {
        // Samples are little-endian in the file; `convert` reads native-endian ones.
        return Err("subsampled channels are decoded on little-endian machines only".into());
    }
    let packed = block.compressed_pixels_le;
    let (data, split) = if packed.len() == raw_len {
        (packed, false) // stored raw: compressing did not make it smaller
    } else {
        let bytes = match header.compression {
            C::ZIP1 | C::ZIP16 => codec::inflate(&packed, raw_len)?,
            C::RLE => codec::unpack_rle(&packed, raw_len)?,
            C::Uncompressed => return Err("an uncompressed block's size is wrong".into()),
            other => {
                return Err(Fault::Exr(exr::error::Error::NotSupported(
                    format!(
                        "subsampled channels are read only from files compressed with NONE, \
                         RLE, ZIPS or ZIP, not {other}"
                    )
                    .into(),
                )))
            }
        };
        if bytes.len() != raw_len {
            return Err("a block does not decompress to its size".into());
        }
        (bytes, true)
    };
    Ok(Decoded {
        data,
        split,
        index: BlockIndex {
            layer,
            pixel_position: exr::math::Vec2(0, first),
            pixel_size: exr::math::Vec2(width, rows),
            level: exr::math::Vec2(0, 0),
        },
    })
}

/// Samples of one type, from the two halves of a split block (each sample's even-indexed
/// bytes in the first, its odd-indexed ones in the second; little-endian), to f32.
fn convert_split(halves: (&[u8], &[u8]), kind: SampleType, dst: &mut [f32]) {
    let (even, odd) = halves;
    match kind {
        SampleType::F32 => codec::join_words(even, odd, dst, f32::from_bits),
        SampleType::U32 => codec::join_words(even, odd, dst, |w| w as f32),
        SampleType::F16 => {
            for (d, (&e, &o)) in dst.iter_mut().zip(even.iter().zip(odd)) {
                *d = f16::from_bits(u16::from_le_bytes([e, o])).to_f32();
            }
        }
    }
}

/// Native-endian samples of one type to f32.
fn convert(bytes: &[u8], kind: SampleType, dst: &mut [f32]) {
    match kind {
        SampleType::F32 => {
            for (d, s) in dst.iter_mut().zip(bytes.chunks_exact(4)) {
                *d = f32::from_ne_bytes([s[0], s[1], s[2], s[3]]);
            }
        }
        SampleType::F16 => {
            for (d, s) in dst.iter_mut().zip(bytes.chunks_exact(2)) {
                *d = f16::from_bits(u16::from_ne_bytes([s[0], s[1]])).to_f32();
            }
        }
        SampleType::U32 => {
            for (d, s) in dst.iter_mut().zip(bytes.chunks_exact(4)) {
                *d = u32::from_ne_bytes([s[0], s[1], s[2], s[3]]) as f32;
            }
        }
    }
}

/// Writes one scan-line part of f32 channels, `planes[i]` stored as channel `names[i]` of
/// `header` (sorted, as OpenEXR stores them), ZIP-compressed in blocks of 16 rows, in parallel
/// when called inside a rayon pool.
pub(super) fn encode(
    writer: impl Write + Seek,
    header: Header,
    planes: &[&[f32]],
) -> Result<(), Fault> {
    let (width, height) = (header.layer_size.0, header.layer_size.1);
    let rows = header.compression.scan_lines_per_block();
    if planes.iter().any(|p| p.len() != width * height) {
        return Err("a plane's length differs from the image's".into());
    }
    exr::block::write(
        writer,
        smallvec::smallvec![header],
        true,
        |meta, chunk_writer| {
            let blocks: Vec<(usize, BlockIndex)> =
                exr::block::enumerate_ordered_header_block_indices(&meta.headers).collect();
            let compress = |&(_, index): &(usize, BlockIndex)| -> Chunk {
                let (y0, lines) = (index.pixel_position.1, index.pixel_size.1.min(rows));
                let line_rows = |y: usize| planes.iter().map(move |p| &p[y * width..][..width]);
                let block_rows = (y0..y0 + lines).flat_map(line_rows);
                // Split as it is gathered: the raw block is never laid out.
                let len = 4 * width * lines * planes.len();
                let mut split = vec![0u8; len];
                let (even, odd) = split.split_at_mut(len / 2);
                let halves = even
                    .chunks_exact_mut(2 * width)
                    .zip(odd.chunks_exact_mut(2 * width));
                for (row, (even, odd)) in block_rows.clone().zip(halves) {
                    codec::split_words(row, even, odd);
                }
                let packed = codec::deflate(&split);
                // OpenEXR stores a block raw when compressing does not make it smaller.
                let compressed_pixels_le = if packed.len() < len {
                    packed
                } else {
                    block_rows.flatten().flat_map(|v| v.to_le_bytes()).collect()
                };
                Chunk {
                    layer_index: 0,
                    compressed_block: CompressedBlock::ScanLine(CompressedScanLineBlock {
                        y_coordinate: y0 as i32,
                        compressed_pixels_le,
                    }),
                }
            };
            // Compressed a batch at a time, in parallel, each batch written before the next:
            // memory holds one batch's blocks, not the whole file's (at 7680 x 4320 the
            // output's 270 compressed blocks took 250-320 MiB beyond a plan's estimate).
            let parallel = rayon::current_thread_index().is_some();
            for batch in blocks.chunks(4 * rayon::current_num_threads().max(1)) {
                let chunks: Vec<Chunk> = if parallel {
                    batch.par_iter().map(compress).collect()
                } else {
                    batch.iter().map(compress).collect()
                };
                for ((index_in_header, _), chunk) in batch.iter().zip(chunks) {
                    chunk_writer.write_chunk(*index_in_header, chunk)?;
                }
            }
            Ok(())
        },
    )?;
    Ok(())
}

/// A scan-line header (ZIP, 16 rows per block, increasing line order, no name attribute) for
/// f32 channels `names` (sorted) of a `width` x `height` image.
pub(super) fn f32_header(names: &[&str], size: (usize, usize)) -> Header {
    let channels = names
        .iter()
        .map(|n| ChannelDescription::named(*n, SampleType::F32))
        .collect();
    let mut header = Header::new(exr::prelude::Text::from(""), size, channels).with_encoding(
        exr::compression::Compression::ZIP16,
        exr::meta::BlockDescription::ScanLines,
        exr::meta::attribute::LineOrder::Increasing,
    );
    header.own_attributes = exr::meta::header::LayerAttributes::default();
    header
}

/// A decoding or encoding failure: the `exr` crate's own error (the caller maps it as it maps
/// the crate's other errors), or what the block placement found wrong.
#[derive(Debug)]
pub(super) enum Fault {
    /// From the `exr` crate.
    Exr(exr::error::Error),
    /// A block that does not fit the header.
    Damaged(String),
}

impl From<&str> for Fault {
    fn from(m: &str) -> Self {
        Fault::Damaged(m.to_owned())
    }
}

impl From<String> for Fault {
    fn from(m: String) -> Self {
        Fault::Damaged(m)
    }
}

impl From<exr::error::Error> for Fault {
    fn from(e: exr::error::Error) -> Self {
        Fault::Exr(e)
    }
}
