//! Filtering-based reconstruction (FRGR, Yan et al. 2024): gradient outlier removal, a
//! pre-denoised guide (RDFC, or our L1), then coarse to fine over 2x levels linked by guided
//! linear upsampling (GLU): per level, gradient enhancement and the gradient-guided filter QP,
//! whose result, upsampled, guides the next finer level.

pub(crate) mod enhance;
pub(crate) mod fastmath;
pub(crate) mod glu;
pub(crate) mod outliers;
pub(crate) mod prefilter;
pub(crate) mod qp;
pub(crate) mod rdfc;
pub(crate) mod util;

use std::borrow::Cow;

use rayon::prelude::*;

use super::band::{self, banded, BandScope, BAND_TRIM, NOISE_BAND};
use super::converged::converged_mask;
use super::param::{choices, Param, Params, Preset, Range};
use super::poisson_l1::{l1_memory, PoissonL1};
use super::prior::{prior_memory, Prior, Quality, Scratch};
use super::{bytes_for, Method, PoissonL1Config, Reconstructor, Register, MIB};
use crate::context::Context;
use crate::error::{Error, Result};
use crate::frame::Frame;
use crate::frame::{FrameBuilder, Layer};
use crate::image::Image;
use crate::progress::Progress;
use crate::report::Report;
use crate::validate::Policy;

/// Which pre-denoised image guides the filter (its `L_d` term and the start of the
/// gradient enhancement).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum FrgrGuide {
    /// RDFC's first pass, as the authors' release does (the reference mode).
    Rdfc,
    /// Our screened Poisson L1 reconstruction: cheaper and, on the bundled sample, a better
    /// guide (relMSE 8.6e-4 vs 1.4e-3), which the filter's output follows closely at low spp
    /// since the guide term's weight is `8 / sqrt(spp)`.
    PoissonL1,
    /// No pre-denoiser: the noisy colour itself (the ablation of the pre-denoiser).
    Colour,
    /// The prior (`recon::prior`): the frame's `prior` layer, or Open Image Denoise on the
    /// base image. A far better guide than RDFC, which it replaces.
    Prior,
}

// The C indices are `GDR_FRGR_GUIDE_*`.
choices!(FrgrGuide {
    Rdfc => "rdfc",
    PoissonL1 => "l1",
    Colour => "none",
    Prior => "prior",
});

/// Settings of FRGR (`frgr`); names, defaults and ranges are in its parameter table
/// below (listed in `docs/PARAMETERS.md`).
#[derive(Clone, Copy, Debug, PartialEq)]
#[non_exhaustive]
pub struct FrgrConfig {
    /// Filter window radius; 0 (the default): by the guide, [`FrgrConfig::window_radius`]
    /// (the release has 4, 9 x 9 windows).
    pub radius: usize,
    /// Resolution levels, each 2x coarser, linked by guided linear upsampling.
    pub levels: usize,
    /// Gradient-enhancement iterations; 0 skips the enhancement.
    pub enhance_iterations: u32,
    /// Take the enhancement's steps after its last possible revert at once, as a Chebyshev
    /// polynomial (the steps' image within f32 rounding, in a quarter of the products or
    /// fewer); false: one step at a time, as the release.
    pub enhance_chebyshev: bool,
    /// The pre-denoiser.
    pub guide: FrgrGuide,
    /// Prefilter albedo and normal before every stage reads them.
    pub prefilter: bool,
    /// ... on frames of fewer samples per pixel than this only (default 16: from 16 spp the
    /// prefilter's noise bound blurs curved surfaces more than it denoises; 1e9: always).
    pub prefilter_below: f32,
    /// Window radius of the RDFC guide's candidate filters (10, 21 x 21, in the release).
    pub rdfc_radius: usize,
    /// Half-width of the noise band the output is clamped to, in standard deviations of the
    /// base image's noise (`recon/band.rs`); 0: off.
    pub noise_band: f32,
    /// The noise band's trimming ratio at 64 spp or more (`recon/band.rs`); 0: never trimmed.
    pub band_trim: f32,
    /// Below 64 spp also trim the band of bright neighbours the gradients confirm as an
    /// object's edge (`recon/emitters.rs`): FRGR spreads lamps into the dark around them.
    pub band_emitters: bool,
    /// Where the band clamps: every pixel, or only beside an emitter's edge (`recon/band.rs`).
    pub band_scope: BandScope,
    /// OIDN's scratch memory when it computes the prior: lowered by a memory limit
    /// ([`Register::fit_memory`]), not a parameter.
    pub(crate) scratch: Scratch,
}

