//! The base image's noise band: a reconstruction should not leave the base image by more than
//! a few standard deviations of the base's own noise. Where it does, it is wrong there (a
//! filter that blurred a wire away, a network that darkened a dim room, a solve that spread an
//! emitter), and the band's edge is a better answer than either.
//!
//! Per pixel and channel, with `s` the standard deviation of the base's noise (the square root
//! of the variance layer averaged over the 3 x 3 neighbourhood, reflect-101 borders: a
//! variance of the mean estimated from a few passes is itself noisy, and its 3 x 3 mean
//! undershoots less), the output is clamped to `[I_b - k s, I_b + k s]`. Frames without a
//! variance layer are left as they are.
//!
//! The width `k` is each method's `noise_band` parameter. Its default, 5, was chosen on the
//! validation split (`docs/benchmarks.md`, "The noise band"): there it removes the gross
//! departures (FRGR's geometric-mean relMSE falls 6-23 % and no FRGR frame is worse than its
//! base any more; GradNet's falls 2-9 % and its worst frame goes from 9.5x to 5.0x its base)
//! and leaves L1 as it was (within 0.3 %); narrower bands cut into good reconstructions where
//! the variance estimate undershoots (dark pixels whose few samples were all 0). On the test
//! split, evaluated once: FRGR -5 to +0.2 %, GradNet -2 to -7 %, L1 -0.1 to -0.2 %; the frames
//! that lose to their base there (bulbs in view, sub-pixel wires) lose less but still lose.
//! Its cost is one pass over the frame (11 ms at 1280 x 720, 2 threads). The band trusts the
//! variance layer: a layer of zeros makes the output the base image.

use rayon::prelude::*;

use super::param::{Param, Range};
use super::{Method, Reconstructor};
use crate::error::Result;
use crate::frame::Frame;
use crate::image::Image;
use crate::progress::Progress;
use crate::recon::ops::reflect;
use crate::report::Report;

/// Default `noise_band`: the band's half-width in standard deviations of the base's noise.
pub(crate) const NOISE_BAND: f32 = 5.0;

/// The `noise_band` entry of a method's parameter table (`get` and `set` reach its field):
/// one name, range and meaning for every method that has a band.
pub(crate) const fn param<C>(get: fn(&C) -> f32, set: fn(&mut C, f32)) -> Param<C> {
    Param::float(
        "noise_band",
        Range::closed(0.0, 1e6),
        NOISE_BAND_DOC,
        get,
        set,
    )
}

/// The documentation of every method's `noise_band` parameter.
const NOISE_BAND_DOC: &str =
    "Clamp the output to the base image ± this many standard deviations of its noise (the \
     variance layer's 3 x 3 mean): where a reconstruction leaves the base by more, it is \
     wrong there; 0: off (frames without a variance layer are never clamped)";

/// `inner`, its output clamped to the noise band of half-width `k` (`inner` itself when `k`
/// is 0). The band is taken around the frame the plan is given, whatever `inner` makes of it
/// (the prior path anchors its solve to a prior, not to the base).
pub(crate) fn banded(inner: Box<dyn Reconstructor>, k: f32) -> Box<dyn Reconstructor> {
    if k > 0.0 {
        Box::new(Banded { inner, k })
    } else {
        inner
    }
}

struct Banded {
    inner: Box<dyn Reconstructor>,
    k: f32,
}

impl Reconstructor for Banded {
    fn method(&self) -> Method {
        self.inner.method()
    }

    fn reconstruct_into(
        &mut self,
        frame: &Frame,
        out: &mut Image,
        report: &mut Report,
        progress: &Progress,
    ) -> Result<()> {
        self.inner.reconstruct_into(frame, out, report, progress)?;
        if frame.variance().is_none() {
            report.skip("noise band (no variance layer)");
            return Ok(());
        }
        let k = self.k;
        let moved = report.time("noise band", || clamp_to_band(out, frame, k));
        if moved > 0 {
            report.note(format!(
                "noise band: {moved} values clamped to the base ± {k} standard deviations"
            ));
        }
        Ok(())
    }
}

