//! The bad-input policy: what happens to NaN, Inf and negative values.
//!
//! Gradient-domain renderers produce them (a failed shift, a division by a vanishing pdf), and
//! one NaN spreads through any global solve, so no bad value ever reaches a method:
//! - non-finite values (NaN, +Inf, -Inf) in any layer become 0;
//! - negative values in colour, variance and reference become 0 (gradients and normals are
//!   signed by nature and are left alone);
//! - implausible gradients become 0: a gradient is a difference of neighbouring colour values,
//!   so one larger than [`GRADIENT_LIMIT`] times the frame's brightest colour value is a broken
//!   estimate, not a feature (absurd but finite gradients, 1e30 or a million times the colour,
//!   were followed by the solvers into outputs of 1e30);
//! - every replacement is counted per layer, and the counts travel with the frame into the
//!   method's report.
//!
//! Under [`Policy::Strict`] the first offending layer is an error instead, naming the layer,
//! the count and the first pixel.

use std::collections::BTreeMap;
use std::fmt;

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::frame::Layer;
use crate::image::Image;

/// What validation does with values it cannot pass on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[non_exhaustive]
pub enum Policy {
    /// Replace bad values by 0 and count them (the default).
    #[default]
    Replace,
    /// Refuse the frame at the first bad value.
    Strict,
}

/// How far a gradient may exceed the frame's brightest colour value before it is implausible.
/// On the project's 244 renders (validation, test, training and guard frames, HDR emitters
/// included) the largest |gradient| is at most 1.82 times the largest colour value; 64 leaves
/// a 35x margin for other renderers' estimators.
pub const GRADIENT_LIMIT: f32 = 64.0;

/// How many values of one layer were replaced.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[non_exhaustive]
pub struct LayerCounts {
    /// NaN or infinite values replaced by 0.
    pub non_finite: u64,
    /// Negative values replaced by 0 (colour, variance, reference only).
    pub negative: u64,
    /// Implausible values replaced by 0 (gradients beyond [`GRADIENT_LIMIT`] times the
    /// brightest colour value only).
    pub implausible: u64,
}

impl LayerCounts {
    /// Total replaced values.
    pub fn total(&self) -> u64 {
        self.non_finite + self.negative + self.implausible
    }
}

/// Per-layer replacement counts of a frame.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
#[non_exhaustive]
pub struct SanitizeReport {
    counts: BTreeMap<Layer, LayerCounts>,
}

impl SanitizeReport {
    pub(crate) fn record(&mut self, layer: Layer, counts: LayerCounts) {
        if counts.total() > 0 {
            self.counts.insert(layer, counts);
        }
    }

    /// Counts for one layer (zero when nothing was replaced).
    pub fn layer(&self, layer: Layer) -> LayerCounts {
        self.counts.get(&layer).copied().unwrap_or_default()
    }

    /// Total replaced values over all layers.
    pub fn total(&self) -> u64 {
        self.counts.values().map(LayerCounts::total).sum()
    }

    /// Layers with replacements, with their counts.
    pub fn iter(&self) -> impl Iterator<Item = (Layer, LayerCounts)> + '_ {
        self.counts.iter().map(|(l, c)| (*l, *c))
    }
}

impl fmt::Display for SanitizeReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.counts.is_empty() {
            return f.write_str("no values replaced");
        }
        let parts: Vec<String> = self
            .iter()
            .map(|(layer, c)| {
                let mut s = format!("{layer}:");
                if c.non_finite > 0 {
                    s += &format!(" {} non-finite", c.non_finite);
                }
                if c.negative > 0 {
                    s += &format!(" {} negative", c.negative);
                }
                if c.implausible > 0 {
                    s += &format!(" {} implausible", c.implausible);
                }
                s
            })
            .collect();
        write!(f, "replaced by 0: {}", parts.join("; "))
    }
}

/// The bound on |gradient| for a frame whose colour (already sanitised) is `color`:
/// [`GRADIENT_LIMIT`] times its brightest value (0 for a black frame: no gradient is then
/// plausible).
pub(crate) fn gradient_bound(color: &Image) -> f32 {
    let brightest = color
        .as_slice()
        .par_iter()
        .copied()
        .reduce(|| 0.0, f32::max);
    GRADIENT_LIMIT * brightest
}

