//! `gdr_frame`: a frame bundle read from disk, for callers without an EXR reader.

use std::ffi::c_char;

use super::gdr_error::*;
use super::{c_str, err, gdr_error, guard, out_ptr};
use crate::frame::Layer;
use crate::io::{self, RawBundle};

/// A frame bundle as read from an OpenEXR file, values as stored (opaque, immutable).
pub struct gdr_frame {
    bundle: RawBundle,
}

unsafe fn frame_ref<'a>(frame: *const gdr_frame) -> Result<&'a gdr_frame, super::CapiError> {
    frame
        .as_ref()
        .ok_or_else(|| super::CapiError::new(GDR_ERROR_NULL_POINTER, "frame is NULL"))
}

/// Read the frame bundle (multi-layer OpenEXR) at `path` into `*out`; NULL on failure (`GDR_ERROR_IO`).
///
/// Values are not validated here: the filter that uses the layers applies its policy.
#[no_mangle]
pub unsafe extern "C" fn gdr_frame_read(
    path: *const c_char,
    out: *mut *mut gdr_frame,
) -> gdr_error {
    guard("gdr_frame_read", || {
        let out = out_ptr(out, "out")?;
        *out = std::ptr::null_mut();
        let bundle = io::read_bundle_raw(c_str(path, "path")?)?;
        *out = Box::into_raw(Box::new(gdr_frame { bundle }));
        Ok(())
    })
}

/// Free `*frame` and set `*frame` to NULL (no-op when `*frame` is NULL); layer pointers die with it.
#[no_mangle]
pub unsafe extern "C" fn gdr_frame_release(frame: *mut *mut gdr_frame) -> gdr_error {
    guard("gdr_frame_release", || {
        let slot = out_ptr(frame, "frame")?;
        let raw = std::mem::replace(slot, std::ptr::null_mut());
        if !raw.is_null() {
            drop(Box::from_raw(raw));
        }
        Ok(())
    })
}

/// Write the frame's width, height and samples per pixel (0 when unknown) into the non-NULL arguments.
#[no_mangle]
pub unsafe extern "C" fn gdr_frame_get_info(
    frame: *const gdr_frame,
    width: *mut usize,
    height: *mut usize,
    spp: *mut f32,
) -> gdr_error {
    guard("gdr_frame_get_info", || {
        let b = &frame_ref(frame)?.bundle;
        if let Some(w) = width.as_mut() {
            *w = b.size.0;
        }
        if let Some(h) = height.as_mut() {
            *h = b.size.1;
        }
        if let Some(s) = spp.as_mut() {
            *s = b.spp.unwrap_or(0.0);
        }
        Ok(())
    })
}

/// Point `*data` at layer `name` as packed planar floats (`channels` planes of width x height) and set `*channels`; NULL and 0 when absent.
///
/// Names: `color`, `dx`, `dy`, `variance`, `albedo`, `normal`, `depth`, `reference`. Pass the
/// layer to `gdr_filter_set_image_planar` with 0 strides. Valid until the frame is released.
#[no_mangle]
pub unsafe extern "C" fn gdr_frame_get_layer(
    frame: *const gdr_frame,
    name: *const c_char,
    data: *mut *const f32,
    channels: *mut usize,
) -> gdr_error {
    guard("gdr_frame_get_layer", || {
        let b = &frame_ref(frame)?.bundle;
        let name = c_str(name, "name")?;
        let data = out_ptr(data, "data")?;
        let channels = out_ptr(channels, "channels")?;
        let Some(layer) = Layer::from_name(name) else {
            return err(
                GDR_ERROR_INVALID_ARGUMENT,
                format!("unknown layer '{name}', expected one of: color, dx, dy, variance, albedo, normal, depth, reference"),
            );
        };
        match b.layers.get(&layer) {
            Some(img) => {
                *data = img.as_slice().as_ptr();
                *channels = img.channels();
            }
            None => {
                *data = std::ptr::null();
                *channels = 0;
            }
        }
        Ok(())
    })
}
