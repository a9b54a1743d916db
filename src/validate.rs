//! The bad-input policy: what happens to NaN, Inf and negative values.
//!
//! Gradient-domain renderers produce them (a failed shift, a division by a vanishing pdf), and
//! one NaN spreads through any global solve, so no bad value ever reaches a method:
//! - non-finite values (NaN, +Inf, -Inf) in any layer become 0;
//! - negative values in colour, variance and reference become 0 (gradients and normals are
//!   signed by nature and are left alone);
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

/// How many values of one layer were replaced.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[non_exhaustive]
pub struct LayerCounts {
    /// NaN or infinite values replaced by 0.
    pub non_finite: u64,
    /// Negative values replaced by 0 (colour, variance, reference only).
    pub negative: u64,
}

impl LayerCounts {
    /// Total replaced values.
    pub fn total(&self) -> u64 {
        self.non_finite + self.negative
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
                s
            })
            .collect();
        write!(f, "replaced by 0: {}", parts.join("; "))
    }
}

/// Checks one layer in place under `policy`, returning what was replaced.
pub(crate) fn sanitize_layer(layer: Layer, img: &mut Image, policy: Policy) -> Result<LayerCounts> {
    let no_negatives = layer.must_be_nonnegative();
    let bad = |v: f32| !v.is_finite() || (no_negatives && v < 0.0);
    if policy == Policy::Strict {
        if let Some(i) = img.as_slice().par_iter().position_first(|&v| bad(v)) {
            let (w, h) = img.size();
            let (c, y, x) = (i / (w * h), (i / w) % h, i % w);
            let count = img.as_slice().par_iter().filter(|&&v| bad(v)).count();
            let v = img.as_slice()[i];
            return Err(Error::input(format!(
                "layer '{layer}' holds {count} {} value(s); first: {v} at pixel ({x}, {y}) \
                 channel {} (strict mode refuses them)",
                if no_negatives {
                    "non-finite or negative"
                } else {
                    "non-finite"
                },
                layer.components()[c]
            )));
        }
        return Ok(LayerCounts::default());
    }
    let (non_finite, negative) = img
        .as_mut_slice()
        .par_chunks_mut(1 << 14)
        .map(|chunk| {
            let (mut nf, mut neg) = (0u64, 0u64);
            for v in chunk {
                if !v.is_finite() {
                    nf += 1;
                    *v = 0.0;
                } else if no_negatives && *v < 0.0 {
                    neg += 1;
                    *v = 0.0;
                }
            }
            (nf, neg)
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    Ok(LayerCounts {
        non_finite,
        negative,
    })
}
