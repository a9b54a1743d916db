//! GradNet's output convolution (32 -> 1 channels, 3 x 3, fp32), applied here to the int8
//! graph's last quantised tensor instead of inside ONNX Runtime.
//!
//! `onnx/gradnet_int8.onnx` ends at `phases`: the last decoder layer's four output phases at half
//! resolution, `N x 4C x h x w` uint8, channel `(2 a + b) C + c` holding channel `c` at the
//! full-resolution rows of parity `a` and columns of parity `b`. The convolution's weights, bias
//! and that tensor's scale and zero point are in the graph's metadata (`output_layer.*`, written by
//! `onnx/gdrecon_py/output_layer.py`, which is also the reference the parity tests hold this
//! to). ONNX Runtime ran the layer as a dequantisation, a reorder to its blocked layout, a
//! convolution padding its 4 phase outputs to 16 and a reorder back: 73 of 367 ms of one
//! 1280 x 720 channel. Here each output row is 6 multiply-adds per weight over contiguous rows
//! of the phases, for the same values up to the order of the fp32 sums.

use ndarray::{Array2, ArrayView3};
use rayon::prelude::*;

use crate::error::{Error, Result};

/// Metadata keys: `output_layer.<name>`.
const PREFIX: &str = "output_layer.";

/// The output convolution: `relu(bias + sum_{c,r,s} weight[c][r][s] v_c(y + r - 1, x + s - 1))`
/// over the dequantised full-resolution tensor `v = scale (q - zero_point)`, zero outside.
#[derive(Debug)]
pub(crate) struct OutputLayer {
    /// `weight[c][r][s]`.
    weight: Vec<[[f32; 3]; 3]>,
    bias: f32,
    scale: f32,
    zero_point: f32,
}

impl OutputLayer {
    /// The layer a graph's metadata describes (`get`: a metadata value by key), or `None` when
    /// it has none; `origin` names the model in errors.
    pub fn from_metadata(
        get: impl Fn(&str) -> Option<String>,
        origin: &str,
    ) -> Result<Option<Self>> {
        let Some(weight) = get(&format!("{PREFIX}weight")) else {
            return Ok(None);
        };
        let bad =
            |what: &str| Error::Model(format!("{origin}: metadata {PREFIX}{what} is malformed"));
        let floats = |text: &str, what: &str| -> Result<Vec<f32>> {
            text.split_whitespace()
                .map(|v| {
                    v.parse::<f32>()
                        .ok()
                        .filter(|v| v.is_finite())
                        .ok_or_else(|| bad(what))
                })
                .collect()
        };
        /// A metadata value that is one number of type `T`.
        fn value<T: std::str::FromStr>(text: Option<String>) -> Option<T> {
            text?.trim().parse().ok()
        }
        let key = |what: &str| get(&format!("{PREFIX}{what}"));
        let one = |what: &str| -> Result<f32> {
            value::<f32>(key(what))
                .filter(|v| v.is_finite())
                .ok_or_else(|| bad(what))
        };
        let channels = value::<usize>(key("channels"))
            .filter(|&c| c > 0)
            .ok_or_else(|| bad("channels"))?;
        let w = floats(&weight, "weight")?;
        if Some(w.len()) != channels.checked_mul(9) {
            return Err(bad("weight"));
        }
        let zero_point = value::<u8>(key("zero_point")).ok_or_else(|| bad("zero_point"))?;
        let scale = one("scale")?;
        if scale <= 0.0 {
            return Err(bad("scale"));
        }
        let weight = w
            .chunks_exact(9)
            .map(|k| std::array::from_fn(|r| std::array::from_fn(|s| k[3 * r + s])))
            .collect();
        Ok(Some(OutputLayer {
            weight,
            bias: one("bias")?,
            scale,
            zero_point: f32::from(zero_point),
        }))
    }

    /// Channels of the full-resolution tensor the layer reads (its phases have 4 times as
    /// many).
    pub fn channels(&self) -> usize {
        self.weight.len()
    }

