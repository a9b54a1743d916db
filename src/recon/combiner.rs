//! `combiner`: a small network that weights, per pixel, reconstructions the prior path already
//! computes: the prior (OIDN's output, or the frame's `prior` layer) and screened Poisson L1 on
//! the prior with its preset data-term weight (2.5, "strong") and with a weak one (0.5, which
//! follows the gradients further). It predicts weights, not colours (a softmax over the three
//! per pixel), so it only decides which estimate to trust where, which generalises from a
//! small training set (Back et al. 2020 make the same choice for their combiner of independent
//! and correlated estimates). The base image is one of its inputs, not a candidate: mixed in,
//! it cost the validation `glass` frames the most (`docs/benchmarks.md`, "Sixteenth session:
//! the combiner").
//!
//! The network (`onnx/gdrecon_py/combiner.py`, trained on the training split against
//! references, `onnx/combiner.onnx`) holds every transform after the candidates: this module
//! stacks 27 planes (the candidates, the base image, the variance, albedo, normal and the two
//! gradients) padded to a multiple of 4 by repeating the last row and column, runs the graph
//! in overlapping tiles when the frame is large, and keeps each tile's core.
//! `combiner.combine` in that file is the reference the parity test holds this to.
//!
//! Needs ONNX Runtime (the `gradnet` cargo feature; found as for GradNet), a prior (OIDN or
//! the frame's `prior` layer) and the frame's variance, albedo and normal layers.

use std::path::PathBuf;

use super::param::{Param, Params};
use super::poisson_l1::{l1_memory, PoissonL1Config};
use super::prior::prior_memory;
use super::{bytes_for, Reconstructor, Register, MIB};
use crate::context::Context;
use crate::error::Result;

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
    /// Tile side in pixels for frames larger than `whole_pixels`; `0` never tiles.
    pub tile_size: usize,
}

impl Default for CombinerConfig {
    fn default() -> Self {
        CombinerConfig {
            model: None,
            runtime: None,
            whole_pixels: 1 << 21,
            tile_size: 512,
        }
    }
}

/// The planes the graph reads, in order (3 channels each): the candidates and the base image,
/// then the frame's other layers. `onnx/gdrecon_py/combiner.py`'s `INPUTS`.
pub const INPUTS: [&str; 9] = [
    "prior", "strong", "weak", "color", "variance", "albedo", "normal", "dx", "dy",
];

/// Data-term weight of the weak candidate (the strong one is l1's `prior` preset's).
const WEAK_ALPHA: f32 = 0.5;

/// Bytes a pixel of a tile costs in the network run (the 27-plane input and ONNX Runtime's
/// activations), and the run's fixed share. Peak RSS of `gdrecon reconstruct` on a 1280 x 720
/// bundle: `-m combiner` 1691 MiB whole, 1339 MiB in tiles of 512; `-m l1 --preset prior` 821
/// MiB. Less the second L1 solve and the candidates (about 170 MiB) that leaves about 700 MiB
/// for the network run whole (760 B a pixel) and 350 MiB for a 512 x 512 tile.
const NET_BYTES: u64 = 1100;
const NET_FIXED: u64 = 128 * MIB;

impl Params for CombinerConfig {
    const TABLE: &'static [Param<Self>] = &[
        Param::int(
            "whole_pixels",
            0,
            i32::MAX as i64,
            "Frames of at most this many pixels (after padding to a multiple of 4) run the \
             network whole; larger ones run it in tiles of tile_size",
            |c| c.whole_pixels as i64,
            |c, v| c.whole_pixels = v as usize,
        ),
        Param::int(
            "tile_size",
            0,
            1 << 16,
            "Tile side in pixels for frames larger than whole_pixels (overlapping square \
             tiles bound the network's memory); 0 never tiles; otherwise at least 56",
            |c| c.tile_size as i64,
            |c, v| c.tile_size = v as usize,
        ),
    ];
}

