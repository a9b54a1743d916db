//! The pre-denoiser: the first pass of RDFC (Rousselle et al. 2013), as the FRGR release uses
//! it to make the guide image.
//!
//! Three candidate non-local-means filters over a 21 x 21 window, each joint with a bilateral
//! term on albedo and normal: `(k_c, f) = (0.45, 1)`, `(0.45, 3)` and `(inf, 3)` (colour term
//! off), feature bandwidth `k_f = 0.6`. Distances (per channel, averaged over channels):
//! - colour, Eq. 5-6: `((c_p - c_q)^2 - (v_p + min(v_p, v_q))) / (1e-10 + k_c^2 (v_p + v_q))`,
//!   averaged over a `(2f+1)^2` patch;
//! - feature, Eq. 7: `(f_p - f_q)^2 / (k_f^2 D_p)`, `D_p = max(var_f, |grad f|^2, 1e-3)` with
//!   the feature variance taken as 0 (bundles carry none; the features are rendered with many
//!   samples).
//!
//! The weight is `min(w_colour, w_albedo, w_normal)` = `exp(-max(d_c, d_a, d_n, 0))`; the
//! centre pixel takes the largest neighbour weight (at least 1e-3). Per candidate, SURE
//! `sum_c (F_c - c_c)^2 - v_c + 2 v_c w_centre / sum w` estimates the error; the SURE maps are
//! smoothed (3 x 3 box: our choice, the release's smoothing is unspecified), the per-pixel
//! argmin makes a one-hot selection map, which is smoothed by the same kind of filter (7 x 7
//! window, 3 x 3 patch, `k_c = 0.5`, `k_f = 0.6`) and used to blend the candidates.
//!
//! Cost: the colour distances are computed once per window offset as images and patch-summed by
//! separable running sums, so a candidate costs the same for any patch size.

use rayon::prelude::*;

use super::util::reflect;
use crate::image::Image;

/// One candidate filter: patch radius `f` and colour bandwidth (`None`: colour term off).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Candidate {
    pub patch: usize,
    pub kc: Option<f32>,
}

/// The release's three candidates.
pub(crate) const CANDIDATES: [Candidate; 3] = [
    Candidate {
        patch: 1,
        kc: Some(0.45),
    },
    Candidate {
        patch: 3,
        kc: Some(0.45),
    },
    Candidate { patch: 3, kc: None },
];

const KF: f32 = 0.6;

/// A feature buffer with its per-pixel normaliser `k_f^2 D_p`.
pub(crate) struct Feature<'a> {
    img: &'a Image,
    norm: Vec<f32>,
}

impl<'a> Feature<'a> {
    /// Prepares a feature: `D_p = max(|grad f|^2 (central differences, mean over channels), 1e-3)`.
    pub fn new(img: &'a Image) -> Self {
        let (w, h) = img.size();
        let ch = img.channels();
        let n = w * h;
        let s = img.as_slice();
        let norm = (0..n)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let mut g2 = 0.0;
                for c in 0..ch {
                    let at = |xx: isize, yy: isize| s[c * n + reflect(yy, h) * w + reflect(xx, w)];
                    let gx =
                        0.5 * (at(x as isize + 1, y as isize) - at(x as isize - 1, y as isize));
                    let gy =
                        0.5 * (at(x as isize, y as isize + 1) - at(x as isize, y as isize - 1));
                    g2 += gx * gx + gy * gy;
                }
                KF * KF * (g2 / ch as f32).max(1e-3)
            })
            .collect();
        Feature { img, norm }
    }
}

/// A per-channel box average of radius `r` of a variance image.
pub(crate) fn smooth_variance(var: &Image, r: usize) -> Image {
    let (w, h) = var.size();
    let mut out = var.clone();
    let mut tmp = Vec::new();
    for c in 0..var.channels() {
        let src = var.plane(c).as_slice().expect("contiguous").to_vec();
        let dst = out.plane_mut(c).into_slice().expect("contiguous");
        box_mean(&src, w, h, r, &mut tmp, dst);
    }
    out
}

/// Box sum of radius `r` over rows then columns (reflect-101), divided by the area.
fn box_mean(src: &[f32], w: usize, h: usize, r: usize, tmp: &mut Vec<f32>, dst: &mut [f32]) {
    let area = ((2 * r + 1) * (2 * r + 1)) as f32;
    tmp.resize(w * h, 0.0);
    tmp.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let s = &src[y * w..(y + 1) * w];
        let mut acc: f32 = (-(r as isize)..=r as isize).map(|d| s[reflect(d, w)]).sum();
        for x in 0..w {
            row[x] = acc;
            acc +=
                s[reflect(x as isize + r as isize + 1, w)] - s[reflect(x as isize - r as isize, w)];
        }
    });
    let tmp = &*tmp;
    dst.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, out) in row.iter_mut().enumerate() {
            let mut acc = 0.0;
            for d in -(r as isize)..=r as isize {
                acc += tmp[reflect(y as isize + d, h) * w + x];
            }
            *out = acc / area;
        }
    });
}

