//! The frames `bench` times: loading, naming (`<scene>_<N>spp.exr`) and resizing.

use std::path::Path;

use gdrecon::{synth, Frame, FrameBuilder, Image, Layer, Policy};

/// A frame with the names the report groups it by.
pub struct BenchFrame {
    /// Display name: the file name, or `synthetic WxH`.
    pub name: String,
    /// Scene: the file name's `<scene>` part, else its stem.
    pub scene: String,
    /// Samples per pixel: from the file name, else from the frame.
    pub spp: Option<f32>,
    /// Size factor against the frame as read (1 for the original).
    pub scale: f64,
    /// The validated frame.
    pub frame: Frame,
    /// The file it was read from (None for the synthetic frame).
    pub path: Option<std::path::PathBuf>,
    /// Made by [`synthetic`]: `--scales` renders it anew at each size (the same scene with
    /// more or fewer pixels) instead of resampling it.
    pub synthetic: bool,
}

/// Reads a bundle and names it from its file name.
pub fn load(path: &Path) -> gdrecon::Result<BenchFrame> {
    let frame = crate::load_frame(path, Policy::Replace, None)?;
    let file = path.file_name().map_or_else(
        || path.display().to_string(),
        |f| f.to_string_lossy().into(),
    );
    let (scene, name_spp) = parse_name(&file);
    Ok(BenchFrame {
        name: file,
        scene,
        spp: name_spp.or(frame.spp()),
        scale: 1.0,
        frame,
        path: Some(path.to_owned()),
        synthetic: false,
    })
}

/// A synthetic frame of the size `spec` (`WxH`), 16 spp, with its reference.
pub fn synthetic(spec: &str) -> gdrecon::Result<BenchFrame> {
    let (w, h) = parse_size(spec)?;
    synthetic_at((w, h), (w, h), 1.0)
}

/// The synthetic frame named for `named` (its size as asked for), rendered at `size`.
fn synthetic_at(
    named: (usize, usize),
    size: (usize, usize),
    scale: f64,
) -> gdrecon::Result<BenchFrame> {
    synth::check_size(size.0, size.1)?;
    let frame = synth::synthetic_frame(size.0, size.1, 16.0, 1);
    Ok(BenchFrame {
        name: format!("synthetic {}x{}", named.0, named.1),
        scene: "synthetic".to_owned(),
        spp: frame.spp(),
        scale,
        frame,
        path: None,
        synthetic: true,
    })
}

/// Parses `WxH`.
pub fn parse_size(s: &str) -> gdrecon::Result<(usize, usize)> {
    let bad = || gdrecon::Error::InvalidArgument(format!("--synthetic '{s}': expected WxH"));
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    let (w, h) = (w.parse().map_err(|_| bad())?, h.parse().map_err(|_| bad())?);
    if w == 0 || h == 0 {
        return Err(bad());
    }
    Ok((w, h))
}

/// Splits `<scene>_<N>spp.exr` into the scene and N; other names give their stem and no spp.
pub fn parse_name(file: &str) -> (String, Option<f32>) {
    let stem = file.rsplit_once('.').map_or(file, |(s, _)| s);
    let parsed = stem.rsplit_once('_').and_then(|(scene, tail)| {
        let n: f32 = tail.strip_suffix("spp")?.parse().ok()?;
        (!scene.is_empty() && n > 0.0).then(|| (scene.to_owned(), n))
    });
    match parsed {
        Some((scene, n)) => (scene, Some(n)),
        None => (stem.to_owned(), None),
    }
}

/// Parses `--scales` (`0.5,1,2`): positive factors, in the given order.
pub fn parse_scales(list: &str) -> gdrecon::Result<Vec<f64>> {
    let scales = super::variant::split_list(list)
        .map(|s| match s.parse::<f64>() {
            Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
            _ => Err(gdrecon::Error::InvalidArgument(format!(
                "--scales: '{s}' is not a positive factor (expected e.g. 0.5,1,2)"
            ))),
        })
        .collect::<gdrecon::Result<Vec<_>>>()?;
    if scales.is_empty() {
        return Err(gdrecon::Error::InvalidArgument(
            "--scales is empty (expected e.g. 0.5,1,2)".into(),
        ));
    }
    Ok(scales)
}

/// `frame` resized by `scale` (a copy; the original when `scale` is 1).
///
/// The synthetic frame is rendered anew at the new size: resampling it would turn its smooth
/// shapes into blocks of 2 x 2 equal pixels at 2x, a frame no renderer makes, on which the
/// solvers behave differently (at 2560 x 1440 the prior path's Jacobi-preconditioned CG took
/// 3.5x as long on the resampled frame as on the one rendered at that size).
///
/// Every layer of any other frame is resampled nearest-neighbour. The gradients are not
/// resampled but re-derived from the source gradients: `dx` at an output pixel is the sum of
/// the source `dx` between the source columns its pixel and its right neighbour sample (0, 1
/// or more terms), likewise `dy` over rows. So the gradients stay the forward differences of
/// the resampled image the renderer's gradients describe, noise included, and the last column
/// of `dx` and the last row of `dy` are 0 as the frame convention says.
pub fn resized(source: &BenchFrame, scale: f64) -> gdrecon::Result<BenchFrame> {
    let frame = &source.frame;
    let (w, h) = scaled_size(frame.size(), scale)?;
    if source.synthetic {
        return synthetic_at(frame.size(), (w, h), scale);
    }
    let xs = source_index(frame.width(), w);
    let ys = source_index(frame.height(), h);
    let mut builder = FrameBuilder::new().spp(frame.spp());
    for layer in frame.present_layers() {
        let image = frame.layer(layer).expect("present layer");
        let resized = match layer {
            Layer::Dx => summed_dx(image, &xs, &ys),
            Layer::Dy => summed_dy(image, &xs, &ys),
            _ => nearest(image, &xs, &ys),
        };
        builder = builder.image(layer, resized);
    }
    Ok(BenchFrame {
        name: source.name.clone(),
        scene: source.scene.clone(),
        spp: source.spp,
        scale,
        frame: builder.build(Policy::Replace)?,
        path: None,
        synthetic: false,
    })
}

