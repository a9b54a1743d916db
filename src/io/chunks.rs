//! The chunk layout of an OpenEXR file, checked before anything is decoded: every block of
//! every part is stored exactly once, where the offset tables say, with the coordinates its
//! place in the table implies, and no two chunks share a byte.
//!
//! The `exr` crate places each chunk by the coordinates the chunk itself carries and reads
//! whatever offsets the tables hold, so a table pointing every entry at chunk 0, or a chunk whose
//! y disagrees with its table entry, decoded into a wrong image with no error (found by an
//! outside test; the OpenEXR library refuses both). This pass reads only the headers' extent, the
//! tables and a few bytes per chunk. Mip and rip levels are checked like the full resolution
//! (though only it is decoded), except that a reduced level may be left unwritten.

use std::io::{Read, Seek, SeekFrom};

use exr::meta::header::Header;
use exr::meta::BlockDescription;

/// What is wrong with a file's chunk layout (the caller adds the path).
pub type Fault = String;

/// The offset tables of a file, one per part, as checked by [`check`].
pub type Offsets = Vec<Vec<u64>>;

/// Checks the chunk layout of a file whose headers `headers` were parsed from `reader`
/// (rewound afterwards), and returns its offset tables. `len` is the file's length in bytes.
pub fn check(
    reader: &mut (impl Read + Seek),
    headers: &[Header],
    len: u64,
) -> Result<Offsets, Fault> {
    let io = |e: std::io::Error| format!("reading the chunk layout: {e}");
    reader.seek(SeekFrom::Start(0)).map_err(io)?;
    headers_end(reader)?; // leaves the reader at the first offset table
    let multipart = headers.len() > 1;
    let mut offsets: Vec<Vec<u64>> = Vec::with_capacity(headers.len());
    for header in headers {
        let mut table = vec![0u64; header.chunk_count];
        for entry in &mut table {
            *entry = u64::from_le_bytes(read_array(reader)?);
        }
        offsets.push(table);
    }
    let chunks_at = reader.stream_position().map_err(io)?;
    // (start, end, part, index) of every chunk, to find overlaps once sorted.
    let mut spans: Vec<(u64, u64, usize, usize)> = Vec::new();
    for (part, (header, table)) in headers.iter().zip(&offsets).enumerate() {
        if header.deep {
            continue; // refused by the decoder (deep data is not a frame bundle)
        }
        let expected = expected_blocks(header);
        if expected.len() != table.len() {
            return Err(format!(
                "part {part} declares {} chunks but its size and block layout make {}",
                table.len(),
                expected.len()
            ));
        }
        for (index, (&offset, want)) in table.iter().zip(&expected).enumerate() {
            let whose = || format!("chunk {index} of part {part} (offset {offset})");
            // A reduced level left unwritten (offset 0, as OpenEXR's writer leaves levels the
            // caller never filled) is never read: only the full resolution is decoded.
            if offset == 0 && want.len() == 4 && want[2..] != [0, 0] {
                continue;
            }
            let header_len = 4 * (multipart as u64 + want.len() as u64 + 1);
            if offset < chunks_at || offset.saturating_add(header_len) > len {
                return Err(format!(
                    "{} lies outside the chunk data ({chunks_at}..{len}): damaged offset table",
                    whose()
                ));
            }
            reader.seek(SeekFrom::Start(offset)).map_err(io)?;
            if multipart {
                let stored = i32::from_le_bytes(read_array(reader)?);
                if stored != part as i32 {
                    return Err(format!(
                        "{} belongs to part {stored}: damaged offset table",
                        whose()
                    ));
                }
            }
            let mut coords = [0i32; 4];
            for c in coords.iter_mut().take(want.len()) {
                *c = i32::from_le_bytes(read_array(reader)?);
            }
            if coords[..want.len()] != want[..] {
                return Err(format!(
                    "{} says it holds block {:?}, but its place in the offset table is block \
                     {want:?}: damaged offset table or chunk",
                    whose(),
                    &coords[..want.len()]
                ));
            }
            let size = i32::from_le_bytes(read_array(reader)?);
            let end = offset
                .saturating_add(header_len)
                .saturating_add(size as u64);
            if size < 0 || end > len {
                return Err(format!(
                    "{} declares {size} bytes of data, past the end of the file ({len} bytes): \
                     truncated or damaged",
                    whose()
                ));
            }
            spans.push((offset, end, part, index));
        }
    }
    spans.sort_unstable();
    if let Some(pair) = spans.windows(2).find(|p| p[1].0 < p[0].1) {
        let ((_, _, p0, i0), (_, _, p1, i1)) = (pair[0], pair[1]);
        return Err(format!(
            "chunk {i0} of part {p0} and chunk {i1} of part {p1} overlap in the file: damaged \
             offset table"
        ));
    }
    reader.seek(SeekFrom::Start(0)).map_err(io)?;
    Ok(offsets)
}