/// The two L1 candidates' settings: the `prior` preset, and the same with the weak weight.
/// (`alpha` is what a solve run on the prior weights its data term by.)
fn candidates() -> [PoissonL1Config; 2] {
    let strong = PoissonL1Config::prior();
    [
        PoissonL1Config {
            alpha: strong.prior_alpha,
            ..strong
        },
        PoissonL1Config {
            alpha: WEAK_ALPHA,
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
        return Ok(Box::new(enabled::Combiner::new(
            self.clone(),
            context,
            width,
            height,
        )?));
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

    /// The prior's share, both L1 solves and their outputs, and the network's run over one
    /// tile (or the whole frame).
    fn memory_estimate(&self, width: usize, height: usize) -> u64 {
        let [strong, weak] = candidates();
        let whole = self.tile_size == 0 || width.saturating_mul(height) <= self.whole_pixels;
        let (tw, th) = if whole {
            (width, height)
        } else {
            (self.tile_size, self.tile_size)
        };
        prior_memory(width, height)
            .saturating_add(l1_memory(&strong, width, height))
            .saturating_add(l1_memory(&weak, width, height))
            .saturating_add(bytes_for(width, height, 5 * 12, 0))
            .saturating_add(bytes_for(tw, th, NET_BYTES, NET_FIXED))
    }
}

#[cfg(feature = "gradnet")]
mod enabled {
    use std::borrow::Cow;
    use std::sync::{Arc, Mutex};

    use ndarray::{s, Array4, ArrayView3, ArrayView4};
    use ort::session::Session;
    use ort::value::TensorRef;
    use rayon::prelude::*;

    use super::{candidates, CombinerConfig, INPUTS};
    use crate::context::Context;
    use crate::error::{Error, Result};
    use crate::frame::{Frame, Layer};
    use crate::image::Image;
    use crate::progress::Progress;
    use crate::recon::gradnet::model::{self, ModelBytes, ModelVariant};
    use crate::recon::gradnet::net::{cancellable, input_names, input_shape, output, session};
    use crate::recon::gradnet::runtime;
    use crate::recon::gradnet::tiles::{self, Overlap, Tile};
    use crate::recon::poisson_l1::PoissonL1;
    use crate::recon::prior::{anchored, Prior, Quality};
    use crate::recon::{Method, Reconstructor};
    use crate::report::Report;

    /// Padding multiple of the graph's input (two 2 x 2 poolings).
    const MULTIPLE: usize = 4;

    /// Pixels a tile reads beyond its core: the receptive field's radius is 20 (measured: a change
    /// to one input pixel moves outputs at most 20 pixels away), rounded up to a multiple of 4.
    const MARGIN: usize = 24;

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
            let input = input_shape(&session, "input");
            let has_output = session.outputs().iter().any(|o| o.name() == "output");
            match input {
                Some(shape)
                    if shape.len() == 4 && shape[1] == 3 * INPUTS.len() as i64 && has_output => {}
                _ => {
                    return Err(Error::Model(format!(
                        "{}: not a combiner graph: expected input `input` (N x {} x H x W) and \
                         output `output`, found inputs [{}]",
                        model.origin,
                        3 * INPUTS.len(),
                        input_names(&session)
                    )))
                }
            }
            Ok(Net {
                session,
                origin: model.origin.clone(),
            })
        }

        /// Runs the graph on `input` (1 x 27 x H x W) and hands its 3 x H x W output to
        /// `consume`.
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
                    .run_with_options(ort::inputs!["input" => input], options)
                    .map_err(fail)?;
                consume(output(&outputs, "combiner inference", |d| {
                    (d[1], d[2], d[3])
                })?);
                Ok(())
            })
        }
    }

    /// The combiner planned for one frame size.
    pub(crate) struct Combiner {
        prior: Prior,
        /// L1 on the prior, strong and weak data term.
        solves: [PoissonL1; 2],
        /// Their outputs.
        outputs: [Image; 2],
        net: Arc<Mutex<Net>>,
        tiles: Vec<Tile>,
        /// One tile's input, `1 x 27 x th x tw`.
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
            let padded = |n: usize| n.div_ceil(MULTIPLE) * MULTIPLE;
            let tiles = tiles::layout(
                padded(width),
                padded(height),
                config.whole_pixels,
                config.tile_size,
                Overlap {
                    margin: MARGIN,
                    multiple: MULTIPLE,
                },
            )?;
            let (th, tw) = (tiles[0].y.size, tiles[0].x.size);
            let rt = runtime::runtime(config.runtime.as_deref())?;
            let threads = context.threads();
            let source = match &config.model {
                Some(path) => format!("file {}", path.display()),
                None => format!("embedded {}", ModelVariant::Combiner.file_name()),
            };
            let model_path = config.model.clone();
            let net = context.shared(&format!("combiner: {source}: {threads} threads"), || {
                let bytes = match &model_path {
                    Some(path) => model::from_file(path)?,
                    None => model::embedded(ModelVariant::Combiner)?,
                };
                Ok(Mutex::new(Net::new(&rt.env, &bytes, threads)?))
            })?;
            let [strong, weak] = candidates();
            Ok(Combiner {
                prior: Prior::new(context, width, height, Quality::High),
                solves: [
                    PoissonL1::new(strong, width, height)?,
                    PoissonL1::new(weak, width, height)?,
                ],
                outputs: [
                    Image::try_zeros(3, width, height)?,
                    Image::try_zeros(3, width, height)?,
                ],
                net,
                tiles,
                input: Array4::zeros((1, 3 * INPUTS.len(), th, tw)),
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

    /// Fills `input` (1 x 27 x th x tw) with tile `tile` of `sources` (9 images of 3 channels,
    /// [`INPUTS`] order); pixels beyond the frame repeat its last row and column.
    fn fill(input: &mut Array4<f32>, sources: [&Image; 9], tile: Tile) {
        let (w, h) = sources[0].size();
        input
            .index_axis_mut(ndarray::Axis(0), 0)
            .outer_iter_mut()
            .into_par_iter()
            .enumerate()
            .for_each(|(k, mut plane)| {
                let src = sources[k / 3].plane(k % 3);
                for (ty, mut row) in plane.outer_iter_mut().enumerate() {
                    let sy = (tile.y.origin + ty).min(h - 1);
                    let src = src.row(sy);
                    for (tx, v) in row.iter_mut().enumerate() {
                        *v = src[(tile.x.origin + tx).min(w - 1)];
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
            for ((solve, output), name) in self.solves.iter_mut().zip(&mut self.outputs).zip(names)
            {
                // The solves' own stages and notes, prefixed with which candidate they are.
                let mut inner = Report::default();
                report.time(name, || {
                    solve.reconstruct_into(&on_prior, output, &mut inner, progress)
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
            let mut net = self.net.lock().unwrap_or_else(|p| p.into_inner());
            let (w, h) = frame.size();
            let count = self.tiles.len();
            report.time("network", || {
                for (i, tile) in self.tiles.iter().enumerate() {
                    fill(&mut self.input, sources, *tile);
                    net.run(self.input.view(), progress, |y| {
                        let rows = tile.y.core_start..tile.y.core_end.min(h);
                        let cols = tile.x.core_start..tile.x.core_end.min(w);
                        for c in 0..3 {
                            let src = y.slice(s![
                                c,
                                rows.start - tile.y.origin..rows.end - tile.y.origin,
                                cols.start - tile.x.origin..cols.end - tile.x.origin
                            ]);
                            out.plane_mut(c)
                                .slice_mut(s![rows.clone(), cols.clone()])
                                .assign(&src);
                        }
                    })?;
                    progress.update((i + 1) as f64 / count as f64)?;
                }
                Ok::<_, Error>(())
            })?;
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