/// The output size for `scale`, at least one pixel.
fn scaled_size((w, h): (usize, usize), scale: f64) -> gdrecon::Result<(usize, usize)> {
    let side = |n: usize| ((n as f64 * scale).round() as usize).max(1);
    let (sw, sh) = (side(w), side(h));
    if sw.saturating_mul(sh) > 1 << 28 {
        return Err(gdrecon::Error::InvalidArgument(format!(
            "--scales {scale}: {w} x {h} would become {sw} x {sh}, too large"
        )));
    }
    Ok((sw, sh))
}

/// For each of `n_out` output samples, the nearest of `n_in` source samples (pixel centres).
fn source_index(n_in: usize, n_out: usize) -> Vec<usize> {
    (0..n_out)
        .map(|i| (((i as f64 + 0.5) * n_in as f64 / n_out as f64) as usize).min(n_in - 1))
        .collect()
}

/// Nearest-neighbour resampling.
fn nearest(image: &Image, xs: &[usize], ys: &[usize]) -> Image {
    Image::from_fn(image.channels(), xs.len(), ys.len(), |(c, x, y)| {
        image.at(c, xs[x], ys[y])
    })
}

/// `dx` of the nearest-resampled image: source `dx` summed from `xs[x]` to `xs[x + 1] - 1`.
fn summed_dx(dx: &Image, xs: &[usize], ys: &[usize]) -> Image {
    Image::from_fn(dx.channels(), xs.len(), ys.len(), |(c, x, y)| {
        match xs.get(x + 1) {
            Some(&next) => (xs[x]..next).map(|k| dx.at(c, k, ys[y])).sum(),
            None => 0.0,
        }
    })
}

/// `dy` of the nearest-resampled image: source `dy` summed from `ys[y]` to `ys[y + 1] - 1`.
fn summed_dy(dy: &Image, xs: &[usize], ys: &[usize]) -> Image {
    Image::from_fn(dy.channels(), xs.len(), ys.len(), |(c, x, y)| {
        match ys.get(y + 1) {
            Some(&next) => (ys[y]..next).map(|k| dy.at(c, xs[x], k)).sum(),
            None => 0.0,
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_give_scene_and_spp() {
        assert_eq!(
            parse_name("cornell_16spp.exr"),
            ("cornell".to_owned(), Some(16.0))
        );
        assert_eq!(
            parse_name("my_scene_4spp.exr"),
            ("my_scene".to_owned(), Some(4.0))
        );
        assert_eq!(parse_name("frame.exr"), ("frame".to_owned(), None));
        assert_eq!(parse_name("a_bspp.exr"), ("a_bspp".to_owned(), None));
    }

    #[test]
    fn the_synthetic_frame_is_rendered_anew_at_each_scale() {
        let source = synthetic("40x30").unwrap();
        for (scale, w, h) in [(2.0, 80, 60), (0.5, 20, 15)] {
            let r = resized(&source, scale).unwrap();
            let native = synth::synthetic_frame(w, h, 16.0, 1);
            for layer in [Layer::Color, Layer::Dx, Layer::Dy, Layer::Reference] {
                let (a, b) = (r.frame.layer(layer).unwrap(), native.layer(layer).unwrap());
                assert_eq!(a.as_slice(), b.as_slice(), "{layer:?} at {scale}");
            }
            assert_eq!((r.name.as_str(), r.scale), ("synthetic 40x30", scale));
        }
    }

    #[test]
    fn resized_gradients_are_forward_differences_of_exact_input() {
        let mut source = synthetic("9x7").unwrap();
        source.synthetic = false;
        // Exact gradients: then the resized ones must be exact too.
        let color = source.frame.color().clone();
        let (dx, dy) = color.forward_differences();
        source.frame = FrameBuilder::new()
            .image(Layer::Color, color)
            .image(Layer::Dx, dx)
            .image(Layer::Dy, dy)
            .build(Policy::Replace)
            .unwrap();
        for scale in [0.5, 2.0, 1.7] {
            let r = resized(&source, scale).unwrap();
            let (ex, ey) = r.frame.color().forward_differences();
            let diff = |a: &Image, b: &Image| {
                a.as_slice()
                    .iter()
                    .zip(b.as_slice())
                    .map(|(p, q)| (p - q).abs())
                    .fold(0.0f32, f32::max)
            };
            assert!(diff(&ex, r.frame.dx()) < 1e-5, "scale {scale}");
            assert!(diff(&ey, r.frame.dy()) < 1e-5, "scale {scale}");
        }
    }
}
