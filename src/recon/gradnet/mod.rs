//! GradNet (Guo et al. 2019): the unsupervised multi-branch auto-encoder, run through ONNX
//! Runtime, with every transform around the network done natively.
//!
//! Per frame: feature normalisation and μ-law compression (`prep`), padding to a multiple of
//! 8 by index maps, the network per colour channel (R, G, B each a batch of one: the same
//! speed as a batch of three here, a third of the memory) in overlapping tiles (`tiles`),
//! the inverse μ-law, then the Gaussian bias correction over the whole frame (`bias`).
//! `onnx/gdrecon_py/pipeline.py` is the reference this module is tested against.
//!
//! Only this module (and only with the `gradnet` cargo feature) knows about ONNX Runtime. The
//! runtime is found and loaded by the first GradNet plan (`runtime`); sessions are kept in
//! the [`Context`] and shared by every plan made from it, so frames of several sizes reuse
//! one loaded model.

// Without the `gradnet` feature the native stages stay compiled (and unit-tested) but unused.
#![cfg_attr(not(feature = "gradnet"), allow(dead_code))]

pub(crate) mod bias;
pub mod model;
pub(crate) mod prep;
pub(crate) mod tiles;

#[cfg(feature = "gradnet")]
pub(crate) mod net;
pub(crate) mod output_layer;
#[cfg(test)]
mod parity;
#[cfg(feature = "gradnet")]
pub(crate) mod runtime;

use std::path::PathBuf;

pub use model::ModelVariant;

/// Arithmetic of a network: the exported fp32 graph, or its int8 quantisation, calibrated on
/// the training split.
///
/// GradNet's feature model runs int8 by default since the forty-first session: its int8 graph
/// (`onnx/gradnet_int8_nhwc.onnx`, the ReLU graph quantisation-aware fine-tuned against
/// references, `docs/gradnet.md`, "A ReLU graph for int8", its decoder channels-last since the
/// fifty-sixth session, "The deployed graph") is 3.0x faster than fp32 on an Intel Xeon with
/// AVX-512 VNNI (the network 3.4x; 1.15-1.17x OIDN's time at 720p, 1.35-1.46x before the
/// rewrite); its relMSE is 0.8 % below fp32's on validation
/// and 0.2 % below on test (geometric means over 24 frames each, #19's bar being 2 %), +3 / +4 %
/// at 64 spp, up to 1.16x on one frame (`dusk` 64 spp). What kept it from being the default,
/// the HDR guard frame, was the bias correction's gain, not int8 (`bias_limit`). `fp32` runs
/// the graph the torch parity tests hold to 1e-4. Frames without features always run the fp32
/// no-feature model. The combiner's head runs int8 by default too: `onnx/combiner_int8.onnx`
/// (`docs/benchmarks.md`, "Seventeenth session").
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Precision {
    /// The int8 graph (the default of GradNet and of the combiner).
    Int8,
    /// The fp32 graph, the one the torch parity tests hold to 1e-4.
    Fp32,
}

choices!(Precision { Int8 => "int8", Fp32 => "fp32" });

/// GradNet's name for [`Precision`] (0.2), kept for callers that use it.
pub type GradNetPrecision = Precision;

impl Precision {
    /// GradNet's embedded model for a frame with features (`true`) or without.
    pub fn variant(self, features: bool) -> ModelVariant {
        match (features, self) {
            (false, _) => ModelVariant::NoFeatures,
            (true, Precision::Fp32) => ModelVariant::Full,
            (true, Precision::Int8) => ModelVariant::FullInt8,
        }
    }
}

#[cfg(feature = "gradnet")]
use super::band::banded;
use super::band::{self, BandScope, BAND_TRIM, NOISE_BAND};
use super::param::{choices, Param, Params, Range};
use super::{Reconstructor, Register};
use crate::context::Context;
use crate::error::Result;