/// What a layer's values are, as far as [`sanitize_layer`] cares, gathered while they were
/// decoded (`io`): a layer this proves clean is not passed over again (at 1280 x 720 that
/// pass was a fifth of the CLI's read).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct Summary {
    /// Whether some value is NaN or infinite.
    non_finite: bool,
    /// Whether some finite value is negative.
    negative: bool,
    /// The largest magnitude of a finite value (0 for none).
    largest: f32,
}

impl Summary {
    /// Adds `values` to the summary.
    pub(crate) fn add(&mut self, values: &[f32]) {
        let (top, largest, negative) = scan_bits(values);
        self.non_finite |= top >= INFINITY_BITS;
        self.negative |= negative;
        self.largest = self.largest.max(f32::from_bits(largest));
    }

    /// Whether [`sanitize_layer`] would replace nothing in a `layer` holding these values,
    /// under the gradient `bound` (see [`gradient_bound`]) when given.
    pub(crate) fn clean(&self, layer: Layer, bound: Option<f32>) -> bool {
        let replaced = self.non_finite || (self.negative && layer.must_be_nonnegative());
        !replaced && bound.is_none_or(|b| self.largest <= b)
    }

    /// [`gradient_bound`] of a colour layer these values prove clean: its brightest value is
    /// then the largest magnitude.
    pub(crate) fn gradient_bound(&self) -> f32 {
        GRADIENT_LIMIT * self.largest
    }
}

/// The bits of +Inf: a value whose magnitude's bits are at least these is not finite.
const INFINITY_BITS: u32 = 0x7f80_0000;

/// Over `values`' bits: the largest magnitude, the largest finite magnitude, and whether some
/// finite value is negative. On bits, as integer maxima and ors, the loop vectorises (the same
/// rules written on floats, with bools, ran one value at a time); magnitudes of finite floats
/// order as their bits do.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn scan_bits(values: &[f32]) -> (u32, u32, bool) {
    let (mut top, mut largest, mut negative) = (0u32, 0u32, 0u32);
    for &v in values {
        let bits = v.to_bits();
        let magnitude = bits & !(1 << 31);
        let finite = magnitude < INFINITY_BITS;
        top = top.max(magnitude);
        largest = largest.max(if finite { magnitude } else { 0 });
        negative |= u32::from(finite & (magnitude != 0)) & (bits >> 31); // -0.0 is not negative
    }
    (top, largest, negative != 0)
}

