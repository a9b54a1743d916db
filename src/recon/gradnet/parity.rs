//! Parity of each native stage with the Python reference, on the fixtures written by
//! `onnx/gdrecon_py/make_fixtures.py` (torch model, numpy pipeline) under `tests/fixtures/gradnet/`.
//! Stated tolerances: pre-processing 1e-6 absolute (same f32 formulas), bias correction 1e-5
//! relative (numpy blurs in f64, we in f32), network 1e-4 absolute against torch; the int8
//! graph 1e-5 absolute against onnxruntime in Python (the same library and kernels: integer
//! sums are exact, so only the fp32 first layers, and the output layer, native here and numpy's
//! there (`output_layer.rs`), can round differently).

use std::path::PathBuf;

use ndarray::{Array3, Array4, ArrayD};
use ndarray_npy::read_npy;

use super::bias;
use super::prep::{self, FeatureNorm, FrameMap, Window};
use crate::frame::Frame;
use crate::image::Image;
use crate::io::exr::read_bundle;
use crate::validate::Policy;

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/gradnet")
        .join(name)
}

fn npy<D: ndarray::Dimension>(name: &str) -> ndarray::Array<f32, D> {
    let a: ArrayD<f32> = read_npy(fixture(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
    a.into_dimensionality::<D>().unwrap()
}

fn frame(crop: &str) -> Frame {
    read_bundle(fixture(&format!("{crop}.exr")), Policy::Replace).unwrap()
}

/// The whole padded frame as one window, prepared the way a tile is.
fn prepared(frame: &Frame) -> (Array4<f32>, Array4<f32>) {
    let map = FrameMap::new(frame.width(), frame.height());
    let (hp, wp) = (map.y.padded_len(), map.x.padded_len());
    let win = Window {
        y0: 0,
        x0: 0,
        h: hp,
        w: wp,
    };
    let mut data = Array4::zeros((3, 8, hp, wp));
    let mut grad = Array4::zeros((3, 2, hp, wp));
    let norm = FeatureNorm::of(frame).expect("fixture has features");
    for c in 0..3 {
        let feats = data.slice_mut(ndarray::s![c, 1..8, .., ..]).into_slice();
        prep::fill_features(frame, norm, map, win, feats.expect("contiguous"));
        let (gx, gy) = grad.multi_slice_mut((ndarray::s![c, 0, .., ..], ndarray::s![c, 1, .., ..]));
        let colour = data.slice_mut(ndarray::s![c, 0, .., ..]);
        prep::fill_channel(frame, c, map, win, colour, gx, gy);
    }
    (data, grad)
}

fn max_abs_diff<D: ndarray::Dimension>(
    a: &ndarray::Array<f32, D>,
    b: &ndarray::Array<f32, D>,
) -> f32 {
    assert_eq!(a.shape(), b.shape());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
fn preprocessing_matches_numpy() {
    for crop in ["crop_a", "crop_b"] {
        let (data, grad) = prepared(&frame(crop));
        let want_data: Array4<f32> = npy(&format!("{crop}_data.npy"));
        let want_grad: Array4<f32> = npy(&format!("{crop}_grad.npy"));
        let (dd, dg) = (
            max_abs_diff(&data, &want_data),
            max_abs_diff(&grad, &want_grad),
        );
        assert!(dd < 1e-6 && dg < 1e-6, "{crop}: data {dd:e}, grad {dg:e}");
    }
}

#[test]
fn bias_correction_matches_numpy() {
    let hwc = |a: Array3<f32>| Image::from_hwc(a.view());
    let mut out = hwc(npy("bias_out.npy"));
    let color = hwc(npy("bias_color.npy"));
    let want = hwc(npy("bias_corrected.npy"));
    bias::correct(&mut out, &color, None).unwrap();
    for (g, w) in out.as_slice().iter().zip(want.as_slice()) {
        assert!((g - w).abs() <= 1e-5 * w.abs().max(1e-3), "{g} vs {w}");
    }
}

#[cfg(all(feature = "gradnet", feature = "embed-model"))]
#[test]
fn network_matches_torch() {
    network_matches(super::model::ModelVariant::Full, "torch", 1e-4);
}

#[cfg(all(feature = "gradnet", feature = "embed-model"))]
#[test]
fn int8_network_matches_onnxruntime_in_python() {
    network_matches(super::model::ModelVariant::FullInt8, "int8_net", 1e-5);
}

/// The embedded `variant` on the crops' prepared inputs, one channel at a time, against
/// `<crop>_<suffix>.npy`, to `tol` absolute (compressed domain).
#[cfg(all(feature = "gradnet", feature = "embed-model"))]
fn network_matches(variant: super::model::ModelVariant, suffix: &str, tol: f32) {
    use super::model::embedded;
    use super::net::Net;
    use super::runtime::runtime;
    use crate::progress::Progress;

    let rt = runtime(None).expect("ONNX Runtime (run `bash onnx/setup.sh`)");
    let mut net = Net::new(&rt.env, &embedded(variant).unwrap(), 2).unwrap();
    for crop in ["crop_a", "crop_b"] {
        let data: Array4<f32> = npy(&format!("{crop}_data.npy"));
        let grad: Array4<f32> = npy(&format!("{crop}_grad.npy"));
        let want: Array4<f32> = npy(&format!("{crop}_{suffix}.npy"));
        for c in 0..3 {
            let sl = ndarray::s![c..c + 1, .., .., ..];
            let mut worst = 0.0f32;
            net.run(data.slice(sl), grad.slice(sl), &Progress::none(), |y| {
                let w = want.slice(ndarray::s![c, 0, .., ..]);
                worst = y
                    .iter()
                    .zip(w)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f32::max);
            })
            .unwrap();
            println!("{variant:?} {crop} channel {c}: max |rust - {suffix}| = {worst:e}");
            assert!(
                worst < tol,
                "{crop} channel {c}: max |rust - {suffix}| = {worst:e}"
            );
        }
    }
}
