//! Frame bundles on disk: round trips, the variants docs/CONVENTIONS.md says readers accept, and a
//! clear error for each kind of bad file.

mod common;

use common::*;
use exr::prelude as x;
use exr::prelude::{AttributeValue, FlatSamples, WritableImage};
use gdrecon::{io, Error, Layer, Policy};
use smallvec::SmallVec;

fn tmp() -> tempfile::TempDir {
    tempfile::tempdir().unwrap()
}

#[test]
fn every_layer_round_trips_exactly() {
    let frame = gdrecon::synth::synthetic_frame(23, 17, 4.0, 3);
    // The synthetic frame has every layer but a denoiser's prior: add one.
    let prior = frame.reference().unwrap().clone();
    let frame = with_prior(frame, prior);
    let dir = tmp();
    let path = dir.path().join("bundle.exr");
    io::write_bundle(&path, &frame).unwrap();
    let back = io::read_bundle(&path, Policy::Strict).unwrap();
    assert_eq!(back.spp(), Some(4.0));
    assert_eq!(back.present_layers(), Layer::ALL.to_vec());
    for layer in Layer::ALL {
        assert_eq!(back.layer(layer), frame.layer(layer), "{layer}");
    }
}

#[test]
fn output_rgb_round_trips() {
    let img = test_image(9, 5);
    let dir = tmp();
    let path = dir.path().join("out.exr");
    io::write_rgb(&path, &img).unwrap();
    assert_eq!(io::read_rgb(&path).unwrap(), img);
    // The output really is plain R, G, B channels.
    let raw = x::read_all_flat_layers_from_file(&path).unwrap();
    let names: Vec<String> = raw.layer_data[0]
        .channel_data
        .list
        .iter()
        .map(|c| c.name.to_string())
        .collect();
    assert_eq!(names, ["B", "G", "R"]);
    assert_eq!(
        raw.layer_data[0].encoding.compression,
        x::Compression::ZIP16
    );
}

/// Writes channels `(name, samples)` with the given encoding and attributes.
fn write_custom(
    path: &std::path::Path,
    size: (usize, usize),
    channels: Vec<(&str, FlatSamples)>,
    encoding: x::Encoding,
    spp: Option<AttributeValue>,
) {
    let list: SmallVec<[x::AnyChannel<FlatSamples>; 4]> = channels
        .into_iter()
        .map(|(n, s)| x::AnyChannel::new(n, s))
        .collect();
    let layer = x::Layer::new(
        size,
        x::LayerAttributes::default(),
        encoding,
        x::AnyChannels::sort(list),
    );
    let mut image = x::Image::from_layer(layer);
    if let Some(v) = spp {
        image.attributes.other.insert(x::Text::from("spp"), v);
    }
    image.write().to_file(path).unwrap();
}

/// Writes an uncompressed file whose named channels are all zero.
fn write_zeros(
    path: &std::path::Path,
    size: (usize, usize),
    names: &[&str],
    spp: Option<AttributeValue>,
) {
    let zeros = || FlatSamples::F32(vec![0.0; size.0 * size.1]);
    let channels = names.iter().map(|n| (*n, zeros())).collect();
    write_custom(path, size, channels, x::Encoding::UNCOMPRESSED, spp);
}

fn plane(w: usize, h: usize, f: impl Fn(usize) -> f32) -> Vec<f32> {
    (0..w * h).map(f).collect()
}