impl Default for FrgrConfig {
    fn default() -> Self {
        FrgrConfig {
            radius: 0,
            levels: 2,
            enhance_iterations: 250,
            enhance_chebyshev: true,
            guide: FrgrGuide::Rdfc,
            prefilter: true,
            prefilter_below: PREFILTER_BELOW,
            rdfc_radius: rdfc::RADIUS,
            noise_band: NOISE_BAND,
            band_trim: BAND_TRIM,
            band_emitters: true,
            band_scope: BandScope::All,
            scratch: Scratch::default(),
        }
    }
}

impl FrgrConfig {
    /// The filter window radius used: `radius`, or when it is 0, 3 (7 x 7 windows) with a
    /// guide of our own (RDFC, L1, none) and the release's 4 (9 x 9) with the prior's, each the
    /// better on validation and on test (`docs/benchmarks.md`, "Forty-sixth session").
    pub fn window_radius(&self) -> usize {
        match (self.radius, self.guide) {
            (0, FrgrGuide::Prior) => REFERENCE_RADIUS,
            (0, _) => RADIUS,
            (r, _) => r,
        }
    }

    /// The release's settings, literally: the reference mode (1000 enhancement iterations,
    /// taken one by one; no noise band), kept for comparison with the default.
    pub fn reference() -> Self {
        FrgrConfig {
            radius: REFERENCE_RADIUS,
            enhance_iterations: REFERENCE_ENHANCE_ITERATIONS,
            enhance_chebyshev: false,
            noise_band: 0.0,
            prefilter_below: PREFILTER_ALWAYS,
            ..FrgrConfig::default()
        }
    }

    /// Faster at a cost on some frames: RDFC's candidate filters over 11 x 11 windows (121
    /// offsets instead of 441) and the filter over 5 x 5 windows (25 weights a pixel instead
    /// of 49). The first setting that ran under OIDN's time at 1280 x 720 on an AVX2 CPU
    /// (0.89-0.91x against the default's 1.64-1.65x); relMSE +2.4 / -0.5 / +0.1 % at 4 / 16 /
    /// 64 spp on validation (worst frame +27 %), +8.6 / +10.8 / +1.8 % on test (worst +52 %,
    /// `lamps` at 16 spp): `docs/benchmarks.md`, "Forty-eighth session".
    pub fn fast() -> Self {
        FrgrConfig {
            radius: FAST_RADIUS,
            rdfc_radius: FAST_RDFC_RADIUS,
            ..FrgrConfig::default()
        }
    }
}

impl Params for FrgrConfig {
    const TABLE: &'static [Param<Self>] = &[
        Param::int(
            "radius",
            0,
            4,
            "Filter window radius (4: 9 x 9 windows, as the release); 0: by the guide, 3 with \
             RDFC, L1 or none (validation: relMSE -2.2 / -2.3 / -1.6 % at 4 / 16 / 64 spp \
             against 4 with RDFC, the QP 1.6x faster), 4 with the prior (3 there: +1.0 / +0.5 / \
             +0.3 %); 1 and 2 are faster and less accurate",
            |c| c.radius as i64,
            |c, v| c.radius = v as usize,
        ),
        // Two levels as the release (bundled sample: 1.37e-3 -> 1.15e-3 with the RDFC guide,
        // 7.9e-4 -> 6.1e-4 with the L1 guide).
        Param::int(
            "levels",
            1,
            4,
            "Resolution levels, each 2x coarser, linked by guided linear upsampling",
            |c| c.levels as i64,
            |c, v| c.levels = v as usize,
        ),
        // Why 250 (the release runs 1000, `reference`): the descent is stopped early to
        // regularise it, and on the validation set stopping sooner is no worse
        // (docs/benchmarks.md: relMSE 0.62 % lower over 18 frames, 4 worse by at most 0.66 %).
        Param::int(
            "enhance_iterations",
            0,
            100_000,
            "Gradient-enhancement iterations (the release: 1000); 0 skips the enhancement",
            |c| c.enhance_iterations.into(),
            |c, v| c.enhance_iterations = v as u32,
        ),
        Param::bool(
            "enhance_chebyshev",
            "Once the enhancement's step can no longer be halved (it lowers the energy at \
             every step, by Gershgorin's bound), take its remaining steps at once as one \
             Chebyshev polynomial of the same operator: the steps' image within f32 rounding \
             (relMSE between the two 1e-13 on real frames), in about 3.5 sqrt(steps) products \
             instead of the steps; false: step by step, as the release",
            |c| c.enhance_chebyshev,
            |c, v| c.enhance_chebyshev = v,
        ),
        Param::choice(
            "guide",
            FrgrGuide::NAMES,
            "The pre-denoised guide: RDFC (the release), our L1 reconstruction, none (the \
             noisy colour, an ablation), or the prior (the frame's 'prior' layer, else Open \
             Image Denoise on the base image)",
            |c| c.guide.index(),
            |c, v| c.guide = FrgrGuide::ALL[v],
        ),
        Param::int(
            "rdfc_radius",
            1,
            10,
            "Window radius of the RDFC guide's three candidate filters: 10 (21 x 21 windows) \
             as the release; smaller is faster and less accurate (7: RDFC 0.82 s instead of \
             1.40 s at 1280 x 720, relMSE +1.5 / +0.2 / -1.2 % at 4 / 16 / 64 spp on \
             validation, +4.4 / +4.7 / +0.4 % on test)",
            |c| c.rdfc_radius as i64,
            |c, v| c.rdfc_radius = v as usize,
        ),
        Param::bool(
            "prefilter",
            "Prefilter albedo and normal (variance-aware bilateral, as the release) before \
             every stage reads them",
            |c| c.prefilter,
            |c, v| c.prefilter = v,
        ),
        Param::float(
            "prefilter_below",
            Range::closed(0.0, PREFILTER_ALWAYS as f64),
            "With prefilter, prefilter only frames of fewer spp than this: from 16 spp the \
             features are clean enough, and the prefilter's noise bound blurs curved surfaces \
             and edges (validation -0.4 / -0.6 % relMSE at 16 / 64 spp without it, +2.2 % at \
             4); 1e9: always, as the release",
            |c| c.prefilter_below,
            |c, v| c.prefilter_below = v,
        ),
        band::param(|c| c.noise_band, |c, v| c.noise_band = v),
        band::trim_param(|c| c.band_trim, |c, v| c.band_trim = v),
        band::emitters_param(|c| c.band_emitters, |c, v| c.band_emitters = v),
        band::scope_param(
            |c| c.band_scope.index(),
            |c, v| c.band_scope = BandScope::ALL[v],
        ),
    ];

    const PRESETS: &'static [Preset<Self>] = &[
        Preset {
            name: "reference",
            doc: "the release's schedule literally: 1000 gradient-enhancement iterations, \
                  taken one by one, the prefilter at any spp, no noise band",
            config: FrgrConfig::reference,
        },
        Preset {
            name: "fast",
            doc: "about half the default's time: RDFC over 11 x 11 windows (rdfc_radius 5) and \
                  5 x 5 filter windows (radius 2); relMSE +2.4 / -0.5 / +0.1 % at 4 / 16 / \
                  64 spp on validation (worst frame +27 %), +8.6 / +10.8 / +1.8 % on test \
                  (worst +52 %)",
            config: FrgrConfig::fast,
        },
    ];
}