    /// The layer over one item's phases (`4C x h x w`) into `out`, resized to `2h x 2w`.
    pub fn apply(&self, phases: ArrayView3<'_, u8>, out: &mut Array2<f32>) -> Result<()> {
        let (c4, h, w) = phases.dim();
        let ch = self.weight.len();
        if c4 != 4 * ch {
            return Err(Error::Runtime(format!(
                "GradNet inference: the graph returned {c4} phase channels, its output layer reads {}",
                4 * ch
            )));
        }
        let phases = phases.as_standard_layout();
        let q = phases.as_slice().expect("standard layout");
        let plane = |k: usize, row: usize| &q[(k * h + row) * w..][..w];
        if out.dim() != (2 * h, 2 * w) {
            *out = Array2::zeros((2 * h, 2 * w));
        }
        if w == 0 {
            return Ok(());
        }
        let rows = out.as_slice_mut().expect("standard layout");
        rows.par_chunks_mut(2 * w).enumerate().for_each_init(
            || {
                (
                    vec![0.0f32; w],
                    vec![0.0f32; w],
                    vec![0.0f32; w + 2],
                    vec![0.0f32; w + 2],
                )
            },
            |(even, odd, p0, p1), (y, row)| {
                even.fill(0.0);
                odd.fill(0.0);
                for r in 0..3 {
                    // The full-resolution row this tap reads; zero outside the frame.
                    let Some(yr) = (y + r).checked_sub(1).filter(|&yr| yr < 2 * h) else {
                        continue;
                    };
                    let (parity, half) = (yr % 2, yr / 2);
                    for (c, k) in self.weight.iter().enumerate() {
                        // Columns of even (p0) and odd (p1) parity, shifted by one: p[n + 1]
                        // is half-resolution column n, p[0] and p[w + 1] are the zero border.
                        dequantise(
                            &mut p0[1..=w],
                            plane(2 * parity * ch + c, half),
                            self.zero_point,
                        );
                        dequantise(
                            &mut p1[1..=w],
                            plane((2 * parity + 1) * ch + c, half),
                            self.zero_point,
                        );
                        accumulate(even, odd, p0, p1, k[r]);
                    }
                }
                let (bias, scale) = (self.bias, self.scale);
                for ((pair, &e), &o) in row.chunks_exact_mut(2).zip(&*even).zip(&*odd) {
                    pair[0] = (bias + scale * e).max(0.0);
                    pair[1] = (bias + scale * o).max(0.0);
                }
            },
        );
        Ok(())
    }
}

/// `out = q - zero_point`, as f32.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn dequantise(out: &mut [f32], q: &[u8], zero_point: f32) {
    for (o, &v) in out.iter_mut().zip(q) {
        *o = f32::from(v) - zero_point;
    }
}