#[test]
fn accepts_f16_tiles_piz_lowercase_components_aliases_and_ignores_unknown_layers() {
    let (w, h) = (70, 40);
    let dir = tmp();
    let path = dir.path().join("variant.exr");
    let f16 = |v: Vec<f32>| FlatSamples::F16(v.into_iter().map(half::f16::from_f32).collect());
    let f32s = FlatSamples::F32;
    let channels = vec![
        ("color.r", f16(plane(w, h, |i| (i % 7) as f32 * 0.25))),
        ("color.g", f16(plane(w, h, |_| 0.5))),
        ("color.b", f16(plane(w, h, |_| 1.0))),
        ("dx.R", f32s(plane(w, h, |_| 0.0))),
        ("dx.G", f32s(plane(w, h, |_| 0.0))),
        ("dx.B", f32s(plane(w, h, |_| 0.0))),
        ("dy.R", f32s(plane(w, h, |_| 0.0))),
        ("dy.G", f32s(plane(w, h, |_| 0.0))),
        ("dy.B", f32s(plane(w, h, |_| 0.0))),
        ("nn.X", f32s(plane(w, h, |_| 0.0))),
        ("nn.Y", f32s(plane(w, h, |_| 1.0))),
        ("nn.Z", f32s(plane(w, h, |_| 0.0))),
        ("dd.T", f32s(plane(w, h, |i| i as f32))),
        ("Albedo.R", f32s(plane(w, h, |_| 0.2))),
        ("Albedo.G", f32s(plane(w, h, |_| 0.3))),
        ("Albedo.B", f32s(plane(w, h, |_| 0.4))),
        ("motion.X", f32s(plane(w, h, |_| 9.0))),
        ("extra", f32s(plane(w, h, |_| 9.0))),
    ];
    let encoding = x::Encoding {
        compression: x::Compression::PIZ,
        blocks: x::Blocks::Tiles(x::Vec2(32, 32)),
        line_order: x::LineOrder::Increasing,
    };
    write_custom(
        &path,
        (w, h),
        channels,
        encoding,
        Some(AttributeValue::I32(64)),
    );
    let raw = io::read_bundle_raw(&path).unwrap();
    assert_eq!(raw.spp, Some(64.0));
    assert_eq!(raw.sources[&Layer::Normal], ["nn.X", "nn.Y", "nn.Z"]);
    assert_eq!(raw.sources[&Layer::Depth], ["dd.T"]);
    assert!(
        raw.ignored.contains(&"motion.X".to_owned()) && raw.ignored.contains(&"extra".to_owned())
    );
    let frame = raw.into_frame(Policy::Strict).unwrap();
    assert_eq!(frame.color().at(0, 3, 0), 0.75);
    assert_eq!(frame.depth().unwrap().at(0, 5, 1), (w + 5) as f32);
    assert_eq!(frame.albedo().unwrap().at(2, 0, 0), 0.4);
    assert!(frame.variance().is_none() && frame.reference().is_none());
}

