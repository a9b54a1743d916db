//! The variance-aware bilateral prefilter of the feature buffers (albedo, normal), run before
//! every stage that reads them, as the FRGR release does.
//!
//! Per pixel `p` and feature `f` (raw: albedo as given, normals in [-1, 1]), with `v` the
//! variance of the feature's mean summed over its channels:
//! `w_q = exp(-|q - p|^2 / 2 - max(|f_q - f_p|^2 - (v_p + v_q), 0) / max(100 v_p, 1e-4))`
//! (spatial sigma 1, squared distances summed over channels); the output is
//! `sum w_q f_q / sum w_q`. The window is the disc of radius 4 (49 taps; the release's notes
//! say a radius of 5 is enough): the spatial factor outside it is below 2e-4 of the centre's,
//! and all of it together 4e-4 of the weights' sum.
//!
//! Differences smaller than the two pixels' noise count as equal, so noise is averaged away
//! while a feature edge (a difference well above the noise) stops the filter. Where the
//! variance is 0 the range scale is `1e-4`: only neighbours within about 0.01 of the pixel are
//! mixed in.
//!
//! Bundles carry no feature variance (the conventions define none), so it is estimated (see
//! [`feature_variance`]). The release also propagates the variance through the filter
//! (`sum w_q^2 v_q / (sum w_q)^2`) for RDFC's feature normaliser `max(var_f, |grad f|^2, 1e-3)`;
//! with an estimated variance RDFC keeps `var_f = 0` as before (the estimate is at most a
//! quarter of the neighbourhood's squared range over spp, of the order of the gradient term it
//! would compete with), so it is not computed.
//!
//! Cost: 49 taps per pixel and feature, one `exp` each, vectorised over runs of a row
//! (`fastmath`; AVX-512 and AVX2 builds picked at run time); the radius-4 disc costs half the
//! radius-5 one (its time and the validation figures: `docs/benchmarks.md`).
//! Validation set (`docs/benchmarks.md`): relMSE 0.5 % lower with it (geometric mean of the
//! 18 frames; 12 better, by up to 2.8 %, 6 worse, by up to 2.0 %, mostly at 64 spp, where
//! the bound overestimates the noise of fine textures).
//!
//! Since the thirty-third session it runs below 16 spp only (`prefilter_below`, its default
//! in `frgr/mod.rs` says why): on today's validation split it gains 2.2 % at 4 spp and costs
//! 0.4 % and 0.6 % at 16 and 64 spp, and on a curved surface of one albedo (a black sphere
//! with small lamps) the bound takes the normals' curvature for noise and blends them, so
//! FRGR's filters spread the lamps over the sphere (the guard's `lamps_16spp`: 1.21x its base
//! with the prefilter, 0.39x without).

use rayon::prelude::*;

use super::fastmath::{exp_nonpositive, fused, madd, max, min};
use super::util::{reflect, PaddedRows};
use crate::error::Result;
use crate::image::{try_zeroed_vec, Image};

/// Radius of the prefilter's window (a disc).
pub(crate) const RADIUS: usize = 4;

/// The window's offsets `(dx, dy)` and their spatial exponents `(dx^2 + dy^2) / 2`.
fn taps() -> Vec<(isize, isize, f32)> {
    let r = RADIUS as isize;
    let mut taps = Vec::new();
    for dy in -r..=r {
        for dx in -r..=r {
            let d2 = dx * dx + dy * dy;
            if d2 <= r * r {
                taps.push((dx, dy, d2 as f32 / 2.0));
            }
        }
    }
    taps
}

