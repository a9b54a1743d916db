//! Arbitrary image-view descriptions through the C ABI (`gdr_filter_set_image`,
//! `gdr_filter_set_image_planar`, commit, execute with `l2`).
//!
//! The library cannot know how large the caller's buffer is, so the contract is: a view it
//! accepts touches exactly the elements its size and strides describe, none twice. The target
//! computes that extent independently, allocates exactly it (plus a canary after it), and when
//! the library accepts the view it checks the elements are distinct, then commits and executes:
//! AddressSanitizer catches any read or write outside the extent, and the canary any write
//! into the input. Views it rejects must come back as INVALID_IMAGE, NULL_POINTER or
//! INVALID_ARGUMENT, never a crash.
#![no_main]

use std::collections::HashSet;
use std::ffi::c_char;
use std::ptr;

use gdrecon::capi::*;
use libfuzzer_sys::fuzz_target;

/// A view description decoded from fuzz bytes.
#[derive(Debug, Clone, Copy)]
struct Desc {
    planar: bool,
    width: usize,
    height: usize,
    channels: usize,
    /// Interleaved: pixel, row. Planar: row, plane. Bytes; 0 = packed.
    s1: usize,
    s2: usize,
    misalign: usize,
}

fn decode(data: &[u8]) -> Option<Desc> {
    let b = |i: usize| data.get(i).copied().unwrap_or(0) as usize;
    if data.len() < 8 {
        return None;
    }
    let stride = |lo: usize, hi: usize, shift: usize| {
        let v = b(lo) | (b(hi) << 8);
        // Mostly small strides; sometimes huge, to reach the overflow checks.
        if b(7) & (1 << shift) != 0 {
            v << 40
        } else {
            v
        }
    };
    Some(Desc {
        planar: b(0) & 1 == 1,
        width: b(1) % 20,
        height: b(2) % 20,
        channels: if b(0) & 2 == 0 { 3 } else { b(3) % 6 },
        s1: stride(3, 4, 0),
        s2: stride(5, 6, 1),
        misalign: if b(0) & 4 == 0 { 0 } else { (b(0) >> 3) % 4 },
    })
}

/// Byte offsets of every element the description names, or None if they do not fit a usize.
fn offsets(d: Desc) -> Option<Vec<usize>> {
    let f = 4usize;
    let (ch, px, row) = if d.planar {
        let row = if d.s1 == 0 { d.width.checked_mul(f)? } else { d.s1 };
        let plane = if d.s2 == 0 { d.height.checked_mul(row)? } else { d.s2 };
        (plane, f, row)
    } else {
        let px = if d.s1 == 0 { d.channels.checked_mul(f)? } else { d.s1 };
        let row = if d.s2 == 0 { d.width.checked_mul(px)? } else { d.s2 };
        (f, px, row)
    };
    let mut out = Vec::with_capacity(d.width * d.height * d.channels);
    for y in 0..d.height {
        for x in 0..d.width {
            for c in 0..d.channels {
                out.push(
                    y.checked_mul(row)?
                        .checked_add(x.checked_mul(px)?)?
                        .checked_add(c.checked_mul(ch)?)?,
                );
            }
        }
    }
    Some(out)
}

unsafe fn set(filter: *mut gdr_filter, name: &[u8], d: Desc, p: *const f32) -> gdr_error {
    let name = name.as_ptr() as *const c_char;
    if d.planar {
        gdr_filter_set_image_planar(filter, name, p, d.width, d.height, d.channels, d.s1, d.s2)
    } else {
        gdr_filter_set_image(filter, name, p, d.width, d.height, d.channels, d.s1, d.s2)
    }
}

const CANARY: f32 = 1234.5;
const LIMIT: usize = 1 << 22;

fuzz_target!(|data: &[u8]| {
    let Some(d) = decode(data) else { return };
    let offsets = offsets(d);
    // A buffer covering exactly the described elements, when that is a sane size.
    let extent = offsets
        .as_ref()
        .and_then(|o| o.iter().max().map(|m| m + 4))
        .filter(|&e| e <= LIMIT);
    unsafe {
        let mut ctx = ptr::null_mut();
        assert_eq!(gdr_context_new(&mut ctx), gdr_error::GDR_ERROR_NONE);
        gdr_context_set_int(ctx, c"threads".as_ptr(), 1);
        assert_eq!(gdr_context_commit(ctx), gdr_error::GDR_ERROR_NONE);
        let mut filter = ptr::null_mut();
        assert_eq!(
            gdr_filter_new(ctx, c"l2".as_ptr(), &mut filter),
            gdr_error::GDR_ERROR_NONE
        );
        // Three inputs with this layout, each in its own buffer of `extent` bytes (+ canary).
        let words = extent.unwrap_or(64) / 4 + 2 + d.misalign;
        let mut buffers: Vec<Vec<f32>> = (0..3)
            .map(|k| {
                let mut v: Vec<f32> = (0..words).map(|i| ((i * 7 + k) % 13) as f32 * 0.1).collect();
                *v.last_mut().unwrap() = CANARY;
                v
            })
            .collect();
        let base = |v: &mut Vec<f32>| (v.as_mut_ptr() as *mut u8).add(d.misalign) as *const f32;
        let mut accepted = true;
        for (k, name) in [&b"color\0"[..], b"dx\0", b"dy\0"].iter().enumerate() {
            let status = set(filter, name, d, base(&mut buffers[k]));
            match status {
                gdr_error::GDR_ERROR_NONE => {}
                gdr_error::GDR_ERROR_INVALID_IMAGE
                | gdr_error::GDR_ERROR_NULL_POINTER
                | gdr_error::GDR_ERROR_INVALID_ARGUMENT => {
                    accepted = false;
                    break;
                }
                other => panic!("unexpected status {other:?} for {d:?}"),
            }
        }
        if accepted {
            let offsets = offsets.expect("an accepted view is addressable");
            assert!(d.misalign == 0, "accepted a misaligned view {d:?}");
            let distinct: HashSet<usize> = offsets.iter().copied().collect();
            assert_eq!(distinct.len(), offsets.len(), "accepted an overlapping view {d:?}");
            if extent.is_some() {
                let mut out = vec![0.0f32; d.width * d.height * 3];
                let status = gdr_filter_set_image(
                    filter,
                    c"output".as_ptr(),
                    out.as_mut_ptr(),
                    d.width,
                    d.height,
                    3,
                    0,
                    0,
                );
                assert_eq!(status, gdr_error::GDR_ERROR_NONE);
                assert_eq!(gdr_filter_commit(filter), gdr_error::GDR_ERROR_NONE);
                assert_eq!(gdr_filter_execute(filter), gdr_error::GDR_ERROR_NONE);
                assert!(out.iter().all(|v| v.is_finite()));
                for b in &buffers {
                    assert_eq!(*b.last().unwrap(), CANARY, "input written");
                }
            }
        }
        let mut msg = ptr::null();
        gdr_get_error(&mut msg);
        gdr_filter_release(&mut filter);
        gdr_context_release(&mut ctx);
    }
});