impl Register for FrgrConfig {
    const SWEEP: &'static [&'static str] = &[
        "",
        "reference",
        "fast",
        "radius=4",
        "levels=1",
        "guide=l1",
        "enhance_iterations=0",
        "guide=none",
        "prefilter=false",
    ];
    const PRIOR_SWEEP: &'static [&'static str] = &["guide=prior"];

    fn plan(
        &self,
        context: &Context,
        width: usize,
        height: usize,
    ) -> Result<Box<dyn Reconstructor>> {
        let inner = Box::new(Frgr::new(context, *self, width, height)?);
        Ok(banded(
            inner,
            self.noise_band,
            self.band_trim,
            self.band_emitters,
            self.band_scope,
        ))
    }

    fn memory_estimate(&self, width: usize, height: usize) -> u64 {
        let own = bytes_for(width, height, FRGR_BYTES_PER_PIXEL, 4 * MIB);
        let guide = match self.guide {
            FrgrGuide::PoissonL1 => l1_memory(&PoissonL1Config::default(), width, height)
                .saturating_add(bytes_for(width, height, 12, 0)),
            FrgrGuide::Prior => prior_memory(width, height, self.scratch),
            FrgrGuide::Rdfc | FrgrGuide::Colour => 0,
        };
        own.saturating_add(guide)
    }

    fn fit_memory(&mut self, width: usize, height: usize, limit: u64) {
        if self.guide == FrgrGuide::Prior {
            let own = bytes_for(width, height, FRGR_BYTES_PER_PIXEL, 4 * MIB);
            self.scratch.fit(width, height, limit, own);
        }
    }
}