/// Variance of a feature's per-pixel mean, summed over its channels, estimated from the
/// feature itself: per channel `(max - f_p)(f_p - min) / spp` over the 3 x 3 neighbourhood.
///
/// Why this bound: a feature varies within a pixel mostly where its footprint straddles
/// surfaces, whose values its neighbours show. The per-sample values then lie within the
/// neighbourhood's range, and a variable in `[m, M]` with mean `f_p` has variance at most
/// `(M - f_p)(f_p - m)` (Bhatia-Davis), with equality when the pixel mixes two surfaces; the
/// mean of `spp` samples divides it by `spp`. Pixels inside a flat region or on either side of a
/// pixel-aligned edge get 0 (nothing to filter), smooth ramps a small overestimate (which a
/// symmetric filter leaves unchanged anyway).
pub(crate) fn feature_variance(f: &Image, spp: f32) -> Result<Image> {
    let (w, h) = f.size();
    let mut out = Image::try_zeros(1, w, h)?;
    if w == 0 || h == 0 {
        return Ok(out);
    }
    let padded = PaddedRows::new(f, 1)?;
    let inv_spp = 1.0 / spp.max(1.0);
    out.as_mut_slice()
        .par_chunks_mut(w)
        .enumerate()
        .for_each(|(y, row)| {
            let (mut lo, mut hi) = (vec![0.0f32; w], vec![0.0f32; w]);
            for c in 0..f.channels() {
                let p = padded.row(c, y, 0, 0, w);
                lo.copy_from_slice(p);
                hi.copy_from_slice(p);
                for dy in -1..=1 {
                    let qy = reflect(y as isize + dy, h);
                    for dx in -1..=1 {
                        let q = padded.row(c, qy, 0, dx, w);
                        for ((l, u), &q) in lo.iter_mut().zip(hi.iter_mut()).zip(q) {
                            *l = min(*l, q);
                            *u = max(*u, q);
                        }
                    }
                }
                for (((o, &p), &l), &u) in row.iter_mut().zip(p).zip(&lo).zip(&hi) {
                    *o += (u - p) * (p - l);
                }
            }
            row.iter_mut().for_each(|v| *v *= inv_spp);
        });
    Ok(out)
}

/// Pixels of a row processed together: their accumulators stay in the L1 cache across the
/// window's taps (720p, radius 5: 0.137 s with whole rows, 0.130 s in runs of 128: the kernel
/// is bound by its arithmetic, not by memory).
const CHUNK: usize = 128;

/// Adds the taps at one window offset to a run of pixels: `fp`/`fq` the centre and neighbour
/// feature rows, `vp`/`vq` their variances, `inv = 1 / max(100 v_p, 1e-4)`, `spatial` the
/// offset's exponent; `num` the weighted sums of the 3 channels, `den` the weights' sum.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn add_taps(
    [n0, n1, n2]: [&mut [f32]; 3],
    den: &mut [f32],
    [p0, p1, p2]: [&[f32]; 3],
    [q0, q1, q2]: [&[f32]; 3],
    (vp, vq, inv): (&[f32], &[f32], &[f32]),
    spatial: f32,
) {
    const F: bool = fused!();
    let n = den.len();
    let (p0, p1, p2, q0, q1, q2) = (&p0[..n], &p1[..n], &p2[..n], &q0[..n], &q1[..n], &q2[..n]);
    let (vp, vq, inv) = (&vp[..n], &vq[..n], &inv[..n]);
    let (n0, n1, n2) = (&mut n0[..n], &mut n1[..n], &mut n2[..n]);
    for i in 0..n {
        let (d0, d1, d2) = (q0[i] - p0[i], q1[i] - p1[i], q2[i] - p2[i]);
        let range = max(d0 * d0 + d1 * d1 + d2 * d2 - (vp[i] + vq[i]), 0.0) * inv[i];
        // Weights below e^-50 (2e-22 of the centre's) are 0, so that their products with the
        // feature are never subnormal (slow on x86).
        let x = -(range + spatial);
        let wq = if x < -50.0 {
            0.0
        } else {
            exp_nonpositive::<F>(x)
        };
        n0[i] = madd::<F>(wq, q0[i], n0[i]);
        n1[i] = madd::<F>(wq, q1[i], n1[i]);
        n2[i] = madd::<F>(wq, q2[i], n2[i]);
        den[i] += wq;
    }
}

