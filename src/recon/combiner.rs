//! `combiner`: a small network that weights, per pixel, reconstructions the prior path already
//! computes: the prior (OIDN's output, or the frame's `prior` layer) and screened Poisson L1 on
//! the prior with its preset data-term weight (2.5, "strong") and with a weak one (0.5, which
//! follows the gradients further), both stopped once an IRLS step barely moves the image
//! ([`STEP_CHANGE`]). It predicts weights, not colours (a softmax over the three
//! per pixel), so it only decides which estimate to trust where, which generalises from a
//! small training set (Back et al. 2020 make the same choice for their combiner of independent
//! and correlated estimates). The base image is one of its inputs, not a candidate: mixed in,
//! it cost the validation `glass` frames the most (`docs/benchmarks.md`, "Sixteenth session:
//! the combiner").
//!
//! The network (`onnx/gdrecon_py/combiner.py`, trained on the training split against
//! references) is shipped as its head alone (`onnx/combiner.onnx`: 21 feature planes in, one
//! logit per candidate out). This module computes the features natively from the 27 planes
//! the model reads (the candidates, the base image, the variance, albedo, normal and the two
//! gradients; scale-free transforms, see `features`) as if the frame were padded to a
//! multiple of 4 by repeating its last row and column, runs the graph in overlapping tiles
//! when the frame is large, and mixes the candidates by the softmax of the logits over each
//! tile's core. In the graph, those transforms and the softmax were 35 % of its time at
//! 1280 x 720; here they take a few milliseconds. `combiner.combine` in that file is the
//! reference the parity test holds this to.
//!
//! One rule runs after the network, the mean guard (`combiner/guard.rs`): an L1 candidate is
//! dropped where its local mean departs from the prior's by more than [`MEAN_TOLERANCE`] (it
//! lost or moved energy the gradients do not carry, as in caustics seen through glass).
//!
//! Then the noise band, beside emitters' edges only and from 16 spp, as on `l1`'s `prior`
//! preset (`recon/band.rs`): the prior spreads a bulb into its dark ring and no candidate
//! holds it (the guard's `lamps_16spp` 0.086 -> 0.050, its base 0.100).
//!
//! Needs ONNX Runtime (the `gradnet` cargo feature; found as for GradNet), a prior (OIDN or
//! the frame's `prior` layer) and the frame's variance, albedo and normal layers.

use std::path::PathBuf;

use super::band::{self, BandScope, BAND_TRIM, NOISE_BAND};
use super::gradnet::tiles::Overlap;
use super::gradnet::Precision;
use super::param::{Param, Params, Range};
use super::poisson_l1::{l1_memory, PoissonL1Config, Preconditioner};
use super::prior::{prior_memory, Scratch};
use super::{bytes_for, Reconstructor, Register, MIB};
use crate::context::Context;
use crate::error::Result;

// Used by the network's path only (the `gradnet` feature).
#[cfg(feature = "gradnet")]
mod guard;

/// Settings of `combiner`; the tunable ones are in its parameter table (`docs/PARAMETERS.md`).
#[derive(Clone, Debug, PartialEq)]
#[non_exhaustive]
pub struct CombinerConfig {
    /// A model file to run instead of the embedded `combiner.onnx`, checked against the
    /// `.sha256` file beside it or the embedded models' hashes.
    pub model: Option<PathBuf>,
    /// The ONNX Runtime library to load, before the other discovery steps (as GradNet's).
    pub runtime: Option<PathBuf>,
    /// Frames of at most this many pixels (after padding) run whole; larger ones in tiles.
    pub whole_pixels: usize,
    /// Most pixels a tile holds (its margins included) for frames larger than
    /// `whole_pixels`, in the shape that runs the fewest pixels (as GradNet's); `0` never
    /// tiles.
    pub tile_pixels: usize,
    /// Which embedded graph runs (ignored when [`Self::model`] is given).
    pub precision: Precision,
    /// IRLS steps of the weak candidate's L1 solve (the strong one's are the `prior` preset's).
    pub weak_steps: u32,
    /// Both candidates' IRLS stops once a step moves the image by less than this (their
    /// `step_change`); 0 runs every step.
    pub step_change: f32,
    /// Both candidates' CG stops at this relative residual (their `cg_tolerance`; default the
    /// `prior` preset's 1e-4, on which the network was trained).
    pub cg_tolerance: f32,
    /// An L1 candidate is dropped where its 9 x 9 local mean departs from the prior's by more
    /// than this fraction of it (the mean guard, [`MEAN_TOLERANCE`]); 0 turns the guard off.
    pub mean_tolerance: f32,
    /// The noise band's half-width in standard deviations (`recon/band.rs`); 0: off.
    pub noise_band: f32,
    /// The band's trimming ratio.
    pub band_trim: f32,
    /// Below 64 spp, trim the band of the edge pixels the gradients confirm.
    pub band_emitters: bool,
    /// Where the band clamps: as the `prior` preset of `l1`, beside emitters' edges only.
    pub band_scope: BandScope,
    /// OIDN's scratch memory when it computes the prior: lowered by a memory limit
    /// ([`Register::fit_memory`]), not a parameter.
    pub(crate) scratch: Scratch,
}