/// `read_bundle` skips the sanitising pass over layers it found clean while decoding them; the
/// frame must be the one a full pass gives (`read_bundle_raw` + `into_frame`): the same values
/// bit for bit, the same counts, the same refusal in strict mode. Each case puts one kind of
/// value in one layer, in files whose blocks take each decoding path (ZIP and RLE, split;
/// uncompressed; PIZ through the `exr` crate) and in f32 and f16 colour.
#[test]
fn values_found_clean_while_reading_give_the_sanitised_frame() {
    let (w, h) = (37, 21); // two ZIP blocks, the second partial
    let at = w * 16 + 5; // in the second block
                         // (what, layer's channel, value): colour's brightest value is 1, so the gradients' bound
                         // is 64.
    let cases: [(&str, &str, f32); 11] = [
        ("clean", "", 0.0),
        ("NaN gradient", "dx.G", f32::NAN),
        ("negative colour", "color.R", -1.0),
        ("negative zero colour", "color.B", -0.0),
        ("infinite variance", "variance.G", f32::INFINITY),
        ("negative variance", "variance.B", -0.5),
        ("negative normal", "normal.X", -2.0),
        ("implausible gradient", "dy.B", 64.5),
        ("gradient at the bound", "dy.R", -64.0),
        ("absurd gradient", "dx.R", -1e30),
        ("NaN colour", "color.G", f32::NAN),
    ];
    let layers = ["color", "dx", "dy", "variance", "normal"];
    let components = |layer| match layer {
        "normal" => ["X", "Y", "Z"],
        _ => ["R", "G", "B"],
    };
    let codecs = [
        x::Compression::ZIP16,
        x::Compression::RLE,
        x::Compression::Uncompressed,
        x::Compression::PIZ,
    ];
    let dir = tmp();
    let path = dir.path().join("values.exr");
    for (what, poisoned, value) in cases {
        for (codec, half) in codecs.into_iter().flat_map(|c| [(c, false), (c, true)]) {
            let mut channels = Vec::new();
            for layer in layers {
                for (k, c) in components(layer).into_iter().enumerate() {
                    let name = format!("{layer}.{c}");
                    let mut v = plane(w, h, |i| match layer {
                        "color" => ((i * 7 + k) % 11) as f32 / 10.0,
                        "dx" | "dy" => ((i % 13) as f32 - 6.0) * 0.5,
                        _ => (i % 5) as f32 * 0.25,
                    });
                    if name == poisoned {
                        v[at] = value;
                    }
                    let samples = if half && layer == "color" {
                        FlatSamples::F16(v.into_iter().map(half::f16::from_f32).collect())
                    } else {
                        FlatSamples::F32(v)
                    };
                    channels.push((name, samples));
                }
            }
            let named = channels
                .iter()
                .map(|(n, s)| (n.as_str(), s.clone()))
                .collect();
            let encoding = x::Encoding {
                compression: codec,
                blocks: x::Blocks::ScanLines,
                line_order: x::LineOrder::Increasing,
            };
            write_custom(
                &path,
                (w, h),
                named,
                encoding,
                Some(AttributeValue::F32(4.0)),
            );
            for policy in [Policy::Replace, Policy::Strict] {
                let case = format!("{what}, {codec:?}, f16 colour {half}, {policy:?}");
                let read = io::read_bundle(&path, policy);
                let passed = io::read_bundle_raw(&path).unwrap().into_frame(policy);
                match (read, passed) {
                    (Ok(read), Ok(passed)) => {
                        assert_eq!(read.sanitized(), passed.sanitized(), "{case}");
                        for layer in passed.present_layers() {
                            let bits = |f: &gdrecon::Frame| -> Vec<u32> {
                                let img = f.layer(layer).unwrap().as_slice();
                                img.iter().map(|v| v.to_bits()).collect()
                            };
                            assert_eq!(bits(&read), bits(&passed), "{case}: {layer}");
                        }
                    }
                    (Err(read), Err(passed)) => {
                        assert_eq!(read.to_string(), passed.to_string(), "{case}")
                    }
                    (read, passed) => panic!("{case}: {read:?} against {passed:?}"),
                }
            }
        }
    }
    // The cases mean what they say: a full pass replaces what each poisons (or keeps it).
    let replaced = |what: &str| {
        let (_, name, value) = cases.iter().find(|c| c.0 == what).unwrap();
        let mut channels = Vec::new();
        for layer in layers {
            for c in components(layer) {
                let n = format!("{layer}.{c}");
                let mut v = plane(w, h, |_| 0.5);
                if n == *name {
                    v[at] = *value;
                }
                channels.push((n, FlatSamples::F32(v)));
            }
        }
        let named = channels
            .iter()
            .map(|(n, s)| (n.as_str(), s.clone()))
            .collect();
        write_custom(&path, (w, h), named, x::Encoding::FAST_LOSSLESS, None);
        io::read_bundle(&path, Policy::Replace)
            .unwrap()
            .sanitized()
            .total()
    };
    assert_eq!(replaced("clean"), 0);
    assert_eq!(replaced("negative normal"), 0);
    assert_eq!(replaced("negative zero colour"), 0);
    // Colour 0.5 everywhere: the bound is 32, so 64.5 and -64 are both implausible here.
    for what in [
        "NaN gradient",
        "negative colour",
        "implausible gradient",
        "absurd gradient",
    ] {
        assert_eq!(replaced(what), 1, "{what}");
    }
}

#[test]
fn spp_attribute_that_is_not_positive_is_reported_as_unknown() {
    let dir = tmp();
    let path = dir.path().join("spp0.exr");
    let ch = [
        "color.R", "color.G", "color.B", "dx.R", "dx.G", "dx.B", "dy.R", "dy.G", "dy.B",
    ];
    write_zeros(&path, (2, 2), &ch, Some(AttributeValue::F32(0.0)));
    let raw = io::read_bundle_raw(&path).unwrap();
    assert_eq!(raw.spp, None);
    assert!(raw.warnings[0].contains("spp = 0"), "{:?}", raw.warnings);
}

fn exr_message(e: Error) -> String {
    match e {
        Error::Exr { message, .. } => message,
        other => panic!("expected an EXR error, got {other:?}"),
    }
}

#[test]
fn missing_file_is_an_io_error_naming_the_path() {
    let e = io::read_bundle("/nonexistent/frame.exr", Policy::Replace).unwrap_err();
    assert!(
        matches!(e, Error::Io { .. }) && e.to_string().contains("/nonexistent/frame.exr"),
        "{e}"
    );
}

#[test]
fn non_exr_data_is_named_as_such() {
    let dir = tmp();
    let path = dir.path().join("image.exr");
    std::fs::write(&path, b"\x89PNG\r\n\x1a\n not an exr at all, just bytes").unwrap();
    let e = io::read_bundle(&path, Policy::Replace).unwrap_err();
    assert!(e.to_string().contains("image.exr"), "{e}");
    assert!(exr_message(e).contains("not an OpenEXR file"));
}