/// FRGR's own bytes a pixel at its peak (gradients, the level pyramid, RDFC, GLU, enhancement
/// and QP images, the output), without a L1 or prior guide.
///
/// Measured: peak heap above the frame, counting allocator (tests/memory.rs, `peak_table`;
/// the estimate includes the L1 guide's `l1_memory` and output):
///
/// | configuration | 640 x 360 | 1280 x 720 | estimate |
/// | --- | --- | --- | --- |
/// | defaults (RDFC guide), `reference`, `levels=1` | 248.8 B/px | 246.5 B/px | 320 B/px + 4 MiB |
/// | `fast` | 248.1 B/px | 246.2 B/px | 320 B/px + 4 MiB |
/// | `guide=l1` | 321.7 B/px | 321.4 B/px | 444 B/px + 5 MiB |
///
/// (Sixty-fourth session, the enhancement without a copy of its guide and the QP's buffers
/// per worker; before it `guide=l1` 330.1 / 329.7 and `fast` as the defaults. Sixty-third
/// session, RDFC's inputs padded once and its tiles written in place; before it 261.6 and
/// 261.3 B/px with the RDFC guide. The table had said 256.6 / 256.3 and 296.1 for the L1
/// guide: later sessions had raised both without updating it.)
///
/// Peak RSS of `gdrecon reconstruct -m frgr` on the demo bundle minus
/// that of `gdrecon info` (the process and the frame as read) is 42 MiB at 640 x 360 (94512
/// against 51408 KiB) and 148 MiB at 1280 x 720 (331196 against 180216 KiB), 168 B a pixel
/// (the frame's read overlaps it). The estimate takes 320 B a pixel and 4 MiB.
const FRGR_BYTES_PER_PIXEL: u64 = 320;

/// The release's gradient-enhancement iterations.
const REFERENCE_ENHANCE_ITERATIONS: u32 = 1000;

/// The release's filter window radius (9 x 9 windows: 81 weights a pixel).
const REFERENCE_RADIUS: usize = 4;

/// The filter window radius with a guide of our own: 7 x 7 windows (49 weights a pixel),
/// chosen on validation in the forty-sixth session against the release's 4 with the RDFC
/// guide: relMSE -2.2 / -2.3 / -1.6 % at 4 / 16 / 64 spp (geometric means; 20 of 24 frames
/// better, the worst `dusk` 4 spp +4.5 %), and the QP 1.6x faster (its cost goes with the
/// square of the window's pixels, as its sweeps' lengths do). On test, read once after the
/// choice: -0.5 / -0.5 / -1.4 %, no frame worse by 1 %. With the prior's guide 4 stays: 3 was
/// +1.0 / +0.5 / +0.3 % on validation (+2.1 / +0.9 / +0.3 % on test, `lamps` 4 spp +11.5 %).
const RADIUS: usize = 3;

/// The `fast` preset's filter window radius (5 x 5 windows): on validation the means at 4 and
/// 16 spp gain over 3 (-2.3 / -2.6 %), but `dusk` at 64 spp loses 25 % (forty-sixth and
/// forty-eighth sessions), which keeps 3 the default.
const FAST_RADIUS: usize = 2;

/// The `fast` preset's RDFC window radius (11 x 11 windows, 121 offsets): RDFC's cost goes
/// with the offsets, so this is about 0.27x the release's 21 x 21; 7 (0.51x) was not enough
/// to bring the filter under OIDN's time on any CPU measured, 3 lost 9-21 % in the means.
const FAST_RDFC_RADIUS: usize = 5;

/// Default `prefilter_below`: the feature prefilter runs below 16 spp only. Its noise bound
/// (`prefilter.rs`: the 3 x 3 range over spp) mistakes a curved surface or an edge for noise
/// and blends it, which the features' own noise no longer pays for at 16 spp. Chosen on
/// validation by the band's rule (geometric means at most +0.5 %, every frame at most +2 %):
/// without the prefilter 16 spp 0.996x (worst 1.015), 64 spp 0.994x (1.004), 4 spp 1.022x
/// (1.096), so 16. On the guard frame `lamps_16spp` (a black sphere with small lamps: one
/// albedo, normals that curve) FRGR goes from 1.21x its base to 0.39x. Test, read once after
/// the choice: 16 spp 0.942x, 64 spp 0.981x (no frame above 1.005x); new renders of the test
/// families 0.970x / 0.990x at 16 / 64 spp (worst 1.008x), and 1.037x on one older 16 spp one
/// (`docs/benchmarks.md`, thirty-third session).
const PREFILTER_BELOW: f32 = 16.0;

/// `prefilter_below` that prefilters every frame (the release).
const PREFILTER_ALWAYS: f32 = 1e9;

/// Largest input magnitude FRGR runs at; larger frames are scaled down.
const LIMIT: f32 = 1e6;

/// FRGR planned for one size.
///
/// What depends on the size alone is made here: the level pyramid's sizes, the gradient
/// buffers that outlier removal writes, and with the L1 guide its planned solve (DCT plans,
/// IRLS buffers) and output. The stages' intermediate images (RDFC, GLU, enhancement, QP)
/// are allocated per execution, fallibly: a failure is `OutOfMemory`, and the plan stays
/// usable.
pub(crate) struct Frgr {
    cfg: FrgrConfig,
    /// Sizes of the levels that run, finest first.
    levels: Vec<(usize, usize)>,
    /// The gradients with outliers removed, rewritten per execution.
    dx: Image,
    dy: Image,
    /// With the L1 guide: its planned solve and the image it writes.
    l1: Option<(PoissonL1, Image)>,
    /// With the prior guide: where the prior comes from.
    prior: Option<Prior>,
}