impl Default for CombinerConfig {
    fn default() -> Self {
        CombinerConfig {
            model: None,
            runtime: None,
            whole_pixels: 1 << 21,
            tile_pixels: 1 << 18,
            precision: Precision::Int8,
            weak_steps: PoissonL1Config::prior().reweight_steps,
            step_change: STEP_CHANGE,
            cg_tolerance: PoissonL1Config::prior().cg_tolerance,
            mean_tolerance: MEAN_TOLERANCE,
            noise_band: NOISE_BAND,
            band_trim: BAND_TRIM,
            band_emitters: true,
            band_scope: BandScope::Edges,
            scratch: Scratch::default(),
        }
    }
}

/// The planes the graph reads, in order (3 channels each): the candidates and the base image,
/// then the frame's other layers. `onnx/gdrecon_py/combiner.py`'s `INPUTS`.
pub const INPUTS: [&str; 9] = [
    "prior", "strong", "weak", "color", "variance", "albedo", "normal", "dx", "dy",
];

/// How the network's tiles overlap: the graph's input is padded to a multiple of 4 (two 2 x 2
/// poolings), and a tile reads 24 pixels beyond its core (the receptive field's radius is 20,
/// measured: a change to one input pixel moves outputs at most 20 pixels away, rounded up to a
/// multiple of 4).
const OVERLAP: Overlap = Overlap {
    margin: 24,
    multiple: 4,
};

/// Data-term weight of the weak candidate (the strong one is l1's `prior` preset's).
const WEAK_ALPHA: f32 = 0.5;

/// The candidates' IRLS regularisation floor: the one the shipped network was trained on
/// (`candidates.py`'s `REG_FLOOR`), l1's default, not the `prior` preset's lower one.
const CANDIDATE_REG_FLOOR: f32 = 1e-2;

/// Default `step_change`: the candidates' IRLS (12 steps, as the network was trained on) stops
/// once a step at the regularisation's floor moves the image by less than 1e-3 in the error
/// metric's units. Chosen on validation among 3e-4, 1e-3 and 3e-3 (the largest within 0.5 %
/// of every step run in each geometric mean and 2 % on every frame: 1.012 at worst); on test
/// within 0.3 % on every frame. At 720p both solves stop at 7 steps (9 and 12 without it), and
/// everything after the prior takes about 0.83x OIDN's time instead of 1.03x
/// (`docs/benchmarks.md`, eighteenth session). A fixed 8 steps for the weak solve was as fast
/// but cost 32 % on one test frame (lamps, 4 spp), where IRLS is still moving at step 8.
pub const STEP_CHANGE: f32 = 1e-3;

/// Default `mean_tolerance`: an L1 candidate is dropped where its 9 x 9 local mean departs
/// from the prior's by more than 40 % (`combiner/guard.rs` says why). Chosen on validation,
/// on the twenty-first session's training run, among windows 5, 9 and 13 and tolerances 0.3,
/// 0.4 and 0.5: every validation frame within 1.05x OIDN and the lowest geometric means (0.3
/// and 0.4 tied; the milder kept). With the shipped network it takes the validation `glass`
/// 4 spp frame from 1.054x to 1.023x OIDN and moves no validation geometric mean by more than
/// 0.4 %; on test it costs 1.3-3.5 % (`docs/benchmarks.md`, twenty-first session).
pub const MEAN_TOLERANCE: f32 = 0.4;

/// Bytes a pixel of a tile costs in the network run (the input and ONNX Runtime's
/// activations), and the run's fixed share, measured with 0.2's whole fp32 graph (27 planes
/// in, the features, softmax and sum inside). Peak RSS of `gdrecon reconstruct` on a 1280 x
/// 720 bundle then: `-m combiner` 1691 MiB whole, 1339 MiB in tiles of 512; `-m l1 --preset
/// prior` 821 MiB. Less the second L1 solve and the candidates (about 170 MiB) that leaves
/// about 700 MiB for the network run whole (760 B a pixel) and 350 MiB for a 512 x 512 tile.
/// The head alone takes less (whole, fp32: 1659 MiB; int8: 1362 MiB), so the bound holds.
const NET_BYTES: u64 = 1100;
const NET_FIXED: u64 = 128 * MIB;