/// Clamps `out` to the base image ± `k` standard deviations of its noise; returns how many
/// values moved (0 without a variance layer or with `k` 0, which means off).
pub(crate) fn clamp_to_band(out: &mut Image, frame: &Frame, k: f32) -> u64 {
    let Some(var) = frame.variance() else {
        return 0;
    };
    if k <= 0.0 {
        return 0;
    }
    let (w, h) = out.size();
    if w == 0 || h == 0 {
        return 0;
    }
    let (base, var) = (frame.color().as_slice(), var.as_slice());
    let n = w * h;
    out.as_mut_slice()
        .par_chunks_mut(w)
        .enumerate()
        .map(|(row, values)| {
            let (c, y) = (row / h, row % h);
            let rows: [&[f32]; 3] = std::array::from_fn(|d| {
                let yy = reflect(y as isize + d as isize - 1, h);
                &var[c * n + yy * w..c * n + (yy + 1) * w]
            });
            let base = &base[c * n + y * w..c * n + (y + 1) * w];
            let mut moved = 0;
            for (x, v) in values.iter_mut().enumerate() {
                let mut sum = 0.0f64;
                for r in rows {
                    for dx in -1..=1 {
                        sum += f64::from(r[reflect(x as isize + dx, w)]);
                    }
                }
                let s = ((sum / 9.0).max(0.0).sqrt() * f64::from(k)) as f32;
                let b = base[x];
                let clamped = v.clamp(b - s, b + s);
                if clamped != *v {
                    *v = clamped;
                    moved += 1;
                }
            }
            moved
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::{FrameBuilder, Layer};
    use crate::validate::Policy;

    fn frame(w: usize, h: usize, var: Option<Image>) -> Frame {
        let colour = Image::from_fn(3, w, h, |(c, x, y)| {
            0.5 + 0.1 * ((x * 3 + y + c) % 4) as f32
        });
        let zero = Image::zeros(3, w, h);
        let mut b = FrameBuilder::new()
            .image(Layer::Color, colour)
            .image(Layer::Dx, zero.clone())
            .image(Layer::Dy, zero);
        if let Some(v) = var {
            b = b.image(Layer::Variance, v);
        }
        b.build(Policy::Strict).unwrap()
    }

    /// The definition, pixel by pixel, in f64.
    fn reference(out: &Image, frame: &Frame, k: f32) -> Image {
        let (w, h) = out.size();
        let var = frame.variance().unwrap();
        Image::from_fn(3, w, h, |(c, x, y)| {
            let mut sum = 0.0f64;
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let (xx, yy) = (reflect(x as isize + dx, w), reflect(y as isize + dy, h));
                    sum += f64::from(var.at(c, xx, yy));
                }
            }
            let s = ((sum / 9.0).sqrt() * f64::from(k)) as f32;
            let b = frame.color().at(c, x, y);
            out.at(c, x, y).clamp(b - s, b + s)
        })
    }

    #[test]
    fn clamps_to_the_band_as_defined() {
        let (w, h) = (7, 5);
        let var = Image::from_fn(3, w, h, |(c, x, y)| 1e-3 * ((x + 2 * y + c) % 5) as f32);
        let f = frame(w, h, Some(var));
        let out = Image::from_fn(3, w, h, |(c, x, y)| ((x * 7 + y * 5 + c) % 9) as f32 * 0.15);
        for k in [0.5, 2.0, 5.0] {
            let mut got = out.clone();
            let moved = clamp_to_band(&mut got, &f, k);
            let want = reference(&out, &f, k);
            assert_eq!(got, want, "k = {k}");
            let differ = out
                .as_slice()
                .iter()
                .zip(want.as_slice())
                .filter(|(a, b)| a != b)
                .count();
            assert_eq!(moved, differ as u64, "k = {k}");
            assert!(moved > 0, "the test must clamp something at k = {k}");
        }
    }

    #[test]
    fn without_variance_or_width_nothing_moves() {
        let (w, h) = (6, 4);
        let out = Image::from_fn(3, w, h, |(c, x, y)| (x + y + c) as f32);
        let mut got = out.clone();
        assert_eq!(clamp_to_band(&mut got, &frame(w, h, None), 5.0), 0);
        assert_eq!(got, out);
        let zero_var = frame(w, h, Some(Image::zeros(3, w, h)));
        assert_eq!(clamp_to_band(&mut got, &zero_var, 0.0), 0);
        assert_eq!(got, out);
        // Zero variance and a band: the base image itself.
        clamp_to_band(&mut got, &zero_var, 5.0);
        assert_eq!(&got, zero_var.color());
    }
}