/// Settings of GradNet; the tunable ones are declared in its parameter table below (listed in
/// `docs/PARAMETERS.md`), the paths are where to find the runtime and a model.
#[derive(Clone, Debug, PartialEq)]
#[non_exhaustive]
pub struct GradNetConfig {
    /// A model file to run instead of the embedded models. Its SHA-256 must match the
    /// `.sha256` file beside it (written by `onnx/gdrecon_py/export.py`) or one of the embedded models'.
    /// Its `data` input decides whether it uses features.
    pub model: Option<PathBuf>,
    /// The ONNX Runtime library to load, before the other discovery steps.
    pub runtime: Option<PathBuf>,
    /// Use albedo, normal and depth when the frame has them (the full model).
    pub use_features: bool,
    /// The feature model's arithmetic (ignored when [`GradNetConfig::model`] is set).
    pub precision: GradNetPrecision,
    /// Frames of at most this many pixels (after padding) run whole, as one tile; larger
    /// ones run in tiles of at most `tile_pixels` pixels.
    pub whole_pixels: usize,
    /// Most pixels a tile holds (its margins included) for frames larger than
    /// `whole_pixels`: the bound on the network's memory. The tiles' shape is the one that
    /// runs the fewest pixels (`tiles::layout`); `0` never tiles.
    pub tile_pixels: usize,
    /// Apply the release's Gaussian bias correction.
    pub bias_correction: bool,
    /// Base-colour level beyond the network's range: where any channel of the base colour
    /// exceeds it with a relative standard deviation under 0.1 (an emitter seen directly, not
    /// a firefly), the base colour is kept, before the bias correction; 0 keeps the network's
    /// output everywhere, as the release. A deviation from the release (`onnx/gdrecon_py/pipeline.py`
    /// step 6b, `docs/benchmarks.md`): chosen on the validation split (2 over 1), where it cut
    /// the error on `studio` 6-18x and on `dusk` 4-8x.
    pub range_limit: f32,
    /// Base-colour level beyond which a pixel enters neither side of the bias correction's
    /// gain, unless `range_limit` keeps it (a quiet emitter, the base colour on both sides):
    /// the noisy rest that far beyond the network's range (an emitter's partly covered edge,
    /// fireflies) is light the network cannot output, and its missing energy otherwise
    /// raises the gain over the whole neighbourhood (a room lit by bulbs in view); 0: every
    /// pixel enters the gain, as the release.
    pub bias_limit: f32,
    /// Half-width of the noise band the output is clamped to, in standard deviations of the
    /// base image's noise (`recon/band.rs`); 0: off.
    pub noise_band: f32,
    /// The noise band's trimming ratio at 64 spp or more (`recon/band.rs`); 0: never trimmed.
    pub band_trim: f32,
    /// Below 64 spp also trim the band of bright neighbours the gradients confirm as an
    /// object's edge (`recon/emitters.rs`); off here: on validation it cost `l1` 5 % on
    /// `dusk` at 4 spp and `gradnet` 1.4 % on `dusk` at 16 spp.
    pub band_emitters: bool,
    /// Where the band clamps: every pixel, or only beside an emitter's edge (`recon/band.rs`).
    pub band_scope: BandScope,
    /// Caps on `(whole_pixels, tile_pixels)` that keep a plan within its memory limit, for
    /// the int8 graph and for an fp32 one, each by its own bytes a pixel: set by
    /// [`Register::fit_memory`] (`max_memory_mb`), `None` without a limit.
    fitted: Option<[(usize, usize); 2]>,
}

impl Default for GradNetConfig {
    fn default() -> Self {
        GradNetConfig {
            model: None,
            runtime: None,
            use_features: true,
            precision: GradNetPrecision::Int8,
            whole_pixels: DEFAULT_WHOLE,
            tile_pixels: DEFAULT_TILE,
            bias_correction: true,
            range_limit: 2.0,
            bias_limit: BIAS_LIMIT,
            noise_band: NOISE_BAND,
            band_trim: BAND_TRIM,
            band_emitters: false,
            band_scope: BandScope::All,
            fitted: None,
        }
    }
}

/// Default [`GradNetConfig::bias_limit`]: chosen on the validation split, geometric mean of
/// the fp32 graph at 4 / 16 spp: 10 5.172e-3 / 1.826e-3, 20 5.195e-3 / 1.831e-3, 50 and 0 (the
/// release) 5.22e-3 / 1.84e-3, 5 5.283e-3 / 1.824e-3; 2 (`range_limit`'s level) cost studio 2x
/// at 4 spp, whose bright walls reach it in noise. On test it cut `lamps` 1.3-2.5x and moved
/// no other family by 1 % (docs/gradnet.md, "The bias limit, and int8 as the default").
pub const BIAS_LIMIT: f32 = 10.0;

/// Default [`GradNetConfig::whole_pixels`]: 2^21, so 1920 x 1080 runs whole in int8 (the
/// fastest and most exact run: no overlap), peaking under 4K's tiled peak (docs/gradnet.md,
/// "Tiles by the pixels they run").
pub const DEFAULT_WHOLE: usize = 1 << 21;

/// Default [`GradNetConfig::tile_pixels`]: 2 x 640 x 640, so 3840 x 2160 runs in 15 int8
/// tiles of 928 x 848 with a peak under 1.5 GB for the whole CLI, 22-channel bundle
/// included (docs/gradnet.md, "Tiles by the pixels they run").
pub const DEFAULT_TILE: usize = 2 * 640 * 640;

/// The share of `whole_pixels` and `tile_pixels` a graph in fp32 runs with (`precision=fp32`,
/// the no-feature model, a model file): it takes 3x the int8 graph's memory a pixel (888 B
/// against 294 B, CLI peaks at 540p-1080p), so with half the pixels it keeps the budgets the
/// fp32 graph had before the int8 one's were raised (1280 x 720 whole, tiles of 640 x 640's
/// area): 1.5x the int8 graph's memory, not 3x.
const FP32_SHARE: usize = 2;

