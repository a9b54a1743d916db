//! Tone-mapped 8-bit PNG previews of linear HDR images.
//!
//! The mapping is `srgb(clamp(v * 2^exposure, 0, 1))`: linear radiance scaled by an exposure
//! in stops, clipped, and encoded with the sRGB transfer curve. It is for looking at results,
//! never for measuring them.

use std::io::BufWriter;
use std::path::Path;

use crate::error::{Error, Result};
use crate::image::Image;

/// The sRGB transfer function of a linear value in [0, 1].
fn srgb(v: f32) -> f32 {
    if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// Tone-maps a 3-channel image to interleaved 8-bit sRGB.
pub fn tonemap(image: &Image, exposure: f32) -> Vec<u8> {
    let scale = 2f32.powf(exposure);
    image
        .to_interleaved()
        .into_iter()
        .map(|v| {
            let v = if v.is_finite() { v * scale } else { 0.0 };
            (srgb(v.clamp(0.0, 1.0)) * 255.0 + 0.5) as u8
        })
        .collect()
}

/// Writes a tone-mapped preview of a 3-channel image.
pub fn write_png(path: impl AsRef<Path>, image: &Image, exposure: f32) -> Result<()> {
    let path = path.as_ref();
    if image.channels() != 3 {
        return Err(Error::arg(format!(
            "a PNG preview needs 3 channels, got {}",
            image.channels()
        )));
    }
    let io_err = |source: std::io::Error| Error::Io {
        path: path.to_owned(),
        source,
    };
    let file = std::fs::File::create(path).map_err(io_err)?;
    let mut encoder = png::Encoder::new(
        BufWriter::new(file),
        image.width() as u32,
        image.height() as u32,
    );
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let png_err = |e: png::EncodingError| match e {
        png::EncodingError::IoError(source) => io_err(source),
        other => Error::arg(format!("{}: cannot encode PNG: {other}", path.display())),
    };
    let mut writer = encoder.write_header().map_err(png_err)?;
    writer
        .write_image_data(&tonemap(image, exposure))
        .map_err(png_err)?;
    writer.finish().map_err(png_err)
}
