//! OpenEXR's byte-stream codecs, ZIP and RLE, both ways. Both store a block's bytes (each
//! row's channels one after another, little-endian samples) *split*: the even-indexed bytes
//! first, then the odd ones, and *predicted*: each byte as its difference to the one before,
//! plus 128. Decoding here stops at the split bytes (see [`inflate`]): the reader converts
//! samples from the two halves directly, so no pass puts the bytes back in order first.

use super::blocks::Fault;

/// Deflate level of written blocks. Level 1 (miniz's fast path) compresses a 1280 x 720 RGB
/// f32 frame of noisy radiance 4.3x faster than the `exr` crate's fixed level 4 (0.064 s
/// against 0.278 s on one core) into a file 4 % larger (10.98 MB against 10.53 MB; OpenEXR's
/// own writer: 10.85 MB): float noise leaves deflate little to find at any level.
/// (libdeflate at its level 1 took 1.5x miniz's time on the same blocks, sixty-first session.)
const ZIP_LEVEL: u8 = 1;

/// A ZIP block's `packed` bytes inflated and un-predicted: the block's `len` bytes, still
/// split. Errors when the stream is damaged (zlib's checksum included) or does not inflate to
/// exactly `len` bytes.
pub(super) fn inflate(packed: &[u8], len: usize) -> Result<Vec<u8>, Fault> {
    let options = zune_inflate::DeflateOptions::default()
        .set_limit(len)
        .set_size_hint(len);
    let mut bytes = zune_inflate::DeflateDecoder::new_with_options(packed, options)
        .decode_zlib()
        .map_err(|_| "a ZIP block is damaged or does not inflate to its size")?;
    if bytes.len() != len {
        return Err("a ZIP block does not inflate to its size".into());
    }
    unpredict(&mut bytes);
    Ok(bytes)
}

/// An RLE block's `packed` bytes unpacked and un-predicted: at most `limit` bytes, still split.
/// The run-length code: a negative count byte `-n` is followed by `n` literal bytes, a count
/// `n >= 0` by one byte repeated `n + 1` times.
pub(super) fn unpack_rle(mut packed: &[u8], limit: usize) -> Result<Vec<u8>, Fault> {
    let mut out = Vec::new();
    out.try_reserve_exact(limit)
        .map_err(|_| "a block too large to allocate")?;
    while let Some((&count, rest)) = packed.split_first() {
        let count = count as i8;
        if count < 0 {
            let n = count.unsigned_abs() as usize;
            let literal = rest
                .get(..n)
                .ok_or("an RLE block ends inside a literal run")?;
            out.extend_from_slice(literal);
            packed = &rest[n..];
        } else {
            let (&byte, rest) = rest.split_first().ok_or("an RLE block ends inside a run")?;
            out.resize(out.len() + count as usize + 1, byte);
            packed = rest;
        }
        if out.len() > limit {
            return Err("an RLE block expands past its size".into());
        }
    }
    unpredict(&mut out);
    Ok(out)
}

/// A block's `split` bytes predicted and deflated: the inverse of [`inflate`].
pub(super) fn deflate(split: &[u8]) -> Vec<u8> {
    let mut predicted = vec![0u8; split.len()];
    if let (Some(first), Some(out)) = (split.first(), predicted.first_mut()) {
        *out = *first;
    }
    // Each byte against the one before it in `split`, not in place: a loop that vectorises.
    let pairs = split.iter().zip(split.iter().skip(1));
    for (out, (before, byte)) in predicted.iter_mut().skip(1).zip(pairs) {
        *out = byte.wrapping_sub(*before).wrapping_add(128);
    }
    miniz_oxide::deflate::compress_to_vec_zlib(&predicted, ZIP_LEVEL)
}

/// Samples per step of [`join_words`].
const JOIN: usize = 16;

/// `dst[j] = value(w)`, `w` the little-endian word of bytes `even[2 j]`, `odd[2 j]`,
/// `even[2 j + 1]`, `odd[2 j + 1]`. In fixed steps over arrays the byte shuffle vectorises (a
/// plain loop over pairs of bytes ran one byte at a time, 10 % of a ZIP read).
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
pub(super) fn join_words(even: &[u8], odd: &[u8], dst: &mut [f32], value: impl Fn(u32) -> f32) {
    let join = |e: &[u8], o: &[u8]| {
        u32::from(e[0]) | u32::from(o[0]) << 8 | u32::from(e[1]) << 16 | u32::from(o[1]) << 24
    };
    let done = dst.len().min(even.len() / 2).min(odd.len() / 2) / JOIN * JOIN;
    let halves = even.chunks_exact(2 * JOIN).zip(odd.chunks_exact(2 * JOIN));
    for (d, (e, o)) in dst[..done].chunks_exact_mut(JOIN).zip(halves) {
        let (e, o): (&[u8; 2 * JOIN], &[u8; 2 * JOIN]) = match (e.try_into(), o.try_into()) {
            (Ok(e), Ok(o)) => (e, o),
            _ => return, // `chunks_exact` gives whole steps
        };
        for (j, d) in d.iter_mut().enumerate() {
            *d = value(join(&e[2 * j..], &o[2 * j..]));
        }
    }
    let pairs = even[2 * done..]
        .chunks_exact(2)
        .zip(odd[2 * done..].chunks_exact(2));
    for (d, (e, o)) in dst[done..].iter_mut().zip(pairs) {
        *d = value(join(e, o));
    }
}

