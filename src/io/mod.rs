//! Reading frame bundles and writing results: OpenEXR in and out, PNG previews.

mod blocks;
mod chunks;
mod codec;
pub mod exr;
pub mod png;

pub use self::exr::{
    read_bundle, read_bundle_from_bytes, read_bundle_raw, read_reference, read_rgb, write_bundle,
    write_rgb, RawBundle,
};
pub use self::png::write_png;