/// Bytes a pixel of a network run takes, and the run's fixed share, for the int8 graph and
/// for an fp32 one (`memory_estimate` says where they come from).
const INT8_BYTES: (u64, u64) = (350, 96 * super::MIB);
const FP32_BYTES: (u64, u64) = (900, 192 * super::MIB);

/// Bytes a pixel of a tiled frame takes besides its tile's run: the output, the bias
/// correction's planes, the masks. Peak RSS of `gdrecon reconstruct -m gradnet -p
/// whole_pixels=0 -p tile_pixels=200000` less `gdrecon info`'s on the demo bundle (tiles of
/// about 0.2 Mpx at every size), fifty-eighth session: +115 MiB at 1280 x 720, +154 MiB at
/// 1920 x 1080, +335 MiB at 3840 x 2160, so 31-35 B a pixel; the estimate takes 48 (it took
/// 64 before it was measured).
const FRAME_BYTES: u64 = 48;

impl GradNetConfig {
    /// `(whole_pixels, tile_pixels)` for the graph that runs: as set for the int8 graph, a
    /// [`FP32_SHARE`] of them for an fp32 one; within the memory limit's caps, if any, but a
    /// tile (or the whole frame) lowered by them never under [`tiles::Overlap::least_fitted`]
    /// (so that a limit under it is refused, not run in tiles that are mostly margin).
    fn budgets(&self, int8: bool) -> (usize, usize) {
        let least = tiles::GRADNET.min_tile().pow(2);
        let (whole, tile) = if int8 {
            (self.whole_pixels, self.tile_pixels)
        } else {
            let tile = match self.tile_pixels {
                0 => 0,
                t => (t / FP32_SHARE).max(least.min(t)),
            };
            (self.whole_pixels / FP32_SHARE, tile)
        };
        match self.fitted {
            Some(caps) => {
                let (most_whole, most_tile) = caps[usize::from(!int8)];
                let tile = match tile {
                    0 => 0,
                    t => t.min(tiles::GRADNET.fitted(most_tile)),
                };
                (whole.min(tiles::GRADNET.fitted(most_whole)), tile)
            }
            None => (whole, tile),
        }
    }

    /// Whether `variant` is the embedded int8 graph (a model file counts as fp32: its memory
    /// is not known).
    #[cfg(feature = "gradnet")]
    fn runs_int8(&self, variant: model::ModelVariant) -> bool {
        self.model.is_none() && variant == model::ModelVariant::FullInt8
    }
}

impl Params for GradNetConfig {
    const TABLE: &'static [Param<Self>] = &[
        Param::int(
            "whole_pixels",
            0,
            i32::MAX as i64,
            "Frames of at most this many pixels (after padding to a multiple of 8) run whole, \
             as one tile (fastest, no overlap); larger ones run in tiles of at most \
             tile_pixels pixels. For the int8 graph; a graph in fp32 (precision=fp32, the \
             no-feature model, a model file) takes half, as it takes 3x the memory a pixel",
            |c| c.whole_pixels as i64,
            |c, v| c.whole_pixels = v as usize,
        ),
        Param::int(
            "tile_pixels",
            0,
            i32::MAX as i64,
            "Most pixels a tile holds, margins included, for frames larger than whole_pixels: \
             the bound on the network's memory; the overlapping tiles take the shape that runs \
             the fewest pixels; 0 never tiles; otherwise at least 208 x 208 = 43264. For the \
             int8 graph; a graph in fp32 takes half (at least 43264)",
            |c| c.tile_pixels as i64,
            |c, v| c.tile_pixels = v as usize,
        ),
        Param::bool(
            "bias_correction",
            "Apply the release's Gaussian bias correction",
            |c| c.bias_correction,
            |c, v| c.bias_correction = v,
        ),
        Param::float(
            "range_limit",
            Range::closed(0.0, 1e9),
            "Keep the base colour where a channel exceeds this with a relative standard \
             deviation under 0.1 (emitters: the μ-law input assumes radiance in [0, 1] and the \
             network cannot output them), before the bias correction so that its gain does \
             not spread their energy; 0 keeps the network's output everywhere (the release)",
            |c| c.range_limit,
            |c, v| c.range_limit = v,
        ),
        Param::float(
            "bias_limit",
            Range::closed(0.0, 1e9),
            "Pixels whose base colour exceeds this in a channel, unless range_limit keeps \
             them, enter neither side of the bias correction's gain: light that far beyond the \
             network's range (an emitter's partly covered edge, fireflies) it cannot output, \
             and its missing energy would brighten the whole neighbourhood (a room lit by bulbs \
             in view); 0: every pixel enters the gain, as the release",
            |c| c.bias_limit,
            |c, v| c.bias_limit = v,
        ),
        band::param(|c| c.noise_band, |c, v| c.noise_band = v),
        band::trim_param(|c| c.band_trim, |c, v| c.band_trim = v),
        band::emitters_param(|c| c.band_emitters, |c, v| c.band_emitters = v),
        band::scope_param(
            |c| c.band_scope.index(),
            |c, v| c.band_scope = BandScope::ALL[v],
        ),
        Param::bool(
            "use_features",
            "Use albedo, normal and depth when the frame has them (the full model); false \
             always runs the no-feature model",
            |c| c.use_features,
            |c, v| c.use_features = v,
        ),
        Param::choice(
            "precision",
            GradNetPrecision::NAMES,
            "Arithmetic of the feature model: int8 (onnx/gradnet_int8_nhwc.onnx, ReLU graph \
             quantisation-aware fine-tuned against training references, its decoder \
             channels-last; 3x faster than fp32 with AVX-512 VNNI, relMSE -0.8 % on validation and -0.2 % on test against fp32, \
             +3-4 % at 64 spp, up to 1.16x on one frame) or fp32 (onnx/gradnet.onnx, the graph \
             the torch parity tests hold); frames without features run the fp32 no-feature \
             model either way; ignored when a model file is given",
            |c| c.precision.index(),
            |c, v| c.precision = GradNetPrecision::ALL[v],
        ),
    ];
}

