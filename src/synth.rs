//! Synthetic gradient-domain frames with a known reference, for demos, tests and benchmarks.
//!
//! The scene is analytic: a smooth sky ramp, a shaded sphere, a bright emitter strip and a
//! checkerboard floor with hard edges. The frame imitates a gradient-domain renderer's output:
//! the base image is the reference plus heteroscedastic noise (standard deviation growing with
//! radiance, falling as `1/sqrt(spp)`, with rare fireflies), and the gradients are the exact
//! forward differences of the reference plus noise about three times smaller (random replay
//! correlates the base and offset paths), with rare gradient outliers. Features (albedo,
//! normal, depth) are exact and noise-free; the variance layer is the noise model's variance,
//! fireflies included (a renderer's sample variance sees them).
//! The generator is deterministic for a seed. It is no substitute for real renders, only a
//! frame whose answer is known.

use crate::frame::{Frame, FrameBuilder, Layer};
use crate::image::Image;
use crate::validate::Policy;

/// SplitMix64: tiny, fast and good enough for noise; fixed so frames are reproducible.
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn uniform(&mut self) -> f32 {
        ((self.next_u64() >> 40) as f32 + 0.5) / (1u64 << 24) as f32
    }

    fn normal(&mut self) -> f32 {
        let (u, v) = (self.uniform(), self.uniform());
        (-2.0 * u.ln()).sqrt() * (std::f32::consts::TAU * v).cos()
    }
}

/// The analytic scene at pixel centre `(x, y)`: (radiance, albedo, normal, depth).
fn scene(x: f32, y: f32, w: f32, h: f32) -> ([f32; 3], [f32; 3], [f32; 3], f32) {
    let (u, v) = (x / w, y / h);
    let (cx, cy, r) = (0.62 * w, 0.45 * h, 0.22 * h.min(w));
    let (dx, dy) = ((x - cx) / r, (y - cy) / r);
    let d2 = dx * dx + dy * dy;
    if (0.08..0.12).contains(&v) && (0.15..0.55).contains(&u) {
        // Emitter strip: very bright, a classic source of fireflies.
        return ([8.0, 7.5, 6.0], [0.0; 3], [0.0, 0.0, 1.0], 5.0);
    }
    if d2 < 1.0 {
        let nz = (1.0 - d2).sqrt();
        let n = [dx, -dy, nz];
        let light = (0.3 * n[0] + 0.5 * n[1] + 0.8 * n[2]).max(0.0);
        let alb = [0.8, 0.25, 0.2];
        let l = 0.05 + 1.4 * light;
        return (alb.map(|a| a * l), alb, n, 3.0 - nz);
    }
    if v > 0.6 {
        // Floor: checkerboard in perspective, soft shadow of the sphere.
        let depth = 1.0 + 2.0 / (v - 0.55);
        let check = ((u * depth * 2.0).floor() as i64 + (depth * 1.5).floor() as i64) & 1;
        let alb = if check == 0 {
            [0.7, 0.7, 0.65]
        } else {
            [0.15, 0.2, 0.3]
        };
        let sx = (x - cx) / (1.3 * r);
        let sy = (y - 0.78 * h) / (0.35 * r);
        let shadow = 1.0 - 0.8 * (-(sx * sx + sy * sy)).exp();
        let l = 0.9 * shadow;
        return (alb.map(|a| a * l), alb, [0.0, 1.0, 0.0], depth);
    }
    let sky = [0.3 + 0.5 * v, 0.45 + 0.4 * v, 0.8];
    (sky, [0.0; 3], [0.0, 0.0, -1.0], 100.0)
}

/// The largest synthetic frame, in pixels (8192 x 8192: its nine layers take 7 GiB).
pub const MAX_PIXELS: usize = 1 << 26;