/// One kernel row `k` over a row pair of phases (`p0`, `p1`: even and odd columns, padded by
/// one zero each side): even output column `2n` reads full-resolution columns `2n - 1, 2n,
/// 2n + 1`, odd column `2n + 1` reads `2n, 2n + 1, 2n + 2`.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn accumulate(even: &mut [f32], odd: &mut [f32], p0: &[f32], p1: &[f32], k: [f32; 3]) {
    let n = even.len();
    let (odd, p0, p1) = (&mut odd[..n], &p0[..n + 2], &p1[..n + 2]);
    for i in 0..n {
        even[i] += k[0] * p1[i] + k[1] * p0[i + 1] + k[2] * p1[i + 1];
        odd[i] += k[0] * p0[i + 1] + k[1] * p1[i + 1] + k[2] * p0[i + 2];
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    /// Against the definition: the phases interleaved into the full-resolution tensor, a
    /// direct 3 x 3 convolution with zero padding, in f64.
    #[test]
    fn matches_a_direct_convolution_of_the_interleaved_phases() {
        let (ch, h, w) = (3, 5, 7);
        let mut seed = 7u32;
        let mut next = || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            seed >> 8
        };
        let weight: Vec<f32> = (0..9 * ch)
            .map(|_| (next() % 2001) as f32 / 1000.0 - 1.0)
            .collect();
        let text = weight
            .iter()
            .map(|v| v.to_string())
            .collect::<Vec<_>>()
            .join(" ");
        let meta = |key: &str| match key.strip_prefix(PREFIX)? {
            "weight" => Some(text.clone()),
            "bias" => Some("-0.25".into()),
            "scale" => Some("0.0125".into()),
            "zero_point" => Some("120".into()),
            "channels" => Some(ch.to_string()),
            _ => None,
        };
        let layer = OutputLayer::from_metadata(meta, "test").unwrap().unwrap();
        let q = Array3::from_shape_fn((4 * ch, h, w), |_| (next() % 256) as u8);
        let mut out = Array2::from_elem((1, 1), f32::NAN);
        layer.apply(q.view(), &mut out).unwrap();
        let v = |c: usize, y: isize, x: isize| -> f64 {
            if y < 0 || x < 0 || y >= 2 * h as isize || x >= 2 * w as isize {
                return 0.0;
            }
            let (y, x) = (y as usize, x as usize);
            let k = 2 * (y % 2) + x % 2;
            0.0125 * (f64::from(q[[k * ch + c, y / 2, x / 2]]) - 120.0)
        };
        let mut positive = 0;
        for y in 0..2 * h {
            for x in 0..2 * w {
                let mut want = -0.25f64;
                for c in 0..ch {
                    for r in 0..3 {
                        for s in 0..3 {
                            let (yy, xx) =
                                (y as isize + r as isize - 1, x as isize + s as isize - 1);
                            want += f64::from(weight[9 * c + 3 * r + s]) * v(c, yy, xx);
                        }
                    }
                }
                let want = want.max(0.0);
                positive += usize::from(want > 0.0);
                let got = f64::from(out[[y, x]]);
                assert!(
                    (got - want).abs() <= 1e-5 * (1.0 + want.abs()),
                    "({y}, {x}): {got} vs {want}"
                );
            }
        }
        assert!(
            positive > 10 && positive < 4 * h * w - 10,
            "both sides of the ReLU: {positive}"
        );
    }

    /// Metadata of a 1-channel layer (weights all 1, every other value 1) with `over` replacing
    /// values by key.
    fn metadata<'a>(over: &'a [(&'a str, &'a str)]) -> impl Fn(&str) -> Option<String> + 'a {
        move |key: &str| {
            let key = key.strip_prefix(PREFIX)?;
            match over.iter().find(|(k, _)| *k == key) {
                Some((_, v)) => Some(v.to_string()),
                None if key == "weight" => Some(["1"; 9].join(" ")),
                None => Some("1".into()),
            }
        }
    }

    #[test]
    fn malformed_metadata_is_refused_and_absent_metadata_is_none() {
        assert!(OutputLayer::from_metadata(|_| None, "m").unwrap().is_none());
        let short = metadata(&[
            ("weight", "1 2 3"),
            ("bias", "0"),
            ("scale", "0"),
            ("zero_point", "0"),
        ]);
        let err = OutputLayer::from_metadata(short, "m.onnx")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("m.onnx") && err.contains("output_layer.weight"),
            "{err}"
        );
        let nan = ["NaN"; 9].join(" ");
        assert!(OutputLayer::from_metadata(metadata(&[("weight", &nan)]), "m").is_err());
        for (key, value) in [
            ("channels", "1e38"),
            ("channels", "1.5"),
            ("zero_point", "256"),
            ("scale", "-1"),
        ] {
            let err = OutputLayer::from_metadata(metadata(&[(key, value)]), "m")
                .unwrap_err()
                .to_string();
            assert!(
                err.contains(&format!("output_layer.{key}")),
                "{key}={value}: {err}"
            );
        }
        // Phases of the wrong channel count are refused, not read out of bounds.
        let layer = OutputLayer::from_metadata(metadata(&[]), "m")
            .unwrap()
            .unwrap();
        let mut out = Array2::zeros((0, 0));
        assert!(layer
            .apply(Array3::zeros((8, 2, 2)).view(), &mut out)
            .is_err());
    }
}