#[test]
fn truncated_file_is_an_error_not_a_panic() {
    let frame = gdrecon::synth::synthetic_frame(16, 16, 4.0, 1);
    let dir = tmp();
    let path = dir.path().join("full.exr");
    io::write_bundle(&path, &frame).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    for cut in [8, 100, bytes.len() / 2, bytes.len() - 10] {
        assert!(
            io::read_bundle_from_bytes(&bytes[..cut]).is_err(),
            "cut at {cut}"
        );
    }
}

#[test]
fn missing_required_layer_in_a_file_names_file_and_layer() {
    let dir = tmp();
    let path = dir.path().join("nody.exr");
    let ch = ["color.R", "color.G", "color.B", "dx.R", "dx.G", "dx.B"];
    write_zeros(&path, (3, 2), &ch, None);
    let e = io::read_bundle(&path, Policy::Replace).unwrap_err();
    let s = e.to_string();
    assert!(
        matches!(e, Error::InvalidInput(_))
            && s.contains("nody.exr")
            && s.contains("'dy'")
            && s.contains("dy.R"),
        "{s}"
    );
}

#[test]
fn incomplete_layer_names_the_missing_channels() {
    let dir = tmp();
    let path = dir.path().join("partial.exr");
    let ch = [
        "color.R", "color.G", "dx.R", "dx.G", "dx.B", "dy.R", "dy.G", "dy.B",
    ];
    write_zeros(&path, (3, 2), &ch, None);
    let m = exr_message(io::read_bundle(&path, Policy::Replace).unwrap_err());
    assert!(
        m.contains("'color' needs channels color.R, color.G, color.B"),
        "{m}"
    );
}

#[test]
fn parts_of_different_sizes_are_refused() {
    let dir = tmp();
    let path = dir.path().join("parts.exr");
    let part = |name: &str, w: usize, h: usize| {
        let list: SmallVec<[x::AnyChannel<FlatSamples>; 4]> = ["B", "G", "R"]
            .iter()
            .map(|c| x::AnyChannel::new(*c, FlatSamples::F32(vec![0.0; w * h])))
            .collect();
        x::Layer::new(
            (w, h),
            x::LayerAttributes::named(name),
            x::Encoding::UNCOMPRESSED,
            x::AnyChannels::sort(list),
        )
    };
    let image = x::Image::from_layers(
        x::ImageAttributes::new(x::IntegerBounds::from_dimensions((4, 4))),
        smallvec::smallvec![part("color", 4, 4), part("dx", 4, 4), part("dy", 3, 4)],
    );
    image.write().to_file(&path).unwrap();
    let m = exr_message(io::read_bundle(&path, Policy::Replace).unwrap_err());
    assert!(m.contains("part 'dy' is 3 x 4"), "{m}");
    // The same layout with equal sizes reads, layer names coming from the part names.
    let image = x::Image::from_layers(
        x::ImageAttributes::new(x::IntegerBounds::from_dimensions((4, 4))),
        smallvec::smallvec![part("color", 4, 4), part("dx", 4, 4), part("dy", 4, 4)],
    );
    image.write().to_file(&path).unwrap();
    assert!(io::read_bundle(&path, Policy::Strict).is_ok());
}

#[test]
fn png_preview_is_written() {
    let dir = tmp();
    let path = dir.path().join("p.png");
    io::write_png(&path, &test_image(8, 4), 0.0).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    assert_eq!(&bytes[1..4], b"PNG");
}

/// Found by fuzzing: a header declaring an enormous data window in a tiny file made the EXR
/// crate allocate whatever it declared. It is refused before decoding.
#[test]
fn absurd_declared_size_is_refused_before_allocating() {
    let bytes = std::fs::read(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/fixtures/exr/oom_declared_size.exr"),
    )
    .unwrap();
    let Err(err) = gdrecon::io::exr::read_bundle_from_bytes(&bytes) else {
        panic!("a 4 KB file declaring 283 GB was accepted");
    };
    let err = err.to_string();
    assert!(
        err.contains("refusing to allocate") || err.contains("damaged"),
        "{err}"
    );
}

