//! One ONNX Runtime session running the GradNet graph.
//!
//! Settings, each for a reason measured here (see `docs/gradnet.md`): all graph optimisations
//! (the layout level turns the convolutions into NCHWc kernels, faster than the extended
//! level);
//! intra-op threads = the context's thread count and no spinning (a spinning pool steals the
//! cores from the rayon stages before and after); one inter-op thread (the graph is a chain);
//! the CPU arena on with memory patterns (fastest; safe because every tile of a plan has the
//! same shape, so the arena does not keep growing).

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use ndarray::{ArrayView2, ArrayView4};
use ort::ep;
use ort::session::builder::GraphOptimizationLevel;
use ort::session::{RunOptions, Session};
use ort::value::TensorRef;

use super::model::ModelBytes;
use crate::error::{Error, Result};
use crate::progress::Progress;

/// How often a run's watcher looks at the cancel flag.
const POLL: Duration = Duration::from_millis(5);

/// A loaded network.
pub(crate) struct Net {
    session: Session,
    /// Channels of the `data` input: 8 (colour + features) or 1 (colour only).
    pub data_channels: usize,
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

impl Net {
    /// Builds a session for `model` with `threads` intra-op threads.
    pub fn new(
        env: &ort::environment::Environment,
        model: &ModelBytes,
        threads: usize,
    ) -> Result<Net> {
        let option = runtime_error("cannot configure the ONNX Runtime session");
        let session = Session::builder(env)
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
            })?;
        let input = |name: &str| {
            session
                .inputs()
                .iter()
                .find(|o| o.name() == name)
                .and_then(|o| o.dtype().tensor_shape().map(|s| s.to_vec()))
        };
        let names = || {
            session
                .inputs()
                .iter()
                .map(|o| o.name().to_owned())
                .collect::<Vec<_>>()
                .join(", ")
        };
        let (data, grad) = (input("data"), input("grad"));
        let has_output = session.outputs().iter().any(|o| o.name() == "output");
        let data_channels = match (&data, &grad) {
            (Some(d), Some(g))
                if d.len() == 4 && g.len() == 4 && g[1] == 2 && matches!(d[1], 1 | 8) && has_output =>
            {
                d[1] as usize
            }
            _ => {
                return Err(Error::Model(format!(
                    "{}: not a GradNet graph: expected inputs data (N x 8 or 1 x H x W) and grad \
                     (N x 2 x H x W) and output `output`, found inputs [{}] with data {:?}, grad {:?}",
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
            origin: model.origin.clone(),
        })
    }

    /// Runs the network on one batch item and hands its `H x W` output to `consume`. A cancel
    /// of `stop` during the run terminates it (ONNX Runtime's run options; a watcher thread
    /// polls the flag every [`POLL`]): one inference at 720p takes a second or more.
    pub fn run(
        &mut self,
        data: ArrayView4<'_, f32>,
        grad: ArrayView4<'_, f32>,
        stop: &Progress,
        consume: impl FnOnce(ArrayView2<'_, f32>),
    ) -> Result<()> {
        let fail = |e: ort::Error| Error::Runtime(format!("GradNet inference failed: {e}"));
        let data = TensorRef::from_array_view(data).map_err(fail)?;
        let grad = TensorRef::from_array_view(grad).map_err(fail)?;
        let options = RunOptions::new().map_err(fail)?;
        let running = AtomicBool::new(true);
        let session = &mut self.session;
        let outputs = std::thread::scope(|s| {
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
            let outputs =
                session.run_with_options(ort::inputs!["data" => data, "grad" => grad], &options);
            running.store(false, Ordering::Release);
            outputs
        });
        stop.check()?;
        let outputs = outputs.map_err(fail)?;
        let out = outputs
            .get("output")
            .ok_or_else(|| Error::Runtime("the graph returned no `output`".into()))?
            .try_extract_array::<f32>()
            .map_err(fail)?;
        let shape = out.shape().to_vec();
        let out = out
            .into_shape_with_order((shape[2], shape[3]))
            .map_err(|e| Error::Runtime(format!("unexpected output shape {shape:?}: {e}")))?;
        consume(out);
        Ok(())
    }
}