/// Filters a 3-channel feature `f` whose per-pixel variance (summed over channels, 1 channel)
/// is `v`.
pub(crate) fn prefilter(f: &Image, v: &Image) -> Result<Image> {
    let (w, h) = f.size();
    assert_eq!(f.channels(), 3, "the prefilter takes 3-channel features");
    assert_eq!(
        (v.channels(), v.size()),
        (1, (w, h)),
        "one variance per pixel"
    );
    if w == 0 || h == 0 {
        return f.try_clone();
    }
    let padded = PaddedRows::new(f, RADIUS)?;
    let vpad = PaddedRows::new(v, RADIUS)?;
    let taps = taps();
    // Per row: the 3 channels' sums, then the weights' sum and `inv`.
    let mut rows = try_zeroed_vec::<f32>(h * 5 * w)?;
    rows.par_chunks_mut(5 * w).enumerate().for_each(|(y, row)| {
        let (n0, rest) = row.split_at_mut(w);
        let (n1, rest) = rest.split_at_mut(w);
        let (n2, rest) = rest.split_at_mut(w);
        let (den, inv) = rest.split_at_mut(w);
        let mut x0 = 0;
        for (((n0, n1), n2), (den, inv)) in n0
            .chunks_mut(CHUNK)
            .zip(n1.chunks_mut(CHUNK))
            .zip(n2.chunks_mut(CHUNK))
            .zip(den.chunks_mut(CHUNK).zip(inv.chunks_mut(CHUNK)))
        {
            let len = den.len();
            let vp = vpad.row(0, y, x0, 0, len);
            for (i, &vi) in inv.iter_mut().zip(vp) {
                *i = 1.0 / (100.0 * vi).max(1e-4);
            }
            let fp = padded.rows3(y, x0, 0, len);
            for &(dx, dy, spatial) in &taps {
                let qy = reflect(y as isize + dy, h);
                add_taps(
                    [&mut *n0, &mut *n1, &mut *n2],
                    den,
                    fp,
                    padded.rows3(qy, x0, dx, len),
                    (vp, vpad.row(0, qy, x0, dx, len), inv),
                    spatial,
                );
            }
            // The centre's weight is 1, so `den >= 1`. Only a sum of weighted features near
            // f32::MAX can overflow (garbage frames): such a pixel keeps its own value.
            for (n, p) in [&mut *n0, &mut *n1, &mut *n2].into_iter().zip(fp) {
                for ((n, &p), &den) in n.iter_mut().zip(p).zip(&*den) {
                    let v = *n * (1.0 / den);
                    *n = if v.is_finite() { v } else { p };
                }
            }
            x0 += len;
        }
    });
    Image::try_par_from_fn(3, w, h, |(c, x, y)| rows[(y * 5 + c) * w + x])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn random_feature(w: usize, h: usize, seed: u64) -> Image {
        let mut s = seed;
        Image::from_fn(3, w, h, |_| {
            s = s
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (s >> 40) as f32 / (1u64 << 24) as f32
        })
    }

    /// The definition, one pixel at a time, in f64; with the propagated variance.
    fn naive(f: &Image, v: &Image) -> (Vec<[f64; 3]>, Vec<f64>) {
        let v = v.as_slice();
        let (w, h) = f.size();
        let r = RADIUS as isize;
        let mut out = Vec::new();
        let mut var = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let vp = f64::from(v[y * w + x]);
                let (mut num, mut den, mut vs) = ([0.0f64; 3], 0.0f64, 0.0f64);
                for dy in -r..=r {
                    for dx in -r..=r {
                        if dx * dx + dy * dy > r * r {
                            continue;
                        }
                        let (qx, qy) = (reflect(x as isize + dx, w), reflect(y as isize + dy, h));
                        let vq = f64::from(v[qy * w + qx]);
                        let d2: f64 = (0..3)
                            .map(|c| {
                                (f64::from(f.at(c, qx, qy)) - f64::from(f.at(c, x, y))).powi(2)
                            })
                            .sum();
                        let range = (d2 - (vp + vq)).max(0.0) / (100.0 * vp).max(1e-4);
                        let wq = (-((dx * dx + dy * dy) as f64 / 2.0) - range).exp();
                        for (c, n) in num.iter_mut().enumerate() {
                            *n += wq * f64::from(f.at(c, qx, qy));
                        }
                        den += wq;
                        vs += wq * wq * vq;
                    }
                }
                out.push(num.map(|n| n / den));
                var.push(vs / (den * den));
            }
        }
        (out, var)
    }

    #[test]
    fn prefilter_equals_its_definition() {
        // Odd sizes, smaller than the window (reflection more than once), and ordinary ones.
        for (w, h) in [(23, 17), (4, 3), (1, 6)] {
            let f = random_feature(w, h, 7);
            let v = Image::from_fn(1, w, h, |(_, x, y)| 0.05 * f.at(0, x, y).powi(2));
            let got = prefilter(&f, &v).unwrap();
            let (want, _) = naive(&f, &v);
            for y in 0..h {
                for x in 0..w {
                    for (c, &e) in want[y * w + x].iter().enumerate() {
                        let g = f64::from(got.at(c, x, y));
                        assert!((g - e).abs() < 1e-5, "{w}x{h} ({x},{y},{c}): {g} vs {e}");
                    }
                }
            }
        }
    }

    #[test]
    fn a_constant_feature_stays_constant() {
        let f = Image::from_fn(3, 15, 12, |(c, _, _)| [0.2, -0.5, 0.9][c]);
        let got = prefilter(&f, &Image::from_fn(1, 15, 12, |_| 0.01)).unwrap();
        for (g, e) in got.as_slice().iter().zip(f.as_slice()) {
            assert!((g - e).abs() < 1e-6, "{g} vs {e}");
        }
    }

    #[test]
    fn an_edge_well_above_the_noise_stops_the_filter() {
        // Left half 0, right half 1 (per channel), noise variance 1e-3: every weight across
        // the edge is below exp(-(3 - 2e-3) / 0.1) = 1e-13 (the tolerance is f32 rounding).
        let f = Image::from_fn(3, 20, 10, |(_, x, _)| if x < 10 { 0.0 } else { 1.0 });
        let got = prefilter(&f, &Image::from_fn(1, 20, 10, |_| 1e-3)).unwrap();
        for (g, e) in got.as_slice().iter().zip(f.as_slice()) {
            assert!((g - e).abs() < 1e-6, "{g} vs {e}");
        }
    }

    #[test]
    fn noise_below_the_variance_is_averaged_away() {
        let noisy = random_feature(32, 32, 3);
        // The values are uniform in [0, 1): per-channel variance 1/12, summed 1/4.
        let v = Image::from_fn(1, 32, 32, |_| 0.25);
        let got = prefilter(&noisy, &v).unwrap();
        let spread = |img: &Image| {
            let s = img.as_slice();
            let m = s.iter().sum::<f32>() / s.len() as f32;
            s.iter().map(|x| (x - m) * (x - m)).sum::<f32>() / s.len() as f32
        };
        // All weights are then nearly the spatial Gaussian's, which keeps sum w^2 / (sum w)^2
        // = 0.0796 of the noise's variance (1 / (4 pi sigma^2), up to truncation): that is
        // also the variance the naive definition propagates.
        assert!(spread(&got) < 0.15 * spread(&noisy), "{}", spread(&got));
        let (_, var) = naive(&noisy, &v);
        assert!(
            var.iter().all(|&x| (x / 0.25 - 0.0796).abs() < 0.005),
            "{:?}",
            &var[..4]
        );
    }

    #[test]
    fn variance_estimate_is_exact_for_a_pixel_mixing_two_surfaces() {
        // Columns 0-2 albedo 0.2, column 3 a 30/70 mix, columns 4-6 albedo 0.8: the mixed
        // pixel's samples are 0.2 with probability 0.3 and 0.8 otherwise (per-sample variance
        // 0.3 * 0.7 * 0.36 = 0.0756 per channel), the others see a single surface.
        let f = Image::from_fn(3, 7, 5, |(_, x, _)| match x {
            0..=2 => 0.2,
            3 => 0.3 * 0.2 + 0.7 * 0.8,
            _ => 0.8,
        });
        let v = feature_variance(&f, 4.0).unwrap();
        for y in 0..5 {
            for x in 0..7 {
                let want = if x == 3 { 3.0 * 0.0756 / 4.0 } else { 0.0 };
                let got = v.at(0, x, y);
                assert!((got - want).abs() < 1e-6, "({x},{y}): {got}");
            }
        }
    }
}