/// Checks one layer in place under `policy`, returning what was replaced. `bound`, when given,
/// is the largest plausible magnitude (gradients, see [`gradient_bound`]).
pub(crate) fn sanitize_layer(
    layer: Layer,
    img: &mut Image,
    policy: Policy,
    bound: Option<f32>,
) -> Result<LayerCounts> {
    let no_negatives = layer.must_be_nonnegative();
    let bound = bound.unwrap_or(f32::INFINITY);
    let bad = |v: f32| !v.is_finite() || (no_negatives && v < 0.0) || v.abs() > bound;
    if policy == Policy::Strict {
        if let Some(i) = img.as_slice().par_iter().position_first(|&v| bad(v)) {
            let (w, h) = img.size();
            let (c, y, x) = (i / (w * h), (i / w) % h, i % w);
            let count = img.as_slice().par_iter().filter(|&&v| bad(v)).count();
            let v = img.as_slice()[i];
            let what = if bound.is_finite() {
                format!("non-finite or implausible (|v| > {bound:e}, {GRADIENT_LIMIT} times the brightest colour value)")
            } else if no_negatives {
                "non-finite or negative".to_owned()
            } else {
                "non-finite".to_owned()
            };
            return Err(Error::input(format!(
                "layer '{layer}' holds {count} {what} value(s); first: {v} at pixel ({x}, {y}) \
                 channel {} (strict mode refuses them)",
                layer.components()[c]
            )));
        }
        return Ok(LayerCounts::default());
    }
    let (non_finite, negative, implausible) = img
        .as_mut_slice()
        .par_chunks_mut(1 << 14)
        .map(|chunk| {
            // Branch-free, so that it vectorises (a branch per value ran this pass at a fifth
            // of memory speed: 13 % of the CLI's `l2` run at 720p); each value counts once, as
            // non-finite, else negative, else implausible. Chunks are 2^14 values: u32 counts.
            let (mut nf, mut neg, mut imp) = (0u32, 0u32, 0u32);
            for v in chunk {
                let finite = v.is_finite();
                let negative = finite & no_negatives & (*v < 0.0);
                let implausible = finite & !negative & (v.abs() > bound);
                nf += u32::from(!finite);
                neg += u32::from(negative);
                imp += u32::from(implausible);
                *v = if finite & !negative & !implausible {
                    *v
                } else {
                    0.0
                };
            }
            (u64::from(nf), u64::from(neg), u64::from(imp))
        })
        .reduce(|| (0, 0, 0), |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2));
    Ok(LayerCounts {
        non_finite,
        negative,
        implausible,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The branch-free pass against the rule written as branches, value by value: each bad
    /// value counted once (non-finite before negative before implausible) and set to 0, every
    /// other value kept bit for bit (-0.0 included), across chunk boundaries.
    #[test]
    fn replace_counts_each_value_once_and_keeps_the_rest() {
        let specials = [
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            -1.0,
            -0.0,
            0.0,
            5.0,
            -5.0,
            2.5e3,
            -2.5e3,
            f32::MIN_POSITIVE,
        ];
        let bound = 1e3;
        for layer in [Layer::Color, Layer::Dx] {
            // Three planes of 3 x 7000 values: more than one 2^14 chunk, a ragged last one.
            let mut img = Image::from_fn(3, 7000, 3, |(c, x, y)| {
                specials[(c * 31 + x * 7 + y * 3) % specials.len()]
            });
            let before = img.as_slice().to_vec();
            let got = sanitize_layer(layer, &mut img, Policy::Replace, Some(bound)).unwrap();
            let mut want = LayerCounts::default();
            for (&v, &out) in before.iter().zip(img.as_slice()) {
                let replaced = if !v.is_finite() {
                    want.non_finite += 1;
                    true
                } else if layer.must_be_nonnegative() && v < 0.0 {
                    want.negative += 1;
                    true
                } else if v.abs() > bound {
                    want.implausible += 1;
                    true
                } else {
                    false
                };
                let expected = if replaced { 0.0 } else { v };
                assert_eq!(
                    out.to_bits(),
                    expected.to_bits(),
                    "{layer}: {v} became {out}"
                );
            }
            assert_eq!(
                (got.non_finite, got.negative, got.implausible),
                (want.non_finite, want.negative, want.implausible),
                "{layer}"
            );
            assert!(want.non_finite > 0 && want.implausible > 0);
        }
    }

    /// A summary calls a set of values clean exactly when the sanitising pass would replace
    /// none of them, for every subset of special values (the largest magnitude at, above and
    /// below the bound; NaN's and Inf's bits above every finite one's), added in two parts.
    #[test]
    fn a_summary_is_clean_exactly_when_nothing_would_be_replaced() {
        let specials = [
            f32::NAN,
            -f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            -1.0,
            -0.0,
            f32::MAX,
            -3.0,
            3.0,
            0.5,
        ];
        let bound = Some(3.0);
        for subset in 0u32..1 << specials.len() {
            let values: Vec<f32> = (0..specials.len())
                .filter(|k| subset >> k & 1 == 1)
                .map(|k| specials[k])
                .collect();
            let mut summary = Summary::default();
            let (first, rest) = values.split_at(values.len() / 2);
            summary.add(first);
            summary.add(rest);
            for (layer, bound) in [
                (Layer::Color, None),
                (Layer::Dx, bound),
                (Layer::Normal, None),
            ] {
                let mut img = Image::from_fn(1, values.len().max(1), 1, |(_, x, _)| {
                    values.get(x).copied().unwrap_or(0.0)
                });
                let counts = sanitize_layer(layer, &mut img, Policy::Replace, bound).unwrap();
                assert_eq!(
                    summary.clean(layer, bound),
                    counts.total() == 0,
                    "{layer}, {values:?}"
                );
            }
        }
        let values = [0.25, -0.0, 2.0, 1.5];
        let mut color = Summary::default();
        color.add(&values);
        let image = Image::from_fn(1, values.len(), 1, |(_, x, _)| values[x]);
        assert_eq!(color.gradient_bound(), gradient_bound(&image));
    }
}
