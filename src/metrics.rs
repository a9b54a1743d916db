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
        .map(|(a, r)| {
            a.iter().zip(r).fold((0.0, 0.0), |(rel, sq), (&a, &r)| {
                let (a, r) = (f64::from(a), f64::from(r));
                let d2 = (a - r) * (a - r);
                (rel + d2 / (r * r + 0.01), sq + d2)
            })
        })
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

#[cfg(test)]
mod tests {
    use super::*;

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