impl Frgr {
    /// Plans FRGR for `width` x `height` frames.
    pub(crate) fn new(
        context: &Context,
        config: FrgrConfig,
        width: usize,
        height: usize,
    ) -> Result<Self> {
        let l1 = match config.guide {
            FrgrGuide::PoissonL1 => Some((
                PoissonL1::new(PoissonL1Config::default(), width, height)?,
                Image::try_zeros(3, width, height)?,
            )),
            FrgrGuide::Rdfc | FrgrGuide::Colour | FrgrGuide::Prior => None,
        };
        let prior = (config.guide == FrgrGuide::Prior)
            .then(|| Prior::new(context, width, height, Quality::High, config.scratch))
            .transpose()?;
        Ok(Frgr {
            levels: level_sizes(width, height, config.levels),
            cfg: config,
            dx: Image::try_zeros(3, width, height)?,
            dy: Image::try_zeros(3, width, height)?,
            l1,
            prior,
        })
    }
}

/// The sizes of the levels FRGR runs on a `width` x `height` frame with at most `levels`:
/// each is the previous one padded to even sides and halved, while the previous one's shorter
/// side is at least [`MIN_LEVEL_SIDE`].
fn level_sizes(width: usize, height: usize, levels: usize) -> Vec<(usize, usize)> {
    let mut sizes = vec![(width, height)];
    while let Some(&(w, h)) = sizes.last() {
        if sizes.len() >= levels || w.min(h) < MIN_LEVEL_SIDE {
            break;
        }
        sizes.push(((w + w % 2) / 2, (h + h % 2) / 2));
    }
    sizes
}

/// Per-pixel variance estimate when the frame has none: the sample variance of the 3 x 3
/// neighbourhood's colour (an overestimate at edges, which makes the filter more cautious).
fn estimate_variance(colour: &Image) -> Result<Image> {
    let (w, h) = colour.size();
    Image::try_par_from_fn(3, w, h, |(c, x, y)| {
        let (mut s, mut s2) = (0.0f32, 0.0f32);
        for dy in -1..=1 {
            for dx in -1..=1 {
                let v = colour.at(
                    c,
                    util::reflect(x as isize + dx, w),
                    util::reflect(y as isize + dy, h),
                );
                s += v;
                s2 += v * v;
            }
        }
        ((s2 - s * s / 9.0) / 8.0).max(0.0)
    })
}

/// `img` times `s`; borrowed as it is when `s` is 1.
fn scaled(img: &Image, s: f32) -> Result<Cow<'_, Image>> {
    if s == 1.0 {
        return Ok(Cow::Borrowed(img));
    }
    let mut out = img.try_clone()?;
    out.as_mut_slice().iter_mut().for_each(|v| *v *= s);
    Ok(Cow::Owned(out))
}

/// `dst = src * s`, in place of a copy.
fn copy_scaled(dst: &mut Image, src: &Image, s: f32) {
    copy_scaled_slice(dst.as_mut_slice(), src.as_slice(), s);
}

/// `dst = src * s` (a copy when `s` is 1), in parallel chunks.
fn copy_scaled_slice(dst: &mut [f32], src: &[f32], s: f32) {
    dst.par_chunks_mut(CHUNK)
        .zip(src.par_chunks(CHUNK))
        .for_each(|(dst, src)| {
            dst.copy_from_slice(src);
            if s != 1.0 {
                dst.iter_mut().for_each(|v| *v *= s);
            }
        });
}

/// Values per parallel task of the whole-frame passes here.
const CHUNK: usize = 1 << 16;

/// The largest magnitude in `img` (0 when empty), NaN passed over as `f32::max` passes it.
/// Taken on the values' bits: for magnitudes the order of the bits is the order of the
/// values, and an integer maximum vectorises where `f32::max`'s NaN rule does not (at
/// 1280 x 720 the three images' pass took 11 ms).
fn peak_magnitude(img: &Image) -> f32 {
    const INF: u32 = 0x7f80_0000;
    img.as_slice()
        .par_chunks(CHUNK)
        .map(|chunk| {
            chunk.iter().fold(0u32, |m, v| {
                let bits = v.to_bits() & !(1 << 31);
                m.max(if bits > INF { 0 } else { bits })
            })
        })
        .max()
        .map_or(0.0, f32::from_bits)
}

/// The buffers of one resolution level.
struct LevelInputs<'a> {
    colour: Cow<'a, Image>,
    var: Image,
    dx: Cow<'a, Image>,
    dy: Cow<'a, Image>,
    albedo: Option<Cow<'a, Image>>,
    normal: Option<Cow<'a, Image>>,
    guide: Cow<'a, Image>,
    /// Pixels already converged (finest level only): the QP returns their colour.
    converged: Option<Vec<bool>>,
}

