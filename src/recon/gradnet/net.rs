//! ONNX Runtime sessions: how one is built and run with a cancel ([`session`],
//! [`cancellable`], shared with the combiner), and the one running the GradNet graph ([`Net`]).
//!
//! Settings, each for a reason measured here (see `docs/gradnet.md`): all graph optimisations
//! (the layout level turns the convolutions into NCHWc kernels, faster than the extended
//! level);
//! intra-op threads = the context's thread count and no spinning (a spinning pool steals the
//! cores from the rayon stages before and after); one inter-op thread (the graph is a chain);
//! the CPU arena on with memory patterns (fastest; safe because every tile of a plan has the
//! same shape, so the arena does not keep growing). A graph that ends before its output
//! convolution (the int8 graph: output `phases`) has it applied here ([`OutputLayer`]).

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use ndarray::{Array2, ArrayView2, ArrayView4};
use ort::ep;
use ort::session::builder::GraphOptimizationLevel;
use ort::session::{RunOptions, Session, SessionOutputs};
use ort::value::{PrimitiveTensorElementType, TensorRef};

use super::model::ModelBytes;
use super::output_layer::OutputLayer;
use crate::error::{Error, Result};
use crate::progress::Progress;

/// The int8 graph's output when its output convolution runs here ([`OutputLayer`]).
const PHASES: &str = "phases";

/// How often a run's watcher looks at the cancel flag.
const POLL: Duration = Duration::from_millis(5);

/// A loaded network.
pub(crate) struct Net {
    session: Session,
    /// Channels of the `data` input: 8 (colour + features) or 1 (colour only).
    pub data_channels: usize,
    /// The output convolution, when the graph ends before it (the int8 graph's `phases`).
    layer: Option<OutputLayer>,
    /// Its output, kept between runs (every tile of a plan has one size).
    full: Array2<f32>,
    /// The output layer's scratch, kept likewise.
    rows: Vec<u8>,
    /// Where the model came from (for reports).
    pub origin: String,
}

impl std::fmt::Debug for Net {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Net")
            .field("origin", &self.origin)
            .field("data_channels", &self.data_channels)
            .finish()
    }
}

fn runtime_error(
    what: &str,
) -> impl Fn(ort::Error<ort::session::builder::SessionBuilder>) -> Error + '_ {
    move |e| Error::Runtime(format!("{what}: {e}"))
}

/// Builds a session for `model` with `threads` intra-op threads and the settings above.
pub(crate) fn session(
    env: &ort::environment::Environment,
    model: &ModelBytes,
    threads: usize,
) -> Result<Session> {
    let option = runtime_error("cannot configure the ONNX Runtime session");
    Session::builder(env)
        .map_err(|e| Error::Runtime(format!("cannot create an ONNX Runtime session: {e}")))?
        .with_optimization_level(GraphOptimizationLevel::All)
        .map_err(&option)?
        .with_intra_threads(threads)
        .map_err(&option)?
        .with_inter_threads(1)
        .map_err(&option)?
        .with_intra_op_spinning(false)
        .map_err(&option)?
        .with_memory_pattern(true)
        .map_err(&option)?
        .with_execution_providers([ep::CPU::default().with_arena_allocator(true).build()])
        .map_err(&option)?
        .commit_from_memory(&model.bytes)
        .map_err(|e| {
            Error::Model(format!(
                "{}: ONNX Runtime cannot load it: {e}",
                model.origin
            ))
        })
}

/// Runs `run` (one inference, and whatever reads its outputs, which borrow the options) with
/// run options that a cancel of `stop` terminates: a watcher thread polls the flag every
/// [`POLL`], since one inference at 720p takes up to a second. A cancelled run returns
/// `Cancelled`, whatever `run` returned.
pub(crate) fn cancellable<T>(
    stop: &Progress,
    run: impl FnOnce(&RunOptions) -> Result<T>,
) -> Result<T> {
    let options = RunOptions::new()
        .map_err(|e| Error::Runtime(format!("cannot make ONNX Runtime run options: {e}")))?;
    let running = AtomicBool::new(true);
    let result = std::thread::scope(|s| {
        if stop.can_stop() {
            s.spawn(|| {
                while running.load(Ordering::Acquire) {
                    if stop.stopped() {
                        let _ = options.terminate();
                        return;
                    }
                    std::thread::sleep(POLL);
                }
            });
        }
        let result = run(&options);
        running.store(false, Ordering::Release);
        result
    });
    stop.check()?;
    result
}

/// The graph's output tensor `name` of elements `T` in the shape `shape` makes of its
/// dimensions (`(H, W)` for one GradNet item), or an error naming what is wrong (`what`: whose
/// inference it was).
pub(crate) fn output<'a, T: PrimitiveTensorElementType, E: ndarray::ShapeArg>(
    outputs: &'a SessionOutputs<'_>,
    name: &str,
    what: &str,
    shape: impl FnOnce(&[usize]) -> E,
) -> Result<ndarray::ArrayView<'a, T, E::Dim>> {
    let out = outputs
        .get(name)
        .ok_or_else(|| Error::Runtime(format!("{what}: the graph returned no `{name}`")))?
        .try_extract_array::<T>()
        .map_err(|e| Error::Runtime(format!("{what} failed: {e}")))?;
    let dims = out.shape().to_vec();
    out.into_shape_with_order(shape(&dims))
        .map_err(|e| Error::Runtime(format!("{what}: unexpected output shape {dims:?}: {e}")))
}

