//! Arbitrary bytes through the frame-bundle reader: it must return a frame or an error, never
//! panic, and a frame it returns must hold only finite values (Policy::Replace sanitises).
#![no_main]

use gdrecon::io::exr::read_bundle_from_bytes;
use gdrecon::Policy;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(raw) = read_bundle_from_bytes(data) else {
        return;
    };
    let Ok(frame) = raw.into_frame(Policy::Replace) else {
        return;
    };
    for layer in frame.present_layers() {
        let image = frame.layer(layer).expect("present");
        assert!(image.all_finite(), "{layer:?} holds non-finite values after Replace");
        assert_eq!(image.size(), frame.size());
    }
});