/// Smallest side that is still split into a coarser level.
const MIN_LEVEL_SIDE: usize = 16;

/// Pads gradients to even sizes: reflect-101 like every other buffer, except that the
/// difference across the new border is the negated mirrored one (a mirrored gradient changes
/// sign) and the last column / row stays 0.
fn pad_gradients<'a>(dx: &'a Image, dy: &'a Image) -> Result<(Cow<'a, Image>, Cow<'a, Image>)> {
    let (w, h) = dx.size();
    let (mut px, mut py) = (glu::pad_even(dx)?, glu::pad_even(dy)?);
    if w % 2 == 1 {
        let px = px.to_mut();
        for c in 0..3 {
            for y in 0..py.height() {
                let mirrored = if w >= 2 { -px.at(c, w - 2, y) } else { 0.0 };
                px.planes_mut()[[c, y, w - 1]] = mirrored;
                px.planes_mut()[[c, y, w]] = 0.0;
            }
        }
    }
    if h % 2 == 1 {
        let py = py.to_mut();
        for c in 0..3 {
            for x in 0..px.width() {
                let mirrored = if h >= 2 { -py.at(c, x, h - 2) } else { 0.0 };
                py.planes_mut()[[c, h - 1, x]] = mirrored;
                py.planes_mut()[[c, h, x]] = 0.0;
            }
        }
    }
    Ok((px, py))
}

impl Frgr {
    /// Filters level `depth` of the planned pyramid, recursing into the next coarser one (GLU)
    /// if there is one; returns the result and its variance.
    fn run_level(
        &self,
        inp: &LevelInputs,
        spp: f32,
        depth: usize,
        report: &mut Report,
        progress: &Progress,
    ) -> Result<(Image, Image)> {
        let (w, h) = inp.colour.size();
        assert_eq!(
            (w, h),
            self.levels[depth],
            "level {depth} has its planned size"
        );
        let up = if depth + 1 < self.levels.len() {
            let pad = glu::pad_even;
            let guide = pad(&inp.guide)?;
            let (albedo, normal) = (
                inp.albedo.as_deref().map(pad).transpose()?,
                inp.normal.as_deref().map(pad).transpose()?,
            );
            // GLU's guide: [guide RGB, 0.1 albedo, 0.1 normal], written in place.
            let features: Vec<&Image> = [&albedo, &normal]
                .into_iter()
                .flatten()
                .map(|f| &**f)
                .collect();
            let (pw, ph) = guide.size();
            let mut j = Image::try_zeros(3 + 3 * features.len(), pw, ph)?;
            let (head, tail) = j.as_mut_slice().split_at_mut(guide.as_slice().len());
            copy_scaled_slice(head, guide.as_slice(), 1.0);
            for (dst, f) in tail.chunks_mut(3 * pw * ph).zip(&features) {
                copy_scaled_slice(dst, f.as_slice(), 0.1);
            }
            let fit = report.time(&format!("glu (level {depth})"), || {
                glu::Glu::new_or_stop(&j, progress)
            })?;
            progress.check()?;
            let (pdx, pdy) = pad_gradients(&inp.dx, &inp.dy)?;
            let (cdx, cdy) = fit.downsample_gradients(&pdx, &pdy)?;
            let down = |img: &Image| fit.downsample(img, false).map(Cow::Owned);
            let coarse = LevelInputs {
                colour: down(&*pad(&inp.colour)?)?,
                var: fit.downsample(&*pad(&inp.var)?, true)?,
                dx: Cow::Owned(cdx),
                dy: Cow::Owned(cdy),
                albedo: albedo.map(|a| down(&a)).transpose()?,
                normal: normal.map(|f| down(&f)).transpose()?,
                guide: down(&guide)?,
                converged: None,
            };
            let (r, v) = self.run_level(&coarse, spp, depth + 1, report, progress)?;
            let (u, uv) = fit.upsample(&r, Some(&v))?;
            let uv = uv.expect("variance requested");
            Some((glu::crop(u, w, h)?, glu::crop(uv, w, h)?))
        } else {
            None
        };
        let enhanced = if self.cfg.enhance_iterations == 0 {
            if depth == 0 {
                report.skip("gradient enhancement (0 iterations): the guide stands in");
            }
            Cow::Borrowed(&*inp.guide)
        } else {
            let lambda = 8.0 / spp.sqrt();
            let (enhanced, outcome) = report.time(&format!("enhance (level {depth})"), || {
                let weights = enhance::EnhanceWeights::new(
                    &inp.dx,
                    &inp.dy,
                    inp.albedo.as_deref(),
                    inp.normal.as_deref(),
                    lambda,
                )?;
                enhance::enhance_or_stop(
                    &inp.guide,
                    &inp.dx,
                    &inp.dy,
                    &weights,
                    self.cfg.enhance_iterations,
                    self.cfg.enhance_chebyshev,
                    progress,
                )
            })?;
            progress.check()?;
            let polynomial = outcome.polynomial.map_or(String::new(), |(steps, degree)| {
                format!(" (the last {steps} as a Chebyshev polynomial of degree {degree})")
            });
            report.note(format!(
                "level {depth} ({w} x {h}): enhancement {} iterations{polynomial}, {} reverts, energy {:.4e} -> {:.4e}",
                self.cfg.enhance_iterations, outcome.reverts, outcome.loss_start, outcome.loss_end
            ));
            Cow::Owned(enhanced)
        };
        let mut level = qp::QpLevel {
            img: &inp.colour,
            var: &inp.var,
            enhanced: &enhanced,
            guide: &inp.guide,
            albedo: inp.albedo.as_deref(),
            normal: inp.normal.as_deref(),
            up: up.as_ref().map(|(u, v)| (u, v)),
            spp,
            radius: self.cfg.window_radius(),
            converged: inp.converged.as_deref(),
            dropped: [false; 5],
        };
        level.dropped = qp::vanishing_terms(&level);
        let dropped: Vec<&str> = (0..5)
            .filter(|&a| level.dropped[a])
            .map(|a| qp::TERM_NAMES[a])
            .collect();
        if !dropped.is_empty() {
            report.skip(format!(
                "QP terms of level {depth} whose weight vanishes at {spp} spp (below {:e} of the \
                 objective): {}",
                qp::VANISHING,
                dropped.join(", ")
            ));
        }
        let (out, var, skipped) = report.time(&format!("qp filter (level {depth})"), || {
            qp::filter_or_stop(&level, progress)
        })?;
        progress.check()?;
        if skipped.empty > 0 {
            report.skip(format!(
                "QP on {} empty pixels of level {depth} (zero colour and variance in the window)",
                skipped.empty
            ));
        }
        if skipped.converged > 0 {
            report.skip(format!(
                "QP on {} converged pixels (noise < {} of the value, consistent gradients): base colour kept",
                skipped.converged,
                crate::recon::converged::RELATIVE_NOISE
            ));
        }
        Ok((out, var))
    }
}