impl Params for CombinerConfig {
    const TABLE: &'static [Param<Self>] = &[
        Param::int(
            "whole_pixels",
            0,
            i32::MAX as i64,
            "Frames of at most this many pixels (after padding to a multiple of 4) run the \
             network whole; larger ones run it in tiles of at most tile_pixels pixels",
            |c| c.whole_pixels as i64,
            |c, v| c.whole_pixels = v as usize,
        ),
        Param::int(
            "tile_pixels",
            0,
            i32::MAX as i64,
            "Most pixels a tile holds, margins included, for frames larger than whole_pixels \
             (overlapping tiles, in the shape that runs the fewest pixels, bound the \
             network's memory); 0 never tiles; otherwise at least 56 x 56 = 3136",
            |c| c.tile_pixels as i64,
            |c, v| c.tile_pixels = v as usize,
        ),
        Param::choice(
            "precision",
            Precision::NAMES,
            "Arithmetic of the network: int8 (onnx/combiner_int8.onnx, quantised on the \
             training split; the network 1.65x faster at 720p, relMSE within 1.6 % of fp32 on \
             every validation and test frame) or fp32 (onnx/combiner.onnx); ignored when a \
             model file is given",
            |c| c.precision.index(),
            |c, v| c.precision = Precision::ALL[v],
        ),
        Param::int(
            "weak_steps",
            1,
            1000,
            "IRLS steps of the weak candidate's L1 solve (the network was trained on 12)",
            |c| c.weak_steps.into(),
            |c, v| c.weak_steps = v as u32,
        ),
        Param::float(
            "step_change",
            Range::below(0.0, 1.0),
            "Both candidates' IRLS stops once a step moves the image by less than this (l1's \
             step_change); 0 runs every step",
            |c| c.step_change,
            |c, v| c.step_change = v,
        ),
        Param::float(
            "cg_tolerance",
            Range::below(0.0, 1.0),
            "Both candidates' CG stops at this relative residual (l1's cg_tolerance; the \
             network was trained on 1e-4). 1e-3 trades accuracy for time: at 1280 x 720 \
             everything after the prior took 0.57x OIDN's time instead of 0.72x, and the \
             validation relMSE rose 0.2-1.0 % per spp (7 % on one frame)",
            |c| c.cg_tolerance,
            |c, v| c.cg_tolerance = v,
        ),
        Param::float(
            "mean_tolerance",
            Range::closed(0.0, 1e6),
            "Drop an L1 candidate where its 9 x 9 local mean departs from the prior's by more \
             than this fraction of it (there it lost or moved energy the prior keeps: caustics \
             seen through glass); 0: off",
            |c| c.mean_tolerance,
            |c, v| c.mean_tolerance = v,
        ),
        band::param(|c| c.noise_band, |c, v| c.noise_band = v),
        band::trim_param(|c| c.band_trim, |c, v| c.band_trim = v),
        band::emitters_param(|c| c.band_emitters, |c, v| c.band_emitters = v),
        band::scope_param(
            |c| c.band_scope.index(),
            |c, v| c.band_scope = BandScope::ALL[v],
        ),
    ];
}

/// The two L1 candidates' settings: the `prior` preset, and the same with the weak weight,
/// multigrid-preconditioned (a weight this weak leaves the system too poorly conditioned for
/// the preset's Jacobi: 78 CG iterations at 1280 x 720 instead of 17, 1.3x the time).
/// Both keep the regularisation floor the network was trained on ([`CANDIDATE_REG_FLOOR`]).
/// (`alpha` is what a solve run on the prior weights its data term by.)
fn candidates(config: &CombinerConfig) -> [PoissonL1Config; 2] {
    let strong = PoissonL1Config {
        reg_floor: CANDIDATE_REG_FLOOR,
        ..PoissonL1Config::prior()
    };
    [
        PoissonL1Config {
            alpha: strong.prior_alpha,
            step_change: config.step_change,
            cg_tolerance: config.cg_tolerance,
            ..strong
        },
        PoissonL1Config {
            alpha: WEAK_ALPHA,
            reweight_steps: config.weak_steps,
            preconditioner: Preconditioner::Multigrid,
            step_change: config.step_change,
            cg_tolerance: config.cg_tolerance,
            ..strong
        },
    ]
}