impl Register for GradNetConfig {
    const SWEEP: &'static [&'static str] = &[
        "",
        "use_features=false",
        "precision=fp32",
        "bias_correction=false",
        "range_limit=0",
        "bias_limit=0",
    ];
    const BUILT: bool = cfg!(feature = "gradnet");

    fn plan(
        &self,
        context: &Context,
        width: usize,
        height: usize,
    ) -> Result<Box<dyn Reconstructor>> {
        #[cfg(feature = "gradnet")]
        return Ok(banded(
            Box::new(GradNet::new(self.clone(), context, width, height)?),
            self.noise_band,
            self.band_trim,
            self.band_emitters,
            self.band_scope,
        ));
        #[cfg(not(feature = "gradnet"))]
        {
            let _ = (context, width, height);
            Err(crate::error::Error::Unsupported(
                "this build of gdrecon has no GradNet (cargo feature `gradnet` is off)".into(),
            ))
        }
    }

    fn gradnet_mut(&mut self) -> Option<&mut GradNetConfig> {
        Some(self)
    }

    fn runtime_mut(&mut self) -> Option<&mut Option<PathBuf>> {
        Some(&mut self.runtime)
    }

    /// Peak RSS of `gdrecon reconstruct -m gradnet` (ONNX Runtime 1.31, CPU, the demo
    /// bundle, run whole) minus that of `gdrecon info` on the same bundle (the process, and the
    /// frame as read), fifty-seventh session:
    ///
    /// | size | `info` | int8 | fp32 (`precision=fp32`) | no-feature model (fp32) |
    /// | --- | --- | --- | --- | --- |
    /// | 960 x 540 | 53820 KiB | +201 MiB | +539 MiB | +541 MiB |
    /// | 1280 x 720 | 89652 KiB | +320 MiB | +912 MiB | |
    /// | 1920 x 1080 | 190948 KiB | +637 MiB | +1857 MiB | +1769 MiB |
    ///
    /// Slopes 294 B (int8) and 888 B (fp32) a pixel, intercepts about 55 and 100 MiB; the
    /// estimate takes [`INT8_BYTES`] and [`FP32_BYTES`]. A tiled frame takes that for one
    /// tile, plus [`FRAME_BYTES`] a pixel of the frame for what is frame-sized: at 3840 x 2160
    /// the int8 graph's estimate is 0.77 GB and the fp32 graph's 0.97 GB, where the CLI's peak
    /// less `info`'s was 0.50 and 0.70 GB. The int8 configuration is estimated for both graphs
    /// (the larger counts), as a frame without features runs the fp32 no-feature model.
    fn memory_estimate(&self, width: usize, height: usize) -> u64 {
        let graph = |int8| self.graph_memory(int8, width, height);
        if self.estimates_int8() {
            graph(true).max(graph(false))
        } else {
            graph(false)
        }
    }

    /// Caps the budgets of each graph whose estimate is over `limit` at what `limit` holds by
    /// the estimate's own figures (that graph's bytes a pixel, one tile and what is
    /// frame-sized), so that each graph takes the largest tiles the limit allows.
    fn fit_memory(&mut self, width: usize, height: usize, limit: u64) {
        let frame = super::bytes_for(width, height, FRAME_BYTES, 0);
        let cap = |int8: bool| {
            if self.graph_memory(int8, width, height) <= limit {
                return (usize::MAX, usize::MAX);
            }
            let (per_pixel, fixed) = if int8 { INT8_BYTES } else { FP32_BYTES };
            (
                super::pixels_within(limit, 0, per_pixel, fixed),
                super::pixels_within(limit, frame, per_pixel, fixed),
            )
        };
        let mut caps = [cap(true), cap(false)];
        if let Some(before) = self.fitted {
            for (cap, old) in caps.iter_mut().zip(before) {
                *cap = (cap.0.min(old.0), cap.1.min(old.1));
            }
        }
        self.fitted = Some(caps);
    }
}