/// The shape of the graph's input `name` (dynamic axes as -1), if it has one.
pub(crate) fn input_shape(session: &Session, name: &str) -> Option<Vec<i64>> {
    session
        .inputs()
        .iter()
        .find(|o| o.name() == name)
        .and_then(|o| o.dtype().tensor_shape().map(|s| s.to_vec()))
}

/// The graph's input names, comma-separated (for errors naming what a graph has instead).
pub(crate) fn input_names(session: &Session) -> String {
    session
        .inputs()
        .iter()
        .map(|o| o.name().to_owned())
        .collect::<Vec<_>>()
        .join(", ")
}

/// A graph whose metadata describes an output layer must return `phases` as uint8 with the
/// layer's `4 C` channels last (where the graph states them): checked when the model is loaded.
fn check_phases(session: &Session, layer: &OutputLayer, origin: &str) -> Result<()> {
    let Some(phases) = session.outputs().iter().find(|o| o.name() == PHASES) else {
        return Err(Error::Model(format!(
            "{origin}: its metadata describes an output layer but the graph has no `{PHASES}` output"
        )));
    };
    let dtype = phases.dtype();
    let channels = dtype.tensor_shape().filter(|s| s.len() == 4).map(|s| s[3]);
    let ok = dtype.tensor_type() == Some(ort::value::TensorElementType::Uint8)
        && matches!(channels, Some(c) if c < 0 || c as usize == 4 * layer.channels());
    if !ok {
        return Err(Error::Model(format!(
            "{origin}: output `{PHASES}` is {dtype:?}; its output layer reads N x (H/2 + 1) x (W/2 + 1) x {} uint8",
            4 * layer.channels()
        )));
    }
    Ok(())
}

impl Net {
    /// Builds a session for `model` with `threads` intra-op threads.
    pub fn new(
        env: &ort::environment::Environment,
        model: &ModelBytes,
        threads: usize,
    ) -> Result<Net> {
        let session = session(env, model, threads)?;
        let input = |name: &str| input_shape(&session, name);
        let names = || input_names(&session);
        let (data, grad) = (input("data"), input("grad"));
        let meta = session.metadata().map_err(|e| {
            Error::Model(format!(
                "{}: cannot read the graph's metadata: {e}",
                model.origin
            ))
        })?;
        let layer = OutputLayer::from_metadata(|key| meta.custom(key), &model.origin)?;
        drop(meta);
        let has_output = match &layer {
            None => session.outputs().iter().any(|o| o.name() == "output"),
            Some(layer) => {
                check_phases(&session, layer, &model.origin)?;
                true
            }
        };
        let data_channels = match (&data, &grad) {
            (Some(d), Some(g))
                if d.len() == 4 && g.len() == 4 && g[1] == 2 && matches!(d[1], 1 | 8) && has_output =>
            {
                d[1] as usize
            }
            _ => {
                return Err(Error::Model(format!(
                    "{}: not a GradNet graph: expected inputs data (N x 8 or 1 x H x W) and grad \
                     (N x 2 x H x W) and output `output` (or `phases` and its output layer), found inputs [{}] with data {:?}, grad {:?}",
                    model.origin,
                    names(),
                    data,
                    grad
                )))
            }
        };
        Ok(Net {
            session,
            data_channels,
            layer,
            origin: model.origin.clone(),
            full: Array2::zeros((0, 0)),
            rows: Vec::new(),
        })
    }

    /// Runs the network on one batch item and hands its `H x W` output to `consume`; a
    /// cancel of `stop` during the run terminates it ([`cancellable`]).
    pub fn run(
        &mut self,
        data: ArrayView4<'_, f32>,
        grad: ArrayView4<'_, f32>,
        stop: &Progress,
        consume: impl FnOnce(ArrayView2<'_, f32>),
    ) -> Result<()> {
        let fail = |e: ort::Error| Error::Runtime(format!("GradNet inference failed: {e}"));
        let (_, _, h, w) = data.dim();
        let data = TensorRef::from_array_view(data).map_err(fail)?;
        let grad = TensorRef::from_array_view(grad).map_err(fail)?;
        let (session, layer) = (&mut self.session, &self.layer);
        let (full, rows) = (&mut self.full, &mut self.rows);
        let origin = &self.origin;
        // A model file's graph may return any shape: one that does not match the input's is
        // refused here rather than read out of bounds by the caller.
        let wrong = |what: &str, dims: &[usize]| {
            Error::Runtime(format!(
                "GradNet inference ({origin}): output `{what}` has shape {dims:?} for a {h} x {w} input"
            ))
        };
        cancellable(stop, |options| {
            let outputs = session
                .run_with_options(ort::inputs!["data" => data, "grad" => grad], options)
                .map_err(fail)?;
            let Some(layer) = layer else {
                let y = output(&outputs, "output", "GradNet inference", |d| {
                    (
                        d.get(2).copied().unwrap_or(0),
                        d.get(3).copied().unwrap_or(0),
                    )
                })?;
                if y.dim() != (h, w) {
                    return Err(wrong("output", y.shape()));
                }
                consume(y);
                return Ok(());
            };
            let phases = output::<u8, _>(&outputs, PHASES, "GradNet inference", |d| match d {
                &[1, ph, pw, c] => (ph, pw, c),
                _ => (0, 0, 0),
            })?;
            let (ph, pw, _) = phases.dim();
            if ph == 0 || pw == 0 || (2 * (ph - 1), 2 * (pw - 1)) != (h, w) {
                return Err(wrong(PHASES, phases.shape()));
            }
            layer.apply(phases, rows, full)?;
            consume(full.view());
            Ok(())
        })
    }
}