impl Register for CombinerConfig {
    const BUILT: bool = cfg!(feature = "gradnet");

    fn runtime_mut(&mut self) -> Option<&mut Option<PathBuf>> {
        Some(&mut self.runtime)
    }

    fn plan(
        &self,
        context: &Context,
        width: usize,
        height: usize,
    ) -> Result<Box<dyn Reconstructor>> {
        #[cfg(feature = "gradnet")]
        return Ok(band::banded(
            Box::new(enabled::Combiner::new(
                self.clone(),
                context,
                width,
                height,
            )?),
            self.noise_band,
            self.band_trim,
            self.band_emitters,
            self.band_scope,
        ));
        #[cfg(not(feature = "gradnet"))]
        {
            let _ = (context, width, height);
            Err(crate::error::Error::Unsupported(
                "this build of gdrecon has no combiner (it runs through ONNX Runtime: cargo \
                 feature `gradnet` is off)"
                    .into(),
            ))
        }
    }

    /// The prior's share, the L1 solve (one plan for both candidates) and both outputs, and
    /// the network's run over one tile (or the whole frame).
    fn memory_estimate(&self, width: usize, height: usize) -> u64 {
        prior_memory(width, height, self.scratch)
            .saturating_add(self.solve_memory(width, height))
            .saturating_add(self.network_memory(width, height))
    }

    /// Lowers OIDN's scratch to what `limit` leaves beside the rest at the network's own
    /// budgets (OIDN in tiles costs less time than the network in small ones), then the
    /// network's budgets to what is left; a tile (or the whole frame) is never lowered below
    /// [`Overlap::least_fitted`], so that a limit under it is refused, not run in tiles that
    /// are mostly margin.
    fn fit_memory(&mut self, width: usize, height: usize, limit: u64) {
        let solve = self.solve_memory(width, height);
        let network = self.network_memory(width, height);
        self.scratch
            .fit(width, height, limit, solve.saturating_add(network));
        if self.memory_estimate(width, height) <= limit {
            return;
        }
        let taken = prior_memory(width, height, self.scratch).saturating_add(solve);
        let most = OVERLAP.fitted(super::pixels_within(limit, taken, NET_BYTES, NET_FIXED));
        self.whole_pixels = self.whole_pixels.min(most);
        if self.tile_pixels > 0 {
            self.tile_pixels = self.tile_pixels.min(most);
        }
    }
}

impl CombinerConfig {
    /// What the combiner holds besides the prior and the network's run: the L1 solve (one
    /// plan for both candidates), the candidates and the guard's mask.
    fn solve_memory(&self, width: usize, height: usize) -> u64 {
        let [strong, weak] = candidates(self);
        l1_memory(&strong, width, height)
            .max(l1_memory(&weak, width, height))
            .saturating_add(bytes_for(width, height, 5 * 12 + 1, 0))
    }

    /// The network's run over one tile, or the whole frame.
    fn network_memory(&self, width: usize, height: usize) -> u64 {
        let pixels = width.saturating_mul(height);
        // A tile holds at most `tile_pixels` pixels, whatever its shape.
        let (tw, th) = if self.tile_pixels == 0 || pixels <= self.whole_pixels {
            (width, height)
        } else {
            (self.tile_pixels.min(pixels), 1)
        };
        bytes_for(tw, th, NET_BYTES, NET_FIXED)
    }
}

#[cfg(feature = "gradnet")]
mod enabled {
    use std::borrow::Cow;
    use std::sync::{Arc, Mutex};
    use std::time::{Duration, Instant};

    use ndarray::{Array4, ArrayView3, ArrayView4};
    use ort::session::Session;
    use ort::value::TensorRef;
    use rayon::prelude::*;

    use super::{candidates, guard, CombinerConfig, Precision, OVERLAP};
    use crate::context::Context;
    use crate::error::{Error, Result};
    use crate::frame::{Frame, Layer};
    use crate::image::Image;
    use crate::progress::Progress;
    use crate::recon::gradnet::model::{self, ModelBytes, ModelVariant};
    use crate::recon::gradnet::net::{cancellable, input_names, input_shape, output, session};
    use crate::recon::gradnet::runtime;
    use crate::recon::gradnet::tiles::{self, Tile};
    use crate::recon::poisson_l1::{PoissonL1, PoissonL1Config};
    use crate::recon::prior::{anchored, Prior, Quality};
    use crate::recon::{repair, Method, Reconstructor};
    use crate::report::{Report, Stage};