impl GradNetConfig {
    /// The estimate for the int8 graph or an fp32 one.
    fn graph_memory(&self, int8: bool, width: usize, height: usize) -> u64 {
        let pixels = width.saturating_mul(height);
        let (whole, tile) = self.budgets(int8);
        let (per_pixel, fixed) = if int8 { INT8_BYTES } else { FP32_BYTES };
        if tile == 0 || pixels <= whole {
            super::bytes_for(width, height, per_pixel, fixed)
        } else {
            // A tile holds at most `tile` pixels, whatever its shape.
            super::bytes_for(tile.min(pixels), 1, per_pixel, fixed)
                .saturating_add(super::bytes_for(width, height, FRAME_BYTES, 0))
        }
    }

    /// Whether the configuration runs the embedded int8 graph for frames with features (and
    /// the fp32 no-feature model for frames without): its estimate covers both graphs.
    fn estimates_int8(&self) -> bool {
        self.model.is_none() && self.precision == GradNetPrecision::Int8
    }
}

#[cfg(feature = "gradnet")]
pub(crate) use enabled::GradNet;

#[cfg(feature = "gradnet")]
mod enabled {
    use std::sync::{Arc, Mutex};
    use std::time::{Duration, Instant};

    use ndarray::{s, Array4};

    use super::model::{self, ModelVariant};
    use super::net::Net;
    use super::prep::{self, FeatureNorm, FrameMap, Window};
    use super::tiles::{self, Tile};
    use super::{bias, runtime, GradNetConfig, GradNetPrecision};
    use crate::context::Context;
    use crate::error::{Error, Result};
    use crate::frame::Frame;
    use crate::image::{try_vec, Image};
    use crate::progress::Progress;
    use crate::recon::converged::converged_mask;
    use crate::recon::{Method, Reconstructor};
    use crate::report::{Report, Stage};

    type SharedNet = Arc<Mutex<Net>>;

    /// GradNet planned for one frame size.
    pub(crate) struct GradNet {
        config: GradNetConfig,
        context: Context,
        map: FrameMap,
        tiles: Vec<Tile>,
        /// Whether `tiles` are laid out for the int8 graph's budgets (or an fp32 graph's).
        int8: bool,
        /// `1 x 8 x th x tw` (channel 0 colour, 1..8 features) and `1 x 2 x th x tw`.
        data: Array4<f32>,
        grad: Array4<f32>,
        /// Loaded networks, by [`ModelVariant::ALL`] index: the configured file (slot 0), or
        /// the embedded models.
        nets: [Option<SharedNet>; ModelVariant::ALL.len()],
        runtime_path: String,
    }