impl Reconstructor for Frgr {
    fn method(&self) -> Method {
        Method::Frgr
    }

    fn reconstruct_into(
        &mut self,
        frame: &Frame,
        out: &mut Image,
        report: &mut Report,
        progress: &Progress,
    ) -> Result<()> {
        let spp = frame.spp().ok_or_else(|| {
            Error::input(
                "frgr needs the samples per pixel, and the frame has none (the bundle's spp \
                 attribute, FrameBuilder::spp, C \"spp\" or the CLI's --spp)",
            )
        })?;
        // The filter squares differences and weights them by squared inverses, in f32: a frame
        // whose radiance exceeds 1e6 (garbage, or extreme HDR) is scaled into range first and
        // the result scaled back, so that nothing overflows. Real frames are untouched.
        let peak = [frame.color(), frame.dx(), frame.dy()]
            .iter()
            .map(|img| peak_magnitude(img))
            .fold(0.0f32, f32::max);
        let scale = if peak > LIMIT { LIMIT / peak } else { 1.0 };
        if scale != 1.0 {
            report.note(format!(
                "radiance up to {peak:e}: filtered at scale {scale:e}"
            ));
        }
        let colour = scaled(frame.color(), scale)?;
        let colour = &*colour;
        // The plan's gradient buffers: the frame's gradients, then outlier removal in place.
        let (dx, dy) = (&mut self.dx, &mut self.dy);
        copy_scaled(dx, frame.dx(), scale);
        copy_scaled(dy, frame.dy(), scale);
        let var_in = frame
            .variance()
            .map(|v| scaled(v, scale * scale))
            .transpose()?;
        let var = match var_in.as_ref() {
            // Renderers estimate the variance of the mean from few passes (ours: 4), so the
            // layer is itself very noisy; a 5 x 5 box average makes the RDFC distances and
            // SURE usable (on the bundled sample: guide relMSE 2.03e-3 -> 1.42e-3).
            Some(v) => rdfc::smooth_variance(v, 2)?,
            None => {
                report.note("variance: estimated from 3 x 3 colour statistics (no variance layer)");
                estimate_variance(colour)?
            }
        };
        progress.check()?;
        let removed = report.time("outliers", || -> Result<u64> {
            let n = outliers::remove_outliers(dx)? + outliers::remove_outliers(dy)?;
            outliers::zero_boundary(dx, true);
            outliers::zero_boundary(dy, false);
            Ok(n)
        })?;
        report.note(format!("gradient outliers replaced: {removed}"));
        progress.check()?;
        let (albedo, normal) = (frame.albedo(), frame.normal());
        let (albedo, normal) = if albedo.is_none() && normal.is_none() {
            report.skip("feature terms and prefilter (no albedo or normal): reduced path");
            (None, None)
        } else if !self.cfg.prefilter {
            report.skip("feature prefilter (turned off)");
            (albedo.map(Cow::Borrowed), normal.map(Cow::Borrowed))
        } else if spp >= self.cfg.prefilter_below {
            report.skip(format!(
                "feature prefilter ({spp} spp, prefilter_below = {})",
                self.cfg.prefilter_below
            ));
            (albedo.map(Cow::Borrowed), normal.map(Cow::Borrowed))
        } else {
            report.note(format!(
                "feature prefilter: variance estimated from 3 x 3 ranges at {spp} spp \
                 (bundles carry no feature variance)"
            ));
            report.time("feature prefilter", || -> Result<_> {
                let filter = |f| -> Result<Cow<Image>> {
                    // After a cancel the feature stays as it is: the update below returns.
                    if progress.stopped() {
                        return Ok(Cow::Borrowed(f));
                    }
                    let v = prefilter::feature_variance(f, spp)?;
                    Ok(Cow::Owned(prefilter::prefilter(f, &v)?))
                };
                Ok((
                    albedo.map(filter).transpose()?,
                    normal.map(filter).transpose()?,
                ))
            })?
        };
        progress.update(0.05)?;
        let guide = match self.cfg.guide {
            FrgrGuide::Rdfc => Cow::Owned(report.time("rdfc", || {
                rdfc::rdfc(
                    colour,
                    &var,
                    albedo.as_deref(),
                    normal.as_deref(),
                    self.cfg.rdfc_radius,
                    progress,
                )
            })?),
            FrgrGuide::PoissonL1 => report
                .time("l1 guide", || {
                    // The Poisson guide sees the gradients as given (before outlier removal).
                    let clean = FrameBuilder::new()
                        .image(Layer::Color, colour.try_clone()?)
                        .image(Layer::Dx, scaled(frame.dx(), scale)?.into_owned())
                        .image(Layer::Dy, scaled(frame.dy(), scale)?.into_owned())
                        .build(Policy::Replace)?;
                    let (l1, out) = self.l1.as_mut().expect("the L1 guide is planned");
                    l1.reconstruct_into(&clean, out, &mut Report::default(), &Progress::none())
                })
                .map(|()| Cow::Borrowed(&self.l1.as_ref().expect("the L1 guide is planned").1))?,
            FrgrGuide::Colour => {
                report.skip("pre-denoiser (guide: the noisy colour)");
                Cow::Borrowed(colour)
            }
            FrgrGuide::Prior => {
                report.skip("pre-denoiser (guide: the prior)");
                let prior = self.prior.as_mut().expect("the prior guide is planned");
                Cow::Owned(scaled(&*prior.get(frame, report, progress)?, scale)?.into_owned())
            }
        };
        progress.update(0.4)?;
        let inputs = LevelInputs {
            colour: Cow::Borrowed(colour),
            var,
            dx: Cow::Borrowed(&self.dx),
            dy: Cow::Borrowed(&self.dy),
            albedo,
            normal,
            guide,
            converged: converged_mask(frame)?,
        };
        let (filtered, _variance) = self.run_level(&inputs, spp, 0, report, progress)?;
        out.as_mut_slice()
            .par_chunks_mut(CHUNK)
            .zip(filtered.as_slice().par_chunks(CHUNK))
            .for_each(|(out, filtered)| {
                for (o, &v) in out.iter_mut().zip(filtered) {
                    *o = v / scale;
                }
            });
        progress.update(1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn peak_magnitude_is_the_largest_magnitude_passing_over_nan() {
        let literal = |v: &[f32]| v.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let special = [
            0.0,
            -0.0,
            1.5,
            -2.5,
            f32::MIN_POSITIVE,
            -1e-45,
            f32::MAX,
            f32::MIN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            -f32::NAN,
            f32::from_bits(0x7fc0_0001),
        ];
        // Every pair and triple of the special values, at places in and across chunks.
        for (a, &x) in special.iter().enumerate() {
            for &y in &special[a..] {
                for &z in &special {
                    let mut v = vec![0.25f32; 3 * CHUNK + 17];
                    (v[3], v[CHUNK + 1], v[3 * CHUNK + 16]) = (x, y, z);
                    let mut img = Image::zeros(1, v.len(), 1);
                    img.as_mut_slice().copy_from_slice(&v);
                    let (got, want) = (peak_magnitude(&img), literal(&v));
                    assert_eq!(got.to_bits(), want.to_bits(), "{x} {y} {z}");
                }
            }
        }
        assert_eq!(peak_magnitude(&Image::zeros(3, 0, 0)), 0.0);
    }
}