    /// Planes of the graph's input (`combiner.py`'s `FEATURES`), and the candidates it weights
    /// (the first three of [`INPUTS`](super::INPUTS)).
    const FEATURES: usize = 21;
    const MIXED: usize = 3;

    /// Radiance floor of the scale each pixel is measured in (`combiner.py`'s `FLOOR`).
    const FLOOR: f32 = 0.01;

    /// The combiner's graph in one session.
    struct Net {
        session: Session,
        origin: String,
    }

    impl Net {
        fn new(
            env: &ort::environment::Environment,
            model: &ModelBytes,
            threads: usize,
        ) -> Result<Net> {
            let session = session(env, model, threads)?;
            let input = input_shape(&session, "features");
            let has_output = session.outputs().iter().any(|o| o.name() == "logits");
            match input {
                Some(shape) if shape.len() == 4 && shape[1] == FEATURES as i64 && has_output => {}
                _ => {
                    return Err(Error::Model(format!(
                        "{}: not a combiner graph: expected input `features` (N x {FEATURES} x \
                         H x W) and output `logits`, found inputs [{}]",
                        model.origin,
                        input_names(&session)
                    )))
                }
            }
            Ok(Net {
                session,
                origin: model.origin.clone(),
            })
        }

        /// Runs the graph on `input` (1 x 21 x H x W features) and hands its logits
        /// (3 x H x W) to `consume`.
        fn run(
            &mut self,
            input: ArrayView4<'_, f32>,
            stop: &Progress,
            consume: impl FnOnce(ArrayView3<'_, f32>),
        ) -> Result<()> {
            let fail = |e: ort::Error| Error::Runtime(format!("combiner inference failed: {e}"));
            let input = TensorRef::from_array_view(input).map_err(fail)?;
            let session = &mut self.session;
            cancellable(stop, |options| {
                let outputs = session
                    .run_with_options(ort::inputs!["features" => input], options)
                    .map_err(fail)?;
                consume(output(&outputs, "logits", "combiner inference", |d| {
                    (d[1], d[2], d[3])
                })?);
                Ok(())
            })
        }
    }

    /// The combiner planned for one frame size.
    pub(crate) struct Combiner {
        prior: Prior,
        /// L1 on the prior, planned once and reconfigured for each candidate in turn (their
        /// settings differ in the data term's weight, the step count and the preconditioner
        /// only; one plan's buffers instead of two: 1.2 GB less at 3840 x 2160).
        solve: PoissonL1,
        /// The strong and the weak candidate's settings.
        candidates: [PoissonL1Config; 2],
        /// Their outputs.
        outputs: [Image; 2],
        net: Arc<Mutex<Net>>,
        tiles: Vec<Tile>,
        /// The mean guard's tolerance (`CombinerConfig::mean_tolerance`).
        mean_tolerance: f32,
        /// One tile's input, `1 x 21 x th x tw`.
        input: Array4<f32>,
        runtime_path: String,
    }

    impl std::fmt::Debug for Combiner {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            f.debug_struct("Combiner")
                .field("tiles", &self.tiles.len())
                .finish()
        }
    }

    impl Combiner {
        /// Plans the combiner: the prior source (nothing loaded yet), both L1 solves, ONNX
        /// Runtime and the model (once per process and context), the tiles and one tile's
        /// input buffer.
        pub(crate) fn new(
            config: CombinerConfig,
            context: &Context,
            width: usize,
            height: usize,
        ) -> Result<Self> {
            let padded = |n: usize| n.div_ceil(OVERLAP.multiple) * OVERLAP.multiple;
            let tiles = tiles::layout(
                padded(width),
                padded(height),
                config.whole_pixels,
                config.tile_pixels,
                OVERLAP,
            )?;
            let (th, tw) = (tiles[0].y.size, tiles[0].x.size);
            let rt = runtime::runtime(config.runtime.as_deref())?;
            let threads = context.threads();
            let variant = match config.precision {
                Precision::Int8 => ModelVariant::CombinerInt8,
                Precision::Fp32 => ModelVariant::Combiner,
            };
            let source = match &config.model {
                Some(path) => format!("file {}", path.display()),
                None => format!("embedded {}", variant.file_name()),
            };
            let model_path = config.model.clone();
            let net = context.shared(&format!("combiner: {source}: {threads} threads"), || {
                let bytes = match &model_path {
                    Some(path) => model::from_file(path)?,
                    None => model::embedded(variant)?,
                };
                Ok(Mutex::new(Net::new(&rt.env, &bytes, threads)?))
            })?;
            let candidates = candidates(&config);
            Ok(Combiner {
                prior: Prior::new(context, width, height, Quality::High, config.scratch)?,
                solve: PoissonL1::new_for(&candidates, width, height)?,
                candidates,
                outputs: [
                    Image::try_zeros(3, width, height)?,
                    Image::try_zeros(3, width, height)?,
                ],
                net,
                tiles,
                mean_tolerance: config.mean_tolerance,
                input: Array4::zeros((1, FEATURES, th, tw)),
                runtime_path: rt.path.display().to_string(),
            })
        }
    }

