//! Error metrics against a reference.
//!
//! - relMSE = mean over pixels and channels of `(I - R)^2 / (R^2 + 0.01)` (GradNet's
//!   definition, Guo et al. 2019, Sec. 6), the project's primary metric; print it with 5
//!   significant digits.
//! - MSE = mean of `(I - R)^2`; PSNR = `10 log10(1 / MSE)`, i.e. peak 1.0 on linear radiance.
//!
//! A non-finite value in the image under test is a failure, never averaged away.

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::image::Image;

/// Errors of an image against a reference.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Metrics {
    /// Relative mean squared error (primary metric).
    pub rel_mse: f64,
    /// Mean squared error.
    pub mse: f64,
    /// Peak signal-to-noise ratio in dB, peak 1.0.
    pub psnr: f64,
}

impl std::fmt::Display for Metrics {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "relMSE {:.5e}  MSE {:.5e}  PSNR {:.2} dB",
            self.rel_mse, self.mse, self.psnr
        )
    }
}

/// Compares `image` with `reference` (same size and channel count).
pub fn compare(image: &Image, reference: &Image) -> Result<Metrics> {
    if image.size() != reference.size() || image.channels() != reference.channels() {
        return Err(Error::input(format!(
            "image is {} x {} x {}, reference is {} x {} x {}",
            image.width(),
            image.height(),
            image.channels(),
            reference.width(),
            reference.height(),
            reference.channels()
        )));
    }
    let non_finite = |img: &Image| img.as_slice().par_iter().filter(|v| !v.is_finite()).count();
    match (non_finite(image), non_finite(reference)) {
        (0, 0) => {}
        (0, n) => {
            return Err(Error::input(format!(
                "reference holds {n} non-finite values: no error can be measured against it"
            )))
        }
        (n, _) => {
            return Err(Error::input(format!(
                "image holds {n} non-finite values: a failed reconstruction, not an error to \
                 average"
            )))
        }
    }
    let chunk = image.width().max(1024);
    // Per-chunk partial sums collected in order and added serially: the same result for
    // any thread count.
    let partials: Vec<(f64, f64)> = image
        .as_slice()
        .par_chunks(chunk)
        .zip(reference.as_slice().par_chunks(chunk))
        .map(|(a, r)| chunk_sums(a, r))
        .collect();
    let n = image.as_slice().len() as f64;
    let (rel, sq) = partials
        .iter()
        .fold((0.0, 0.0), |(a, b), (c, d)| (a + c, b + d));
    let mse = sq / n;
    Ok(Metrics {
        rel_mse: rel / n,
        mse,
        psnr: if mse > 0.0 {
            10.0 * (1.0 / mse).log10()
        } else {
            f64::INFINITY
        },
    })
}

/// The sums of `(a - r)^2 / (r^2 + 0.01)` and `(a - r)^2` over one chunk, in 8 interleaved
/// lanes (so that they vectorise: one running sum is a chain of dependent additions, and ran
/// the CLI's two comparisons of a 720p frame in 12 ms), the lanes then added in order.
fn chunk_sums(a: &[f32], r: &[f32]) -> (f64, f64) {
    const L: usize = 8;
    let (mut rel, mut sq) = ([0.0f64; L], [0.0f64; L]);
    let mut add = |k: usize, a: f32, r: f32| {
        let (a, r) = (f64::from(a), f64::from(r));
        let d2 = (a - r) * (a - r);
        rel[k] += d2 / (r * r + 0.01);
        sq[k] += d2;
    };
    let (ab, rb) = (a.chunks_exact(L), r.chunks_exact(L));
    let (at, rt) = (ab.remainder(), rb.remainder());
    for (a8, r8) in ab.zip(rb) {
        for k in 0..L {
            add(k, a8[k], r8[k]);
        }
    }
    for (k, (&a, &r)) in at.iter().zip(rt).enumerate() {
        add(k, a, r);
    }
    (rel.iter().sum(), sq.iter().sum())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The lane sums against one running f64 sum per term, on lengths around the lane width.
    #[test]
    fn lane_sums_match_a_running_sum() {
        for len in [0, 1, 7, 8, 9, 1023, 4096 + 5] {
            let a: Vec<f32> = (0..len).map(|i| ((i * 37 % 101) as f32) * 0.03).collect();
            let r: Vec<f32> = (0..len).map(|i| ((i * 11 % 89) as f32) * 0.05).collect();
            let (mut rel, mut sq) = (0.0f64, 0.0f64);
            for (&a, &r) in a.iter().zip(&r) {
                let (a, r) = (f64::from(a), f64::from(r));
                rel += (a - r) * (a - r) / (r * r + 0.01);
                sq += (a - r) * (a - r);
            }
            let (got_rel, got_sq) = chunk_sums(&a, &r);
            assert!(
                (got_rel - rel).abs() <= 1e-12 * rel.max(1.0),
                "{len}: {got_rel} {rel}"
            );
            assert!(
                (got_sq - sq).abs() <= 1e-12 * sq.max(1.0),
                "{len}: {got_sq} {sq}"
            );
        }
    }

    #[test]
    fn hand_computed_values() {
        let r = Image::from_fn(1, 2, 1, |(_, x, _)| [0.0, 1.0][x]);
        let i = Image::from_fn(1, 2, 1, |(_, x, _)| [0.1, 0.5][x]);
        let m = compare(&i, &r).unwrap();
        let rel = (0.01f64 / 0.01 + 0.25 / 1.01) / 2.0;
        assert!((m.rel_mse - rel).abs() < 1e-7, "{}", m.rel_mse);
        assert!((m.mse - 0.13).abs() < 1e-7);
        assert!((m.psnr - 10.0 * (1.0f64 / 0.13).log10()).abs() < 1e-4);
    }

    #[test]
    fn non_finite_is_a_failure() {
        let r = Image::zeros(3, 2, 2);
        let mut i = Image::zeros(3, 2, 2);
        i.as_mut_slice()[5] = f32::NAN;
        let e = compare(&i, &r).unwrap_err();
        assert!(e.to_string().contains("1 non-finite"), "{e}");
    }

    #[test]
    fn size_mismatch_is_an_error() {
        assert!(compare(&Image::zeros(3, 2, 2), &Image::zeros(3, 3, 2)).is_err());
    }
}
