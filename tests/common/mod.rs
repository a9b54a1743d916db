//! Independent references for the solver tests: the screened Poisson problem written as an
//! explicit sparse least-squares system (one row per residual, as in the energy's definition)
//! and solved by plain f64 conjugate gradients on the normal equations, plus a naive f64 IRLS
//! built on it. Nothing here shares code with the library's solvers.
#![allow(dead_code)]

use gdrecon::{Frame, FrameBuilder, Image, Layer, Policy};

/// Deterministic pseudo-random numbers for test data.
pub struct Lcg(pub u64);

impl Lcg {
    pub fn uniform(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64) / ((1u64 << 53) as f64)
    }
    pub fn signed(&mut self) -> f64 {
        2.0 * self.uniform() - 1.0
    }
}

/// One residual row: sum_k coef_k * I[idx_k] - target, one row per channel.
#[derive(Clone)]
pub struct Row {
    pub terms: Vec<(usize, f64)>,
    pub target: [f64; 3],
}

/// The screened Poisson residual rows of a frame: data rows `alpha (I - I_b)`, then the
/// `w - 1` horizontal and `h - 1` vertical difference rows per line / column.
pub fn residual_rows(frame: &Frame, alpha: f64) -> Vec<Row> {
    let (w, h) = frame.size();
    let get = |img: &Image, c: usize, x: usize, y: usize| f64::from(img.at(c, x, y));
    let mut rows = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            rows.push(Row {
                terms: vec![(i, alpha)],
                target: std::array::from_fn(|c| alpha * get(frame.color(), c, x, y)),
            });
            if x + 1 < w {
                rows.push(Row {
                    terms: vec![(i + 1, 1.0), (i, -1.0)],
                    target: std::array::from_fn(|c| get(frame.dx(), c, x, y)),
                });
            }
            if y + 1 < h {
                rows.push(Row {
                    terms: vec![(i + w, 1.0), (i, -1.0)],
                    target: std::array::from_fn(|c| get(frame.dy(), c, x, y)),
                });
            }
        }
    }
    rows
}

/// Solves min sum_rows weight_row * (row . I - target)^2 per channel by f64 CG on the normal
/// equations to a relative residual of `tol`; returns planar [c][pixel].
pub fn weighted_lsq(
    rows: &[Row],
    weights: &[f64],
    n: usize,
    x0: &[Vec<f64>],
    tol: f64,
) -> Vec<Vec<f64>> {
    let apply = |v: &[f64]| -> Vec<f64> {
        let mut out = vec![0.0; n];
        for (row, &wt) in rows.iter().zip(weights) {
            let r: f64 = row.terms.iter().map(|&(i, c)| c * v[i]).sum();
            for &(i, c) in &row.terms {
                out[i] += wt * c * r;
            }
        }
        out
    };
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    (0..3)
        .map(|ch| {
            let mut b = vec![0.0; n];
            for (row, &wt) in rows.iter().zip(weights) {
                for &(i, c) in &row.terms {
                    b[i] += wt * c * row.target[ch];
                }
            }
            let mut x = x0[ch].clone();
            let ax = apply(&x);
            let mut r: Vec<f64> = b.iter().zip(&ax).map(|(b, a)| b - a).collect();
            let mut p = r.clone();
            let mut rr = dot(&r, &r);
            let bb = dot(&b, &b).max(1e-300);
            for _ in 0..100 * n {
                if rr <= tol * tol * bb {
                    break;
                }
                let q = apply(&p);
                let a = rr / dot(&p, &q);
                for i in 0..n {
                    x[i] += a * p[i];
                    r[i] -= a * q[i];
                }
                let rr_new = dot(&r, &r);
                let beta = rr_new / rr;
                rr = rr_new;
                for i in 0..n {
                    p[i] = r[i] + beta * p[i];
                }
            }
            x
        })
        .collect()
}

/// The exact L2 screened Poisson solution, by the sparse reference.
pub fn reference_l2(frame: &Frame, alpha: f64) -> Vec<Vec<f64>> {
    let rows = residual_rows(frame, alpha);
    let n = frame.width() * frame.height();
    let x0: Vec<Vec<f64>> = (0..3).map(|_| vec![0.0; n]).collect();
    weighted_lsq(&rows, &vec![1.0; rows.len()], n, &x0, 1e-10)
}