    /// The frame's layers the network reads besides colour and gradients, or an error naming
    /// those it lacks.
    fn layers(frame: &Frame) -> Result<[&Image; 3]> {
        match (frame.variance(), frame.albedo(), frame.normal()) {
            (Some(v), Some(a), Some(n)) => Ok([v, a, n]),
            _ => {
                let missing: Vec<&str> = [Layer::Variance, Layer::Albedo, Layer::Normal]
                    .into_iter()
                    .filter(|l| frame.layer(*l).is_none())
                    .map(Layer::name)
                    .collect();
                Err(Error::input(format!(
                    "the combiner needs the frame's variance, albedo and normal layers (its \
                     network was trained with them); this frame lacks {}",
                    missing.join(", ")
                )))
            }
        }
    }

    /// `x / (1 + |x|)`: `combiner.py`'s `_soft`, a signed compression to (-1, 1).
    fn soft(x: f32) -> f32 {
        x / (1.0 + x.abs())
    }

    /// Fills `input` (1 x 21 x th x tw) with the features of tile `tile` of `sources` (9
    /// images of 3 channels, [`INPUTS`](super::INPUTS) order) as `combiner.py`'s `features`
    /// computes them on the frame padded by repeating its last row and column: pixels beyond
    /// the frame take the last row's and column's features, whose forward differences are 0
    /// in both. Each feature is one loop over a row's columns, with the same arithmetic in the
    /// same order as the reference, so that the loops vectorise (all but the logarithms):
    /// 0.109 s -> 0.017 s at 1280 x 720 with 2 threads (AMD EPYC).
    fn features(input: &mut Array4<f32>, sources: [&Image; 9], tile: Tile) {
        let (w, h) = sources[0].size();
        let n = w * h;
        let src: [&[f32]; 9] = sources.map(Image::as_slice);
        let (th, tw) = (input.dim().2, input.dim().3);
        let planes = input.as_slice_mut().expect("a tile's input is contiguous");
        // Row `ty` of every plane, so that rows can be filled in parallel.
        let mut rows: Vec<Vec<&mut [f32]>> =
            (0..th).map(|_| Vec::with_capacity(FEATURES)).collect();
        for plane in planes.chunks_mut(th * tw) {
            for (row, slot) in plane.chunks_mut(tw).zip(&mut rows) {
                slot.push(row);
            }
        }
        // The frame's columns the tile's first `inside` columns read, `first..first + inside`
        // (a tile starting in the padding reads the last column); those beyond repeat the last
        // one's features.
        let inside = w.saturating_sub(tile.x.origin).clamp(1, tw);
        let first = tile.x.origin.min(w - 1);
        // Columns with a right neighbour in the frame; the frame's last column, if the tile
        // reaches it, is its own neighbour (difference 0).
        let inner = inside - usize::from(first + inside == w);
        rows.into_par_iter().enumerate().for_each(|(ty, mut out)| {
            let sy = (tile.y.origin + ty).min(h - 1);
            let row = |s: usize, c: usize, y: usize| {
                let o = c * n + y * w + first;
                &src[s][o..o + inside]
            };
            // The same row from the next column on (`inner` values, then the last again).
            let right = |s: usize, c: usize| {
                let o = c * n + sy * w + first + 1;
                &src[s][o..o + inner]
            };
            let cur: [[&[f32]; 3]; 9] =
                std::array::from_fn(|s| std::array::from_fn(|c| row(s, c, sy)));
            // The row below the prior and the strong candidate, for their vertical
            // differences; the last row is its own "below", so its difference is 0.
            let down: [[&[f32]; 3]; 2] =
                std::array::from_fn(|s| std::array::from_fn(|c| row(s, c, (sy + 1).min(h - 1))));
            let [p0, p1, p2] = cur[0];
            // The pixel's scale, from the least noisy estimate (in the level's plane until
            // the end, where it becomes its logarithm).
            {
                let q = &mut out[9][..inside];
                for (((q, &a), &b), &c) in q.iter_mut().zip(p0).zip(p1).zip(p2) {
                    *q = (a + b + c) / 3.0 + FLOOR;
                }
            }
            let (head, tail) = out.split_at_mut(9);
            let q: &[f32] = &tail[0][..inside];
            // The strong and weak candidates and the base image, relative to the prior.
            for s in 1..4 {
                for c in 0..3 {
                    let o = &mut head[3 * (s - 1) + c][..inside];
                    for (((o, &v), &p), &q) in o.iter_mut().zip(cur[s][c]).zip(cur[0][c]).zip(q) {
                        *o = soft((v - p) / q);
                    }
                }
            }
            let (level, rest) = tail.split_first_mut().expect("21 planes");
            let q: &[f32] = &level[..inside];
            {
                let [v0, v1, v2] = cur[4];
                let o = &mut rest[0][..inside];
                for ((((o, &a), &b), &c), &q) in o.iter_mut().zip(v0).zip(v1).zip(v2).zip(q) {
                    let var = (a.max(0.0) + b.max(0.0) + c.max(0.0)) / 3.0;
                    *o = (var.sqrt() / q + 1e-3).ln();
                }
            }
            // How far the prior and the strong candidate are from the gradients: the mean
            // over channels of |g - forward difference| (0 at the last column and row).
            for s in 0..2 {
                let [v0, v1, v2] = cur[s];
                let [gx0, gx1, gx2] = cur[7];
                let [gy0, gy1, gy2] = cur[8];
                let [r0, r1, r2] = [right(s, 0), right(s, 1), right(s, 2)];
                let [d0, d1, d2] = down[s];
                let (ox, oy) = rest[1 + 2 * s..3 + 2 * s].split_at_mut(1);
                let (ox, oy) = (&mut ox[0][..inside], &mut oy[0][..inside]);
                for x in 0..inside {
                    let (a, b, c) = (v0[x], v1[x], v2[x]);
                    // The frame's last column: its own right neighbour.
                    let (ra, rb, rc) = if x < inner {
                        (r0[x], r1[x], r2[x])
                    } else {
                        (a, b, c)
                    };
                    let ex = (gx0[x] - (ra - a)).abs()
                        + (gx1[x] - (rb - b)).abs()
                        + (gx2[x] - (rc - c)).abs();
                    let ey = (gy0[x] - (d0[x] - a)).abs()
                        + (gy1[x] - (d1[x] - b)).abs()
                        + (gy2[x] - (d2[x] - c)).abs();
                    ox[x] = soft(ex / 3.0 / q[x]);
                    oy[x] = soft(ey / 3.0 / q[x]);
                }
            }
            for c in 0..3 {
                for (o, &v) in rest[5 + c][..inside].iter_mut().zip(cur[5][c]) {
                    *o = v.clamp(0.0, 1.0);
                }
                for (o, &v) in rest[8 + c][..inside].iter_mut().zip(cur[6][c]) {
                    *o = v.clamp(-1.0, 1.0);
                }
            }
            for q in level[..inside].iter_mut() {
                *q = q.ln();
            }
            for plane in out.iter_mut() {
                let last = plane[inside - 1];
                plane[inside..].fill(last);
            }
        });
    }

