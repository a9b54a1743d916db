//! GradNet's output convolution (32 -> 1 channels, 3 x 3, fp32), applied here to the int8
//! graph's last quantised tensor instead of inside ONNX Runtime.
//!
//! The deployed int8 graph (`onnx/gradnet_int8_nhwc.onnx`) ends at `phases`: the last decoder
//! layer's four output phases, channels-last, `N x (h + 1) x (w + 1) x 4C` uint8, channels
//! `(2 a + b) C ..` holding the full-resolution rows of parity `a` and columns of parity `b` at
//! rows `a .. a + h`, columns `b .. b + w` (one 2 x 2 convolution with pads 1 computes all four
//! phases; `onnx/gdrecon_py/nhwc.py`, which says why the graph is channels-last). So the
//! full-resolution pixel `(y, x)` is at row `(y + 1) / 2`, column `(x + 1) / 2`, channels
//! `(2 (y % 2) + x % 2) C ..`. The convolution's weights, bias and that tensor's scale and zero
//! point are in the graph's metadata (`output_layer.*`, written by
//! `onnx/gdrecon_py/output_layer.py`, which is also the reference the parity tests hold this
//! to). ONNX Runtime ran the layer as a dequantisation, a reorder to its blocked layout, a
//! convolution padding its 4 phase outputs to 16 and a reorder back: 73 of 367 ms of one
//! 1280 x 720 channel. Here the phases are put channels-first, row by row over every thread (2 %
//! of a 720p GradNet bench's samples), then each output row is 6 multiply-adds per weight over
//! contiguous rows of the phases, for the same values up to the order of the fp32 sums.

use ndarray::{Array2, ArrayView3};
use rayon::prelude::*;

use crate::error::{Error, Result};

/// Metadata keys: `output_layer.<name>`.
const PREFIX: &str = "output_layer.";