/// Checks a synthetic frame's size before anything is allocated: both sides positive, the
/// product at most [`MAX_PIXELS`] (a size from a command line must never abort the process).
pub fn check_size(width: usize, height: usize) -> crate::error::Result<()> {
    match width.checked_mul(height) {
        Some(n) if n > 0 && n <= MAX_PIXELS => Ok(()),
        _ => Err(crate::error::Error::arg(format!(
            "a synthetic frame of {width} x {height}: the size must be positive and at most \
             {MAX_PIXELS} pixels (8192 x 8192)"
        ))),
    }
}

/// A synthetic frame of `width` x `height` at `spp` samples per pixel, with its reference
/// layer. Deterministic for a seed. Callers taking sizes from outside check them with
/// [`check_size`] first.
pub fn synthetic_frame(width: usize, height: usize, spp: f32, seed: u64) -> Frame {
    let (w, h) = (width, height);
    let (wf, hf) = (w as f32, h as f32);
    let mut reference = Image::zeros(3, w, h);
    let mut albedo = Image::zeros(3, w, h);
    let mut normal = Image::zeros(3, w, h);
    let mut depth = Image::zeros(1, w, h);
    for y in 0..h {
        for x in 0..w {
            let (rad, alb, nrm, dep) = scene(x as f32 + 0.5, y as f32 + 0.5, wf, hf);
            for c in 0..3 {
                reference.planes_mut()[[c, y, x]] = rad[c];
                albedo.planes_mut()[[c, y, x]] = alb[c];
                normal.planes_mut()[[c, y, x]] = nrm[c];
            }
            depth.planes_mut()[[0, y, x]] = dep;
        }
    }
    let mut rng = Rng(seed ^ 0x6764_7265_636F_6E00);
    let inv_sqrt_spp = 1.0 / spp.max(1e-3).sqrt();
    let sigma = |r: f32| (0.6 * r.sqrt() + 0.05) * inv_sqrt_spp;
    let mut color = reference.clone();
    let mut variance = Image::zeros(3, w, h);
    for c in 0..3 {
        for y in 0..h {
            for x in 0..w {
                let r = reference.at(c, x, y);
                let s = sigma(r);
                let mut v = r + s * rng.normal();
                let mut var = s * s;
                if rng.uniform() < 2e-4 {
                    // A firefly adds f to the pixel's mean: one of its spp samples carried
                    // f * spp, so the samples' variance of the mean (what a renderer writes)
                    // grows by about f^2. Without it the layer would call the spike certain
                    // and a noise band would keep it.
                    let f = 50.0 * rng.uniform();
                    v += f;
                    var += f * f;
                }
                color.planes_mut()[[c, y, x]] = v.max(0.0);
                variance.planes_mut()[[c, y, x]] = var;
            }
        }
    }
    let mut gradient = |axis_x: bool| {
        let mut g = Image::zeros(3, w, h);
        for c in 0..3 {
            for y in 0..h {
                for x in 0..w {
                    let (nx, ny) = if axis_x { (x + 1, y) } else { (x, y + 1) };
                    if nx >= w || ny >= h {
                        continue;
                    }
                    let (a, b) = (reference.at(c, x, y), reference.at(c, nx, ny));
                    let s = 0.35 * (sigma(a) + sigma(b)) * 0.5;
                    let mut d = b - a + s * rng.normal();
                    if rng.uniform() < 1e-4 {
                        d += 30.0 * (rng.uniform() - 0.5);
                    }
                    g.planes_mut()[[c, y, x]] = d;
                }
            }
        }
        g
    };
    let dx = gradient(true);
    let dy = gradient(false);
    FrameBuilder::new()
        .image(Layer::Color, color)
        .image(Layer::Dx, dx)
        .image(Layer::Dy, dy)
        .image(Layer::Variance, variance)
        .image(Layer::Albedo, albedo)
        .image(Layer::Normal, normal)
        .image(Layer::Depth, depth)
        .image(Layer::Reference, reference)
        .spp(Some(spp))
        .build(Policy::Replace)
        .expect("the synthetic frame is valid by construction")
}