    /// Writes the core of `tile` into `out`: per pixel, the candidates (`sources`' first
    /// [`MIXED`]) weighted by the softmax of the graph's `logits` (3 x th x tw), less those the
    /// mean guard dropped there (`dropped`: bit `k - 1` for candidate `k`; the prior, 0, stays).
    fn mix(
        out: &mut Image,
        logits: ArrayView3<'_, f32>,
        sources: [&Image; 9],
        dropped: &[u8],
        tile: Tile,
    ) {
        let (w, h) = out.size();
        let n = w * h;
        let cands: [&[f32]; MIXED] = std::array::from_fn(|k| sources[k].as_slice());
        let rows = tile.y.core_start..tile.y.core_end.min(h);
        let cols = tile.x.core_start..tile.x.core_end.min(w);
        let (r, g, b) = {
            let planes = out.as_mut_slice();
            let (r, rest) = planes.split_at_mut(n);
            let (g, b) = rest.split_at_mut(n);
            (r, g, b)
        };
        let span = rows.start * w..rows.end * w;
        r[span.clone()]
            .par_chunks_mut(w)
            .zip(g[span.clone()].par_chunks_mut(w))
            .zip(b[span].par_chunks_mut(w))
            .enumerate()
            .for_each(|(k, ((r, g), b))| {
                let y = rows.start + k;
                let ty = y - tile.y.origin;
                for x in cols.clone() {
                    let tx = x - tile.x.origin;
                    let i = y * w + x;
                    let kept = |k: usize| k == 0 || dropped[i] & (1 << (k - 1)) == 0;
                    let l: [f32; MIXED] = std::array::from_fn(|k| logits[(k, ty, tx)]);
                    let top = (0..MIXED)
                        .filter(|&k| kept(k))
                        .map(|k| l[k])
                        .fold(f32::NEG_INFINITY, f32::max);
                    let e: [f32; MIXED] =
                        std::array::from_fn(|k| if kept(k) { (l[k] - top).exp() } else { 0.0 });
                    let sum: f32 = e.iter().sum();
                    let weight = e.map(|v| v / sum);
                    for (c, o) in [&mut r[x], &mut g[x], &mut b[x]].into_iter().enumerate() {
                        *o = (0..MIXED).map(|k| weight[k] * cands[k][c * n + i]).sum();
                    }
                }
            });
    }