/// Joint NLM / bilateral filtering of `data` guided by `colour` (with its per-channel variance
/// `var`) and `features`, for each candidate; returns per candidate the filtered data and the
/// centre weight ratio `w_centre / sum w` per pixel.
pub(crate) fn nlm_candidates(
    colour: &Image,
    var: &Image,
    features: &[Feature],
    data: &Image,
    radius: usize,
    candidates: &[Candidate],
) -> Vec<(Image, Vec<f32>)> {
    let (w, h) = colour.size();
    let n = w * h;
    let dch = data.channels();
    let (c, v, d) = (colour.as_slice(), var.as_slice(), data.as_slice());
    let m = candidates.len();
    let mut num = vec![0.0f32; m * dch * n];
    let mut den = vec![0.0f32; m * n];
    let mut maxw = vec![0.0f32; m * n];
    let mut delta = vec![0.0f32; n];
    let mut weights = vec![0.0f32; m * n];
    let mut dfeat = vec![0.0f32; n];
    let mut patched = vec![vec![0.0f32; n]; 4];
    let mut tmp = Vec::new();
    let r = radius as isize;
    for oy in -r..=r {
        for ox in -r..=r {
            if ox == 0 && oy == 0 {
                continue;
            }
            // Column map of this offset, computed once: the inner loops have no division.
            let qx: Vec<usize> = (0..w).map(|x| reflect(x as isize + ox, w)).collect();
            let qx = &qx;
            delta.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
                let (o, qo) = (y * w, reflect(y as isize + oy, h) * w);
                for (x, out) in row.iter_mut().enumerate() {
                    let (i, q) = (o + x, qo + qx[x]);
                    let mut acc = 0.0;
                    for ch in 0..3 {
                        let (vp, vq) = (v[ch * n + i], v[ch * n + q]);
                        let diff = c[ch * n + i] - c[ch * n + q];
                        acc += (diff * diff - (vp + vp.min(vq))) / (1e-10 + vp + vq);
                    }
                    *out = acc / 3.0;
                }
            });
            dfeat.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
                let (o, qo) = (y * w, reflect(y as isize + oy, h) * w);
                for (x, out) in row.iter_mut().enumerate() {
                    let (i, q) = (o + x, qo + qx[x]);
                    let mut worst = 0.0f32;
                    for f in features {
                        let (fs, ch) = (f.img.as_slice(), f.img.channels());
                        let mut acc = 0.0;
                        for k in 0..ch {
                            let diff = fs[k * n + i] - fs[k * n + q];
                            acc += diff * diff;
                        }
                        worst = worst.max(acc / ch as f32 / f.norm[i]);
                    }
                    *out = worst;
                }
            });
            for (k, cand) in candidates.iter().enumerate() {
                if cand.kc.is_some() {
                    box_mean(&delta, w, h, cand.patch, &mut tmp, &mut patched[k]);
                }
            }
            // One weight image per candidate (one exp per pixel), then accumulate.
            let (patched, dfeat) = (&patched, &dfeat);
            weights
                .par_chunks_mut(n)
                .zip(den.par_chunks_mut(n).zip(maxw.par_chunks_mut(n)))
                .enumerate()
                .for_each(|(k, (wk, (dn, mx)))| {
                    let cand = candidates[k];
                    for i in 0..n {
                        let dist = match cand.kc {
                            Some(kc) => (patched[k][i] / (kc * kc)).max(dfeat[i]),
                            None => dfeat[i],
                        };
                        let wgt = (-dist.max(0.0)).exp();
                        wk[i] = wgt;
                        dn[i] += wgt;
                        mx[i] = mx[i].max(wgt);
                    }
                });
            let weights = &weights;
            num.par_chunks_mut(n).enumerate().for_each(|(kc_idx, acc)| {
                let (k, ch) = (kc_idx / dch, kc_idx % dch);
                let wk = &weights[k * n..(k + 1) * n];
                for (y, row) in acc.chunks_mut(w).enumerate() {
                    let qy = reflect(y as isize + oy, h) * w;
                    let src = &d[ch * n + qy..ch * n + qy + w];
                    for (x, a) in row.iter_mut().enumerate() {
                        *a += wk[y * w + x] * src[qx[x]];
                    }
                }
            });
        }
    }
    (0..m)
        .map(|k| {
            let mut out = Image::zeros(dch, h, w);
            let mut ratio = vec![0.0f32; n];
            let o = out.as_mut_slice();
            for i in 0..n {
                let wc = maxw[k * n + i].max(1e-3);
                let total = den[k * n + i] + wc;
                ratio[i] = wc / total;
                for ch in 0..dch {
                    o[ch * n + i] = (num[(k * dch + ch) * n + i] + wc * d[ch * n + i]) / total;
                }
            }
            (out, ratio)
        })
        .collect()
}