/// The inverse of [`join_words`] for f32 `values`: `even[2 j]`, `odd[2 j]`, `even[2 j + 1]`,
/// `odd[2 j + 1]` are the little-endian bytes of `values[j]`.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
pub(super) fn split_words(values: &[f32], even: &mut [u8], odd: &mut [u8]) {
    let split = |v: f32, e: &mut [u8], o: &mut [u8]| {
        let [b0, b1, b2, b3] = v.to_le_bytes();
        (e[0], o[0], e[1], o[1]) = (b0, b1, b2, b3);
    };
    let done = values.len().min(even.len() / 2).min(odd.len() / 2) / JOIN * JOIN;
    let halves = even
        .chunks_exact_mut(2 * JOIN)
        .zip(odd.chunks_exact_mut(2 * JOIN));
    for (v, (e, o)) in values[..done].chunks_exact(JOIN).zip(halves) {
        let (e, o): (&mut [u8; 2 * JOIN], &mut [u8; 2 * JOIN]) = match (e.try_into(), o.try_into())
        {
            (Ok(e), Ok(o)) => (e, o),
            _ => return, // `chunks_exact_mut` gives whole steps
        };
        for (j, &v) in v.iter().enumerate() {
            split(v, &mut e[2 * j..], &mut o[2 * j..]);
        }
    }
    let pairs = even[2 * done..]
        .chunks_exact_mut(2)
        .zip(odd[2 * done..].chunks_exact_mut(2));
    for (&v, (e, o)) in values[done..].iter().zip(pairs) {
        split(v, e, o);
    }
}

/// Bytes per word in [`unpredict`].
const WORD: usize = 8;
/// Words per group in [`unpredict`]: the group's running sums are kept on the stack.
const GROUP: usize = 64;
/// The top bit of every byte of a word.
const HIGH: u64 = 0x8080_8080_8080_8080;

/// Undoes the byte predictor in place: `bytes[i] = bytes[i - 1] + bytes[i] - 128` (wrapping), a
/// running sum. Byte by byte it is a chain of dependent adds (the `exr` crate's loop, in pairs,
/// ran at about 1.8 GB/s, 20 % of a ZIP read). Here the sums are taken within 8-byte words
/// first, with no dependence between words (so the loop vectorises), and one byte add a word
/// carries the running total into them: the same bytes, 2-3x faster.
pub(super) fn unpredict(bytes: &mut [u8]) {
    let Some((&mut first, rest)) = bytes.split_first_mut() else {
        return;
    };
    let mut total = first;
    let mut groups = rest.chunks_exact_mut(WORD * GROUP);
    let mut sums = [0u64; GROUP];
    for group in &mut groups {
        total = unpredict_group(group, &mut sums, total);
    }
    for byte in groups.into_remainder() {
        total = total.wrapping_add(*byte).wrapping_sub(128);
        *byte = total;
    }
}

/// [`unpredict`] over one group of `GROUP` words that follows a byte of value `total`;
/// returns the group's last byte.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn unpredict_group(group: &mut [u8], sums: &mut [u64; GROUP], mut total: u8) -> u8 {
    for (sum, word) in sums.iter_mut().zip(group.chunks_exact(WORD)) {
        *sum = word_sums(u64::from_le_bytes(word.try_into().expect("8 bytes")));
    }
    // The running total before each word: the only serial step, one byte add a word.
    let mut before = [0u8; GROUP];
    for (b, sum) in before.iter_mut().zip(sums.iter()) {
        *b = total;
        total = total.wrapping_add((sum >> 56) as u8);
    }
    for ((sum, &b), word) in sums.iter().zip(&before).zip(group.chunks_exact_mut(WORD)) {
        let carried = add_bytes(*sum, u64::from_le_bytes([b; WORD]));
        word.copy_from_slice(&carried.to_le_bytes());
    }
    total
}