    impl std::fmt::Debug for GradNet {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            f.debug_struct("GradNet")
                .field("config", &self.config)
                .field("tiles", &self.tiles.len())
                .finish()
        }
    }

    impl GradNet {
        /// Plans GradNet for `width x height` frames on `context`: finds and loads ONNX
        /// Runtime (once per process) and the model (once per context), lays out the tiles and
        /// allocates one tile's buffers.
        pub(crate) fn new(
            config: GradNetConfig,
            context: &Context,
            width: usize,
            height: usize,
        ) -> Result<Self> {
            let map = FrameMap::new(width, height);
            // Lay out for the model most frames will need, and load it now, so the first frame
            // does not pay.
            let first = config
                .precision
                .variant(config.model.is_some() || config.use_features);
            let int8 = config.runs_int8(first);
            let tiles = layout(&config, map, int8)?;
            let (data, grad) = buffers(tiles[0])?;
            let runtime = runtime::runtime(config.runtime.as_deref())?;
            let mut plan = GradNet {
                map,
                tiles,
                int8,
                data,
                grad,
                nets: Default::default(),
                runtime_path: runtime.path.display().to_string(),
                context: context.clone(),
                config,
            };
            plan.net(first)?;
            Ok(plan)
        }

        /// Lays the tiles out again for the graph that runs, when it is not the one the plan
        /// laid them out for (a frame without features under the int8 default runs the fp32
        /// no-feature model, in smaller tiles), with buffers for them.
        fn lay_out_for(&mut self, int8: bool) -> Result<()> {
            if int8 == self.int8 {
                return Ok(());
            }
            let tiles = layout(&self.config, self.map, int8)?;
            if self.data.dim() != (1, 8, tiles[0].y.size, tiles[0].x.size) {
                (self.data, self.grad) = buffers(tiles[0])?;
            }
            (self.tiles, self.int8) = (tiles, int8);
            Ok(())
        }

        /// The network for `variant` (ignored when a model file is configured), loaded into
        /// the context on first use.
        fn net(&mut self, variant: ModelVariant) -> Result<SharedNet> {
            let slot = if self.config.model.is_some() {
                0
            } else {
                ModelVariant::ALL
                    .iter()
                    .position(|v| *v == variant)
                    .expect("a known variant")
            };
            if let Some(net) = &self.nets[slot] {
                return Ok(net.clone());
            }
            // Keyed by where the model comes from, so that a second plan on the context neither
            // re-reads nor re-hashes 25 MB: the check runs once, when the session is made. (A
            // model file is therefore read once per context.)
            let threads = self.context.threads();
            let source = match &self.config.model {
                Some(path) => format!("file {}", path.display()),
                None => format!("embedded {}", variant.file_name()),
            };
            let key = format!("gradnet: {source}: {threads} threads");
            let (model_path, runtime_path) =
                (self.config.model.clone(), self.config.runtime.clone());
            let net = self.context.shared(&key, || {
                let bytes = match &model_path {
                    Some(path) => model::from_file(path)?,
                    None => model::embedded(variant)?,
                };
                let rt = runtime::runtime(runtime_path.as_deref())?;
                Ok(Mutex::new(Net::new(&rt.env, &bytes, threads)?))
            })?;
            self.nets[slot] = Some(net.clone());
            Ok(net)
        }
    }

    /// The tiles of `config`'s budgets for the int8 graph or an fp32 one.
    fn layout(config: &GradNetConfig, map: FrameMap, int8: bool) -> Result<Vec<Tile>> {
        let (whole, tile) = config.budgets(int8);
        let (w, h) = (map.x.padded_len(), map.y.padded_len());
        tiles::layout(w, h, whole, tile, tiles::GRADNET)
    }

    /// One tile's input buffers, `1 x 8 x th x tw` and `1 x 2 x th x tw`, zeroed; out of
    /// memory is an error, never an abort (#18: a re-layout allocates them in an execution).
    fn buffers(tile: Tile) -> Result<(Array4<f32>, Array4<f32>)> {
        let (th, tw) = (tile.y.size, tile.x.size);
        let buffer = |planes: usize| {
            let data = try_vec(planes * th * tw, 0.0f32)?;
            Ok::<_, Error>(
                Array4::from_shape_vec((1, planes, th, tw), data)
                    .expect("the length is the shape's"),
            )
        };
        Ok((buffer(8)?, buffer(2)?))
    }

    /// Copies the frame's colour into `out` over `tile`'s core (inside the frame).
    fn copy_base_core(frame: &Frame, tile: Tile, out: &mut Image) {
        let (w, h) = frame.size();
        let (rows, cols) = (
            tile.y.core_start..tile.y.core_end.min(h),
            tile.x.core_start..tile.x.core_end.min(w),
        );
        for c in 0..3 {
            let src = frame.color().plane(c);
            out.plane_mut(c)
                .slice_mut(s![rows.clone(), cols.clone()])
                .assign(&src.slice(s![rows.clone(), cols.clone()]));
        }
    }

    /// Whether colour and gradients are zero everywhere in window `win` of the padded frame.
    fn window_is_empty(frame: &Frame, map: FrameMap, win: Window) -> bool {
        let images = [frame.color(), frame.dx(), frame.dy()];
        (win.y0..win.y0 + win.h).all(|py| {
            let sy = map.y.plain(py);
            images.iter().all(|img| {
                (0..3).all(|c| {
                    let row = img.plane(c);
                    let row = row.row(sy);
                    (win.x0..win.x0 + win.w).all(|px| row[map.x.plain(px)] == 0.0)
                })
            })
        })
    }

    /// Whether every pixel of window `win` of the padded frame is converged (`mask`, frame
    /// width `w`).
    fn window_is_converged(mask: &[bool], w: usize, map: FrameMap, win: Window) -> bool {
        (win.y0..win.y0 + win.h).all(|py| {
            let row = map.y.plain(py) * w;
            (win.x0..win.x0 + win.w).all(|px| mask[row + map.x.plain(px)])
        })
    }

    /// Clamps `out` to `[0, max(I_b) + (W + H) max|g|]`: no image whose gradients are the
    /// frame's can leave that range along any path from its brightest base pixel. Real frames
    /// never reach it (it only catches a network output that invents light, e.g. on a flat
    /// frame); returns how many values were clamped.
    fn clamp_to_input_range(frame: &Frame, out: &mut Image) -> u64 {
        let (w, h) = frame.size();
        let colour_max = frame
            .color()
            .as_slice()
            .iter()
            .fold(0.0f32, |m, v| m.max(*v));
        let mut grad_max = 0.0f32;
        for c in 0..3 {
            let (dx, dy) = (frame.dx().plane(c), frame.dy().plane(c));
            for y in 0..h {
                for x in 0..w {
                    if x + 1 < w {
                        grad_max = grad_max.max(dx[[y, x]].abs());
                    }
                    if y + 1 < h {
                        grad_max = grad_max.max(dy[[y, x]].abs());
                    }
                }
            }
        }
        let bound = colour_max + (w + h) as f32 * grad_max;
        let mut clamped = 0;
        for v in out.as_mut_slice() {
            if *v > bound {
                *v = bound;
                clamped += 1;
            }
        }
        clamped
    }

    /// Per pixel: whether any channel of the base colour exceeds `limit` and is known to a
    /// relative standard deviation below [`EMITTER_NOISE`] (an emitter seen directly, whose
    /// radiance every sample returns, not a firefly).
    fn emitters(frame: &Frame, limit: f32) -> Vec<bool> {
        let n = frame.width() * frame.height();
        let base = frame.color().as_slice();
        let var = frame.variance().map(|v| v.as_slice());
        let quiet = |i: usize| var.is_none_or(|v| v[i].max(0.0).sqrt() < EMITTER_NOISE * base[i]);
        (0..n)
            .map(|p| (0..3).any(|c| base[c * n + p] > limit && quiet(c * n + p)))
            .collect()
    }

    /// Copies the base colour into `out` where `mask` is set; returns how many pixels.
    fn keep_base(frame: &Frame, out: &mut Image, mask: &[bool]) -> u64 {
        let n = mask.len();
        let base = frame.color().as_slice();
        let o = out.as_mut_slice();
        let mut kept = 0;
        for p in (0..n).filter(|&p| mask[p]) {
            for c in 0..3 {
                o[c * n + p] = base[c * n + p];
            }
            kept += 1;
        }
        kept
    }

    /// Per pixel: whether any channel of the base colour exceeds `limit`, leaving out the
    /// pixels in `kept`.
    fn beyond(frame: &Frame, limit: f32, kept: Option<&[bool]>) -> Vec<bool> {
        let n = frame.width() * frame.height();
        let base = frame.color().as_slice();
        (0..n)
            .map(|p| !kept.is_some_and(|k| k[p]) && (0..3).any(|c| base[c * n + p] > limit))
            .collect()
    }

    /// Relative standard deviation of the base colour under which a bright pixel is taken
    /// for an emitter seen directly (whose radiance every sample returns).
    const EMITTER_NOISE: f32 = 0.1;

    impl Reconstructor for GradNet {
        fn method(&self) -> Method {
            Method::GradNet
        }

        fn reconstruct_into(
            &mut self,
            frame: &Frame,
            out: &mut Image,
            report: &mut Report,
            progress: &Progress,
        ) -> Result<()> {
            let norm = if self.config.use_features {
                FeatureNorm::of(frame)
            } else {
                None
            };
            let variant = self.config.precision.variant(norm.is_some());
            self.lay_out_for(self.config.runs_int8(variant))?;
            let net = self.net(variant)?;
            let mut net = net.lock().unwrap_or_else(|p| p.into_inner());
            let use_features = net.data_channels == 8;
            if use_features && norm.is_none() {
                return Err(Error::input(format!(
                    "the model {} uses albedo, normal and depth, which this frame lacks{}",
                    net.origin,
                    if self.config.use_features {
                        ""
                    } else {
                        " (or use_features is off)"
                    }
                )));
            }
            if !use_features {
                if norm.is_none() && self.config.use_features {
                    // Name what is missing: a frame with albedo and normal but no depth
                    // otherwise looked like one with no features at all.
                    let missing: Vec<&str> = [
                        ("albedo", frame.albedo().is_none()),
                        ("normal", frame.normal().is_none()),
                        ("depth", frame.depth().is_none()),
                    ]
                    .into_iter()
                    .filter_map(|(name, absent)| absent.then_some(name))
                    .collect();
                    report.skip(format!(
                        "feature branch: the frame lacks {} (the feature model needs albedo, \
                         normal and depth): ran the no-feature model",
                        missing.join(", ")
                    ));
                } else {
                    report.skip("feature branch: the model has none");
                }
            }
            if variant == ModelVariant::NoFeatures
                && self.config.precision == GradNetPrecision::Int8
                && self.config.model.is_none()
            {
                report.note(
                    "precision int8 applies to the feature model: the no-feature model ran in fp32",
                );
            }
            report.note(format!(
                "GradNet: model {}, ONNX Runtime {}, {} tile(s) of {} x {}",
                net.origin,
                self.runtime_path,
                self.tiles.len(),
                self.data.dim().3,
                self.data.dim().2
            ));

            let (mut prepare, mut network) = (Duration::ZERO, Duration::ZERO);
            let (h, w) = (frame.height(), frame.width());
            let runs = (self.tiles.len() * 3) as f64;
            let mut done = 0.0;
            let mut empty_tiles = 0;
            let mut converged_tiles = 0;
            let converged = converged_mask(frame)?;
            for tile in self.tiles.clone() {
                let win = Window {
                    y0: tile.y.origin,
                    x0: tile.x.origin,
                    h: tile.y.size,
                    w: tile.x.size,
                };
                // Nothing for the network to do where its whole window is black (no light, no
                // gradient: the network would only add its bias) or converged: the base colour
                // is the answer (black in the first case).
                let skip = if window_is_empty(frame, self.map, win) {
                    empty_tiles += 1;
                    true
                } else if converged
                    .as_deref()
                    .is_some_and(|m| window_is_converged(m, w, self.map, win))
                {
                    converged_tiles += 1;
                    true
                } else {
                    false
                };
                if skip {
                    copy_base_core(frame, tile, out);
                    done += 3.0;
                    progress.update(0.97 * done / runs)?;
                    continue;
                }
                let started = Instant::now();
                if let (true, Some(norm)) = (use_features, norm) {
                    let planes = self
                        .data
                        .slice_mut(s![0, 1..8, .., ..])
                        .into_slice()
                        .expect("tile buffers are contiguous");
                    prep::fill_features(frame, norm, self.map, win, planes);
                }
                prepare += started.elapsed();
                for c in 0..3 {
                    let started = Instant::now();
                    let (gx, gy) = self
                        .grad
                        .multi_slice_mut((s![0, 0, .., ..], s![0, 1, .., ..]));
                    let colour = self.data.slice_mut(s![0, 0, .., ..]);
                    prep::fill_channel(frame, c, self.map, win, colour, gx, gy);
                    let filled = Instant::now();
                    prepare += filled - started;
                    let data = self.data.slice(s![.., ..net.data_channels, .., ..]);
                    let mut plane = out.plane_mut(c);
                    net.run(data, self.grad.view(), progress, |y| {
                        // Keep the core, inside the frame; inverse μ-law, clamp at 0.
                        let rows = tile.y.core_start..tile.y.core_end.min(h);
                        let cols = tile.x.core_start..tile.x.core_end.min(w);
                        for py in rows {
                            let src = y.row(py - tile.y.origin);
                            let mut dst = plane.row_mut(py);
                            for px in cols.clone() {
                                let v = prep::expand(src[px - tile.x.origin]);
                                dst[px] = if v > 0.0 && v.is_finite() { v } else { 0.0 };
                            }
                        }
                    })?;
                    network += filled.elapsed();
                    done += 1.0;
                    progress.update(0.97 * done / runs)?;
                }
            }
            if empty_tiles > 0 {
                report.skip(format!(
                    "network on {empty_tiles} of {} tiles: no radiance and no gradient in them",
                    self.tiles.len()
                ));
            }
            if converged_tiles > 0 {
                report.skip(format!(
                    "network on {converged_tiles} of {} tiles: every pixel in them converged (base colour kept)",
                    self.tiles.len()
                ));
            }
            report.stages.push(Stage {
                name: "prepare".into(),
                time: prepare,
            });
            report.stages.push(Stage {
                name: "network".into(),
                time: network,
            });
            let limit = self.config.range_limit;
            let kept = (limit > 0.0).then(|| emitters(frame, limit));
            if let Some(mask) = &kept {
                let count = keep_base(frame, out, mask);
                if count > 0 {
                    report.note(format!(
                        "{count} pixels beyond range_limit {limit} keep their base colour"
                    ));
                }
            }
            progress.check()?;
            if self.config.bias_correction {
                let bias_limit = self.config.bias_limit;
                let skip = (bias_limit > 0.0).then(|| beyond(frame, bias_limit, kept.as_deref()));
                drop(kept); // a frame-sized mask less at the correction's peak
                report.time("bias correction", || {
                    bias::correct(out, frame.color(), skip.as_deref())
                })?;
            } else {
                report.skip("bias correction (disabled)");
            }
            let clamped = clamp_to_input_range(frame, out);
            if clamped > 0 {
                report.note(format!(
                    "{clamped} output values above the input's range were clamped"
                ));
            }
            progress.update(1.0)?;
            Ok(())
        }
    }
}

#[cfg(test)]
mod fit_tests {
    use super::*;
    use crate::recon::Register;

    /// A memory limit lowers each graph's tile budget, but never below the least fitted tile;
    /// a budget set by hand below it stays as set.
    #[test]
    fn a_limit_lowers_tiles_to_the_least_fitted_and_no_lower() {
        let least = tiles::GRADNET.least_fitted();
        let (w, h) = (3840, 2160);
        let mut fitted = GradNetConfig::default();
        fitted.fit_memory(w, h, 0);
        for int8 in [true, false] {
            let free = GradNetConfig::default().budgets(int8);
            let (whole, tile) = fitted.budgets(int8);
            assert_eq!(tile, least, "int8 {int8}");
            assert!(whole == least && tile < free.1, "int8 {int8}");
        }
        let mut small = GradNetConfig {
            tile_pixels: tiles::GRADNET.min_tile().pow(2),
            ..GradNetConfig::default()
        };
        small.fit_memory(w, h, 0);
        assert_eq!(small.budgets(true).1, small.tile_pixels);
    }
}