/// The RDFC pre-denoised guide of `colour` (variance of the mean `var`).
pub(crate) fn rdfc(
    colour: &Image,
    var: &Image,
    albedo: Option<&Image>,
    normal: Option<&Image>,
) -> Image {
    let (w, h) = colour.size();
    let n = w * h;
    let features: Vec<Feature> = albedo.into_iter().chain(normal).map(Feature::new).collect();
    let filtered = nlm_candidates(colour, var, &features, colour, 10, &CANDIDATES);
    // SURE per candidate, smoothed by a 3 x 3 box.
    let (c, v) = (colour.as_slice(), var.as_slice());
    let mut tmp = Vec::new();
    let sure: Vec<Vec<f32>> = filtered
        .iter()
        .map(|(f, ratio)| {
            let fs = f.as_slice();
            let raw: Vec<f32> = (0..n)
                .map(|i| {
                    (0..3)
                        .map(|ch| {
                            let (e, vv) = (fs[ch * n + i] - c[ch * n + i], v[ch * n + i]);
                            e * e - vv + 2.0 * vv * ratio[i]
                        })
                        .sum()
                })
                .collect();
            let mut smooth = vec![0.0; n];
            box_mean(&raw, w, h, 1, &mut tmp, &mut smooth);
            smooth
        })
        .collect();
    let m = filtered.len();
    let onehot = Image::from_fn(m, h, w, |(k, y, x)| {
        let i = y * w + x;
        let best = (0..m)
            .min_by(|&a, &b| sure[a][i].total_cmp(&sure[b][i]))
            .unwrap_or(0);
        f32::from(u8::from(best == k))
    });
    let sel = nlm_candidates(
        colour,
        var,
        &features,
        &onehot,
        3,
        &[Candidate {
            patch: 1,
            kc: Some(0.5),
        }],
    )
    .remove(0)
    .0;
    let s = sel.as_slice();
    Image::from_fn(3, h, w, |(ch, y, x)| {
        let i = y * w + x;
        let (mut acc, mut tot) = (0.0, 0.0);
        for (k, (f, _)) in filtered.iter().enumerate() {
            acc += s[k * n + i] * f.as_slice()[ch * n + i];
            tot += s[k * n + i];
        }
        if tot > 0.0 {
            acc / tot
        } else {
            c[ch * n + i]
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_variance_returns_the_input() {
        let (w, h) = (24, 16);
        let img = Image::from_fn(3, h, w, |(c, y, x)| {
            ((x * 3 + y * 5 + c) % 7) as f32 * 0.1 + 0.05
        });
        let out = rdfc(&img, &Image::zeros(3, h, w), None, None);
        let d = out
            .as_slice()
            .iter()
            .zip(img.as_slice())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(d < 1e-5, "{d}");
    }

    #[test]
    fn noise_is_reduced_on_a_flat_image() {
        let (w, h) = (32, 32);
        let mut s = 1u64;
        let mut rnd = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 0.2
        };
        let img = Image::from_fn(3, h, w, |_| 0.5 + rnd());
        let var = Image::from_fn(3, h, w, |_| 0.2 * 0.2 / 12.0);
        let out = rdfc(&img, &var, None, None);
        let mse = |a: &Image| {
            a.as_slice()
                .iter()
                .map(|v| (v - 0.5) * (v - 0.5))
                .sum::<f32>()
        };
        assert!(
            mse(&out) < 0.2 * mse(&img),
            "{} vs {}",
            mse(&out),
            mse(&img)
        );
    }

    #[test]
    fn box_mean_of_a_constant_is_the_constant() {
        let src = vec![2.0f32; 7 * 5];
        let (mut tmp, mut dst) = (Vec::new(), vec![0.0; 35]);
        box_mean(&src, 7, 5, 3, &mut tmp, &mut dst);
        assert!(dst.iter().all(|&v| (v - 2.0).abs() < 1e-6));
    }
}