#[test]
fn htj2k_is_refused_before_its_decoder_allocates() {
    // A 1 KB file found by fuzzing: HTJ2K-compressed, declaring 46 MB of samples; exr 1.74's
    // decoder took 2 GB on it before failing.
    let bytes = include_bytes!("fixtures/exr/htj2k_1kb_declares_46mb.exr");
    let err = io::exr::read_bundle_from_bytes(bytes)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("not supported") && err.contains("j2k") && err.contains("ZIP"),
        "{err}"
    );
}

/// Inside a context's pool, blocks are compressed and decompressed in parallel: the file written
/// is byte for byte the single-threaded one, and reading gives the same frame, for ZIP scan
/// lines (our writer, 32 blocks: three batches of up to 4 a thread) and for f16 PIZ tiles (the
/// `exr` crate's writer).
#[test]
fn parallel_blocks_give_the_single_threaded_result() {
    let context = gdrecon::Context::new(gdrecon::ContextOptions::with_threads(Some(3))).unwrap();
    let dir = tmp();
    let frame = gdrecon::synth::synthetic_frame(203, 497, 16.0, 5);
    let (one, many) = (dir.path().join("one.exr"), dir.path().join("many.exr"));
    io::write_bundle(&one, &frame).unwrap();
    context.install(|| io::write_bundle(&many, &frame)).unwrap();
    assert_eq!(std::fs::read(&one).unwrap(), std::fs::read(&many).unwrap());
    let back = context
        .install(|| io::read_bundle(&many, Policy::Strict))
        .unwrap();
    for layer in frame.present_layers() {
        assert_eq!(back.layer(layer), frame.layer(layer), "{layer}");
    }

    let (w, h) = (150, 70);
    let tiles = dir.path().join("tiles.exr");
    let f16 = |v: Vec<f32>| FlatSamples::F16(v.into_iter().map(half::f16::from_f32).collect());
    let channels = [
        "color.R", "color.G", "color.B", "dx.R", "dx.G", "dx.B", "dy.R", "dy.G", "dy.B",
    ]
    .iter()
    .enumerate()
    .map(|(k, n)| {
        (
            *n,
            f16(plane(w, h, |i| ((i * (k + 3)) % 11) as f32 * 0.125)),
        )
    })
    .collect();
    let encoding = x::Encoding {
        compression: x::Compression::PIZ,
        blocks: x::Blocks::Tiles(x::Vec2(32, 16)),
        line_order: x::LineOrder::Increasing,
    };
    write_custom(&tiles, (w, h), channels, encoding, None);
    let single = io::read_bundle(&tiles, Policy::Strict).unwrap();
    let parallel = context
        .install(|| io::read_bundle(&tiles, Policy::Strict))
        .unwrap();
    for layer in single.present_layers() {
        assert_eq!(parallel.layer(layer), single.layer(layer), "{layer}");
    }
    assert_eq!(
        single.color().at(1, 149, 69),
        ((69 * 150 + 149) * 4 % 11) as f32 * 0.125
    );
}

/// A block that deflate cannot shrink (random bits) is stored raw, as OpenEXR does; one that
/// it can is compressed; both read back exactly, here and through the `exr` crate's reader.
#[test]
fn incompressible_and_compressible_blocks_round_trip() {
    let dir = tmp();
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut noise = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        f32::from_bits((state as u32 & 0x807f_ffff) | 0x3f00_0000)
    };
    let random = gdrecon::Image::from_fn(3, 64, 40, |_| noise());
    let smooth = gdrecon::Image::from_fn(3, 64, 40, |(c, x, y)| (c + x + y) as f32);
    for (name, img) in [("random", random), ("smooth", smooth)] {
        let path = dir.path().join(format!("{name}.exr"));
        io::write_rgb(&path, &img).unwrap();
        assert_eq!(io::read_rgb(&path).unwrap(), img, "{name}");
        let raw = x::read_all_flat_layers_from_file(&path).unwrap();
        let r = &raw.layer_data[0].channel_data.list[2];
        assert_eq!(r.name.to_string(), "R");
        match &r.sample_data {
            FlatSamples::F32(v) => assert_eq!(v[..], img.as_slice()[..64 * 40], "{name}"),
            other => panic!("{name}: {other:?}"),
        }
    }
    let size = |n: &str| std::fs::metadata(dir.path().join(n)).unwrap().len();
    assert!(
        size("random.exr") > 3 * 64 * 40 * 4,
        "random bits were not stored raw"
    );
    assert!(
        size("smooth.exr") < 3 * 64 * 40 * 4 / 4,
        "a smooth image was not compressed"
    );
}