    impl Reconstructor for Combiner {
        fn method(&self) -> Method {
            Method::Combiner
        }

        fn reconstruct_into(
            &mut self,
            frame: &Frame,
            out: &mut Image,
            report: &mut Report,
            progress: &Progress,
        ) -> Result<()> {
            let [variance, albedo, normal] = layers(frame)?;
            let prior = match self.prior.get(frame, report, progress)? {
                Cow::Borrowed(given) => given.try_clone()?,
                Cow::Owned(computed) => computed,
            };
            let on_prior = anchored(prior, frame)?;
            let names = ["l1 (strong)", "l1 (weak)"];
            for ((config, output), name) in self.candidates.iter().zip(&mut self.outputs).zip(names)
            {
                let solve = &mut self.solve;
                solve.reconfigure(*config);
                // The solves' own stages and notes, prefixed with which candidate they are.
                let mut inner = Report::default();
                report.time(name, || {
                    solve.reconstruct_into(&on_prior, output, &mut inner, progress)?;
                    // As `l1 --preset prior` gives it (its plan's `repair`: non-finite values
                    // the base colour, negative ones 0), which is what `candidates.py` reads.
                    // The shipped network was trained on candidates from before that rule
                    // (0.16 % of the weak candidate's training values negative, 0.03 % on
                    // validation); with them clamped its validation figures held or improved
                    // (`docs/benchmarks.md`, twenty-second session).
                    repair(output, frame.color());
                    Ok::<_, Error>(())
                })?;
                report
                    .notes
                    .extend(inner.notes.into_iter().map(|n| format!("{name}: {n}")));
            }
            let sources = [
                on_prior.color(),
                &self.outputs[0],
                &self.outputs[1],
                frame.color(),
                variance,
                albedo,
                normal,
                frame.dx(),
                frame.dy(),
            ];
            let dropped = report.time("mean guard", || {
                guard::dropped(
                    sources[0],
                    [sources[1], sources[2]],
                    self.mean_tolerance,
                    FLOOR,
                    progress,
                )
            })?;
            let mut net = self.net.lock().unwrap_or_else(|p| p.into_inner());
            let count = self.tiles.len();
            // Stages summed over the tiles: the native steps around the graph, and the graph.
            let mut times = [Duration::ZERO; 3];
            for (i, tile) in self.tiles.iter().enumerate() {
                let t0 = Instant::now();
                features(&mut self.input, sources, *tile);
                let t1 = Instant::now();
                let mut t2 = t1;
                net.run(self.input.view(), progress, |logits| {
                    t2 = Instant::now();
                    mix(out, logits, sources, &dropped, *tile)
                })?;
                for (time, (start, end)) in
                    times
                        .iter_mut()
                        .zip([(t0, t1), (t1, t2), (t2, Instant::now())])
                {
                    *time += end - start;
                }
                progress.update((i + 1) as f64 / count as f64)?;
            }
            for (name, time) in ["features", "network", "mix"].into_iter().zip(times) {
                report.stages.push(Stage {
                    name: name.into(),
                    time,
                });
            }
            report.note(format!(
                "combiner: model {}, ONNX Runtime {}, {} tile(s) of {} x {}",
                net.origin,
                self.runtime_path,
                count,
                self.input.dim().3,
                self.input.dim().2
            ));
            Ok(())
        }
    }
}