/// Naive IRLS for the group-L1 energy with the published weight rule and schedule, the
/// regularisation held at `reg_floor` once it halves below it.
pub fn reference_l1(frame: &Frame, alpha: f64, steps: u32, reg_floor: f64) -> Vec<Vec<f64>> {
    let rows = residual_rows(frame, alpha);
    let n = frame.width() * frame.height();
    let mut x: Vec<Vec<f64>> = (0..3)
        .map(|c| {
            frame
                .color()
                .plane(c)
                .iter()
                .map(|&v| f64::from(v))
                .collect()
        })
        .collect();
    let mut weights = vec![1.0; rows.len()];
    for k in 0..steps {
        if k > 0 {
            let reg = (0.05 * 0.5f64.powi(k as i32 - 1)).max(reg_floor);
            for (row, wt) in rows.iter().zip(weights.iter_mut()) {
                let e2: f64 = (0..3)
                    .map(|c| {
                        let v: f64 = row.terms.iter().map(|&(i, co)| co * x[c][i]).sum::<f64>()
                            - row.target[c];
                        v * v
                    })
                    .sum();
                *wt = 1.0 / (e2.sqrt() + reg);
            }
            let mean = weights.iter().sum::<f64>() / weights.len() as f64;
            weights.iter_mut().for_each(|w| *w /= mean);
        }
        x = weighted_lsq(&rows, &weights, n, &x, 1e-12);
    }
    x
}

/// Group-L1 energy of a planar f64 solution.
pub fn l1_energy(frame: &Frame, alpha: f64, x: &[Vec<f64>]) -> f64 {
    residual_rows(frame, alpha)
        .iter()
        .map(|row| {
            (0..3)
                .map(|c| {
                    let v: f64 =
                        row.terms.iter().map(|&(i, co)| co * x[c][i]).sum::<f64>() - row.target[c];
                    v * v
                })
                .sum::<f64>()
                .sqrt()
        })
        .sum()
}

/// An image as planar f64.
pub fn to_f64(img: &Image) -> Vec<Vec<f64>> {
    (0..img.channels())
        .map(|c| img.plane(c).iter().map(|&v| f64::from(v)).collect())
        .collect()
}

/// Max |a - b| / max |b| over all values.
pub fn rel_max_diff(a: &[Vec<f64>], b: &[Vec<f64>]) -> f64 {
    let scale = b
        .iter()
        .flatten()
        .fold(0.0f64, |m, v| m.max(v.abs()))
        .max(1e-30);
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
        / scale
}

/// A smooth test image with an edge, `(x, y)` -> RGB.
pub fn test_image(w: usize, h: usize) -> Image {
    Image::from_fn(3, w, h, |(c, x, y)| {
        let (u, v) = (x as f32 / w as f32, y as f32 / h as f32);
        let edge = if u + 0.5 * v > 0.6 { 0.8 } else { 0.1 };
        0.3 + 0.2 * (6.0 * u + c as f32).sin() * (4.0 * v).cos() + edge + 0.1 * c as f32
    })
}

/// Exact forward differences of `img` (0 in the last column / row).
pub fn exact_gradients(img: &Image) -> (Image, Image) {
    img.forward_differences()
}
/// A frame from planar images.
pub fn frame(color: Image, dx: Image, dy: Image) -> Frame {
    FrameBuilder::new()
        .image(Layer::Color, color)
        .image(Layer::Dx, dx)
        .image(Layer::Dy, dy)
        .build(Policy::Replace)
        .unwrap()
}

/// `frame` with `prior` as its `prior` layer, as a renderer that ran its own denoiser hands
/// it over (the frame's layers are clean already: nothing is replaced).
pub fn with_prior(frame: Frame, prior: Image) -> Frame {
    frame
        .into_builder()
        .image(Layer::Prior, prior)
        .build(Policy::Replace)
        .unwrap()
}

/// A noisy frame: base = image + noise, gradients = exact + smaller noise.
pub fn noisy_frame(w: usize, h: usize, seed: u64) -> (Frame, Image) {
    let clean = test_image(w, h);
    let (dx, dy) = exact_gradients(&clean);
    let mut rng = Lcg(seed);
    let mut noisy = |img: &Image, s: f64| {
        Image::from_fn(3, w, h, |(c, x, y)| {
            img.at(c, x, y) + (s * rng.signed()) as f32
        })
    };
    let color = noisy(&clean, 0.2);
    let dx = noisy(&dx, 0.05);
    let dy = noisy(&dy, 0.05);
    (frame(color, dx, dy), clean)
}