/// The coordinates each chunk must carry, in offset-table order: `[y]` for scan lines
/// (absolute, as stored), `[tile x, tile y, level x, level y]` for tiles.
fn expected_blocks(header: &Header) -> Vec<Vec<i32>> {
    let origin_y = header.own_attributes.layer_position.y();
    let lines = header.compression.scan_lines_per_block() as i32;
    let tiled = matches!(header.blocks, BlockDescription::Tiles(_));
    header
        .blocks_increasing_y_order()
        .map(|block| {
            let t = block.location;
            if tiled {
                vec![
                    t.tile_index.x() as i32,
                    t.tile_index.y() as i32,
                    t.level_index.x() as i32,
                    t.level_index.y() as i32,
                ]
            } else {
                vec![origin_y + t.tile_index.y() as i32 * lines]
            }
        })
        .collect()
}

/// Walks the headers (magic, version, attributes, and for multi-part files the empty header
/// ending the list) and returns the position of the first offset table.
fn headers_end(reader: &mut (impl Read + Seek)) -> Result<u64, Fault> {
    walk_headers(reader, |_, _, _| {})
}

/// A compression the `exr` crate does not know (ZSTD, added in OpenEXR 3.4), named from the raw
/// headers, which the crate refuses to parse (it called such files "damaged"). `None` when the
/// compression is not the problem. Rewinds the reader.
pub fn unsupported(reader: &mut (impl Read + Seek)) -> Option<String> {
    let mut found = None;
    reader.seek(SeekFrom::Start(0)).ok()?;
    let _ = walk_headers(reader, |name, kind, value| {
        if found.is_none() && name == "compression" && kind == "compression" && value.len() == 1 {
            found = match value[0] {
                0..=11 => None,
                13 => Some("ZSTD compression (OpenEXR 3.4)".to_owned()),
                code => Some(format!("compression number {code}")),
            };
        }
    });
    reader.seek(SeekFrom::Start(0)).ok()?;
    found.map(|c| {
        format!(
            "{c} is not decoded by this reader; write the bundle with ZIP, PIZ, RLE, PXR24, B44 \
             or DWA"
        )
    })
}

/// Walks the headers, handing `visit` each `compression` attribute as (name, type, value), others
/// skipped unread; returns the position after the headers.
fn walk_headers(
    reader: &mut (impl Read + Seek),
    mut visit: impl FnMut(&str, &str, &[u8]),
) -> Result<u64, Fault> {
    let magic: [u8; 4] = read_array(reader)?;
    if magic != [0x76, 0x2f, 0x31, 0x01] {
        return Err("not an OpenEXR file (no magic number)".into());
    }
    let version = u32::from_le_bytes(read_array(reader)?);
    let multipart = version & 0x1000 != 0;
    loop {
        let mut attributes = 0;
        loop {
            let name = read_name(reader)?;
            if name.is_empty() {
                break;
            }
            let kind = read_name(reader)?;
            let size = i32::from_le_bytes(read_array(reader)?);
            if size < 0 {
                return Err(format!("attribute '{name}' has a negative size"));
            }
            if kind == "compression" && size == 1 {
                let mut value = vec![0u8; size as usize];
                reader
                    .read_exact(&mut value)
                    .map_err(|e| format!("reading the headers: {e}"))?;
                visit(&name, &kind, &value);
            } else {
                reader
                    .seek(SeekFrom::Current(i64::from(size)))
                    .map_err(|e| format!("reading the headers: {e}"))?;
            }
            attributes += 1;
        }
        if !multipart || attributes == 0 {
            break;
        }
    }
    reader
        .stream_position()
        .map_err(|e| format!("reading the headers: {e}"))
}

/// A null-terminated attribute name or type (at most 255 bytes, as the format allows).
fn read_name(reader: &mut impl Read) -> Result<String, Fault> {
    let mut name = Vec::new();
    loop {
        let [b] = read_array::<1>(reader)?;
        if b == 0 {
            return Ok(String::from_utf8_lossy(&name).into_owned());
        }
        if name.len() == 255 {
            return Err("a header attribute name is longer than 255 bytes".into());
        }
        name.push(b);
    }
}

fn read_array<const N: usize>(reader: &mut impl Read) -> Result<[u8; N], Fault> {
    let mut bytes = [0u8; N];
    reader.read_exact(&mut bytes).map_err(|e| {
        if e.kind() == std::io::ErrorKind::UnexpectedEof {
            "truncated (the file ends inside its headers, offset tables or a chunk header)".into()
        } else {
            format!("reading the chunk layout: {e}")
        }
    })?;
    Ok(bytes)
}