/// The running sums of a word's eight bytes less 128 each (little-endian: byte 0 first).
#[inline(always)]
fn word_sums(word: u64) -> u64 {
    let x = word ^ HIGH; // - 128 in every byte (mod 256)
    let x = add_bytes(x, x << 8);
    let x = add_bytes(x, x << 16);
    add_bytes(x, x << 32)
}

/// Byte-wise wrapping addition of two words (no carry crosses a byte).
#[inline(always)]
fn add_bytes(a: u64, b: u64) -> u64 {
    ((a & !HIGH) + (b & !HIGH)) ^ ((a ^ b) & HIGH)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The predictor undone byte by byte, as OpenEXR's specification writes it.
    fn unpredict_plainly(bytes: &mut [u8]) {
        for i in 1..bytes.len() {
            bytes[i] = bytes[i - 1].wrapping_add(bytes[i]).wrapping_sub(128);
        }
    }

    fn interleave(split: &[u8]) -> Vec<u8> {
        let (even, odd) = split.split_at(split.len().div_ceil(2));
        (0..split.len())
            .map(|i| if i % 2 == 0 { even[i / 2] } else { odd[i / 2] })
            .collect()
    }

    /// The word-wise running sum against the byte-by-byte one, on lengths around the word and
    /// group sizes and on bytes that wrap (every value, in a scrambled order).
    #[test]
    fn unpredict_is_the_plain_running_sum() {
        for len in [0usize, 1, 2, 8, 9, 511, 512, 513, 514, 1025, 5000] {
            let mut bytes: Vec<u8> = (0..len).map(|i| (i * 167 + i / 7) as u8).collect();
            let mut plain = bytes.clone();
            unpredict(&mut bytes);
            unpredict_plainly(&mut plain);
            assert_eq!(bytes, plain, "length {len}");
        }
    }

    /// `deflate` then `inflate` gives the split bytes back (odd and even lengths); a damaged
    /// stream and a wrong size are refused.
    #[test]
    fn deflated_blocks_inflate_to_their_bytes() {
        for len in [0usize, 1, 2, 7, 64, 1001, 4099] {
            let split: Vec<u8> = (0..len).map(|i| (i * 37 % 251) as u8).collect();
            let packed = deflate(&split);
            assert_eq!(inflate(&packed, len).unwrap(), split, "length {len}");
            assert!(inflate(&packed, len + 1).is_err(), "length {len} + 1");
            if len > 0 {
                assert!(inflate(&packed, len - 1).is_err(), "length {len} - 1");
            }
        }
        let mut packed = deflate(&[7u8; 300]);
        let middle = packed.len() / 2;
        packed[middle] ^= 0x55;
        assert!(inflate(&packed, 300).is_err(), "a flipped byte");
    }

    /// `split_words` lays f32 samples out as OpenEXR's split does (the little-endian bytes'
    /// even positions, then the odd ones), and `join_words` reads them back bit for bit (NaN
    /// payloads, -0 and infinities included), on lengths around the step.
    #[test]
    fn samples_split_and_join_bit_for_bit() {
        for len in [0usize, 1, 15, 16, 17, 33, 1000] {
            let values: Vec<f32> = (0..len)
                .map(|i| match i % 5 {
                    0 => f32::from_bits(0x7fc0_1234 + i as u32),
                    1 => -0.0,
                    2 => f32::NEG_INFINITY,
                    _ => i as f32 * -1.37e-3,
                })
                .collect();
            let mut split = vec![0u8; 4 * len];
            let (even, odd) = split.split_at_mut(2 * len);
            split_words(&values, even, odd);
            let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
            assert_eq!(interleave(&split), bytes, "length {len}");
            let mut back = vec![0.0f32; len];
            let (even, odd) = split.split_at(2 * len);
            join_words(even, odd, &mut back, f32::from_bits);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&back), bits(&values), "length {len}");
        }
    }

    /// OpenEXR's RLE: literal runs (negative counts) and repeats (count + 1 copies), and the
    /// faults: a run cut short, a block longer than its size.
    #[test]
    fn rle_runs_unpack_and_damage_is_refused() {
        let packed = [0xfdu8, 1, 2, 3, 2, 9];
        let mut expected = [1u8, 2, 3, 9, 9, 9];
        unpredict_plainly(&mut expected);
        assert_eq!(unpack_rle(&packed, 6).unwrap(), expected);
        assert!(unpack_rle(&[0xfe, 1], 6).is_err());
        assert!(unpack_rle(&[3], 6).is_err());
        assert!(unpack_rle(&[9, 5], 6).is_err());
    }
}