/// The `phases` layout this reads (`output_layer.layout`).
const LAYOUT: &str = "nhwc_padded";

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
        let layout = key("layout").unwrap_or_else(|| "nchw".into());
        if layout != LAYOUT {
            return Err(Error::Model(format!(
                "{origin}: its phases are in the layout `{layout}` ({PREFIX}layout); gdrecon \
                 reads `{LAYOUT}`, the deployed graph's: rewrite it with `python -m \
                 gdrecon_py.nhwc --model FILE --out FILE.nhwc.onnx` (onnx/gdrecon_py/nhwc.py)"
            )));
        }
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

    /// The layer over one item's phases (`(h + 1) x (w + 1) x 4C`) into `out`, resized to
    /// `2h x 2w`; `rows` is scratch kept between calls (the phases channels-first).
    pub fn apply(
        &self,
        phases: ArrayView3<'_, u8>,
        rows: &mut Vec<u8>,
        out: &mut Array2<f32>,
    ) -> Result<()> {
        let (h1, w1, c4) = phases.dim();
        let ch = self.weight.len();
        if c4 != 4 * ch || h1 == 0 || w1 == 0 {
            return Err(Error::Runtime(format!(
                "GradNet inference: the graph returned phases of shape {:?}, its output layer reads \
                 (h + 1) x (w + 1) x {}",
                phases.shape(),
                4 * ch
            )));
        }
        let (h, w) = (h1 - 1, w1 - 1);
        if out.dim() != (2 * h, 2 * w) {
            *out = Array2::zeros((2 * h, 2 * w));
        }
        if w == 0 || h == 0 {
            return Ok(());
        }
        let phases = phases.as_standard_layout();
        let q = phases.as_slice().expect("standard layout");
        // Channels-first per half-resolution row: rows[(m 4C + k) w + n] is channel k of phase
        // (a, b) = divmod(k / C, 2) at half-resolution (m, n), read at (m + a, n + b). The
        // convolution below runs along rows; channels-last it would be a dot product per pixel
        // (measured 5x slower, "The deployed graph" in docs/gradnet.md).
        rows.resize(h * c4 * w, 0);
        let stride = w1 * c4;
        rows.par_chunks_mut(c4 * w)
            .enumerate()
            .for_each(|(m, row)| unshuffle(row, &q[m * stride..][..2 * stride], ch));
        let plane = |k: usize, half: usize| &rows[(half * c4 + k) * w..][..w];
        let out_rows = out.as_slice_mut().expect("standard layout");
        out_rows.par_chunks_mut(2 * w).enumerate().for_each_init(
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

/// One half-resolution row `m` of the four phases channels-first (`row`: `4C x w`) from the
/// channels-last rows `m` and `m + 1` of the graph's output (`src`: `2 x (w + 1) x 4C`): in
/// 8 x 8 blocks of bytes (8 columns of 8 channels of one phase; [`transpose8`]) where `C` is a
/// multiple of 8, byte by byte otherwise and for the last `w % 8` columns.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn unshuffle(row: &mut [u8], src: &[u8], ch: usize) {
    let c4 = 4 * ch;
    let w = row.len() / c4;
    let stride = (w + 1) * c4;
    // Where channel k's column 0 is in `src`: phase (a, b) = divmod(k / C, 2) at (a, b).
    let first = |k: usize| ((k / ch) / 2) * stride + ((k / ch) % 2) * c4 + k;
    let blocked = if ch % 8 == 0 { w / 8 * 8 } else { 0 };
    for n0 in (0..blocked).step_by(8) {
        for k0 in (0..c4).step_by(8) {
            let at = first(k0) + n0 * c4;
            let mut block: [u64; 8] = std::array::from_fn(|i| {
                u64::from_le_bytes(src[at + i * c4..][..8].try_into().expect("8 bytes"))
            });
            transpose8(&mut block);
            for (j, bytes) in block.iter().enumerate() {
                row[(k0 + j) * w + n0..][..8].copy_from_slice(&bytes.to_le_bytes());
            }
        }
    }
    for (k, plane) in row.chunks_exact_mut(w).enumerate() {
        let from = &src[first(k)..];
        for (n, v) in plane.iter_mut().enumerate().skip(blocked) {
            *v = from[n * c4];
        }
    }
}

/// Transposes an 8 x 8 matrix of bytes held as 8 little-endian rows: byte `j` of row `i`
/// becomes byte `i` of row `j`. Three rounds swap the off-diagonal halves of 2 x 2, 4 x 4 and
/// 8 x 8 blocks (bytes, byte pairs, byte quadruples).
#[inline(always)]
fn transpose8(m: &mut [u64; 8]) {
    for (shift, mask, pairs) in [
        (
            8,
            0x00ff_00ff_00ff_00ff_u64,
            [(0, 1), (2, 3), (4, 5), (6, 7)],
        ),
        (16, 0x0000_ffff_0000_ffff, [(0, 2), (1, 3), (4, 6), (5, 7)]),
        (32, 0x0000_0000_ffff_ffff, [(0, 4), (1, 5), (2, 6), (3, 7)]),
    ] {
        for (i, j) in pairs {
            let t = ((m[i] >> shift) ^ m[j]) & mask;
            m[j] ^= t;
            m[i] ^= t << shift;
        }
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
    /// direct 3 x 3 convolution with zero padding, in f64, for two shapes with one scratch.
    #[test]
    fn matches_a_direct_convolution_of_the_interleaved_phases() {
        let mut rows = vec![7u8; 5];
        // 3 and 19 channels: byte by byte; 8 and 16: in blocks of 8 columns (and 9 and 3 left)
        for (ch, h, w) in [(3, 5, 7), (19, 4, 6), (8, 3, 17), (16, 2, 8)] {
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
                "layout" => Some(LAYOUT.into()),
                _ => None,
            };
            let layer = OutputLayer::from_metadata(meta, "test").unwrap().unwrap();
            let q = Array3::from_shape_fn((h + 1, w + 1, 4 * ch), |_| (next() % 256) as u8);
            let mut out = Array2::from_elem((1, 1), f32::NAN);
            layer.apply(q.view(), &mut rows, &mut out).unwrap();
            assert_eq!(out.dim(), (2 * h, 2 * w));
            // Full-resolution pixel (y, x) is phase (y % 2, x % 2) at half-resolution (y / 2,
            // x / 2), stored at row y / 2 + y % 2, column x / 2 + x % 2.
            let v = |c: usize, y: isize, x: isize| -> f64 {
                if y < 0 || x < 0 || y >= 2 * h as isize || x >= 2 * w as isize {
                    return 0.0;
                }
                let (y, x) = (y as usize, x as usize);
                let k = 2 * (y % 2) + x % 2;
                let q = q[[y / 2 + y % 2, x / 2 + x % 2, k * ch + c]];
                0.0125 * (f64::from(q) - 120.0)
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
                        "{ch} channels, ({y}, {x}): {got} vs {want}"
                    );
                }
            }
            assert!(
                positive > 10 && positive < 4 * h * w - 10,
                "both sides of the ReLU: {positive}"
            );
        }
    }

    #[test]
    fn transpose8_transposes() {
        let rows: [u64; 8] = std::array::from_fn(|i| {
            u64::from_le_bytes(std::array::from_fn(|j| (16 * i + j) as u8))
        });
        let mut m = rows;
        transpose8(&mut m);
        for (i, row) in rows.iter().enumerate() {
            for (j, column) in m.iter().enumerate() {
                assert_eq!(column.to_le_bytes()[i], row.to_le_bytes()[j], "({i}, {j})");
            }
        }
    }

    /// Metadata of a 1-channel layer (weights all 1, every other value 1) with `over` replacing
    /// values by key.
    fn metadata<'a>(over: &'a [(&'a str, &'a str)]) -> impl Fn(&str) -> Option<String> + 'a {
        move |key: &str| {
            let key = key.strip_prefix(PREFIX)?;
            match over.iter().find(|(k, _)| *k == key) {
                Some((_, v)) => Some(v.to_string()),
                None if key == "weight" => Some(["1"; 9].join(" ")),
                None if key == "layout" => Some(LAYOUT.into()),
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
        // A graph whose phases are in another layout (the canonical QDQ graph's, which says
        // none) is refused with the rewrite that fixes it.
        for layout in [None, Some("nchw")] {
            let meta = |key: &str| match key.strip_prefix(PREFIX) {
                Some("layout") => layout.map(String::from),
                _ => metadata(&[])(key),
            };
            let err = OutputLayer::from_metadata(meta, "m.onnx")
                .unwrap_err()
                .to_string();
            assert!(
                err.contains("m.onnx") && err.contains("gdrecon_py.nhwc"),
                "{err}"
            );
        }
        // Phases of the wrong channel count are refused, not read out of bounds.
        let layer = OutputLayer::from_metadata(metadata(&[]), "m")
            .unwrap()
            .unwrap();
        let mut out = Array2::zeros((0, 0));
        for shape in [(2, 2, 8), (0, 2, 4), (2, 0, 4)] {
            assert!(layer
                .apply(Array3::zeros(shape).view(), &mut Vec::new(), &mut out)
                .is_err());
        }
    }
}
