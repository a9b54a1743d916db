"""ONNX Runtime sessions, created in one place with the settings of the Rust path
(src/recon/gradnet/net.rs): CPU execution provider, `threads` intra-op threads with spinning
off, one inter-op thread, ORT_ENABLE_ALL, CPU memory arena on. onnxruntime is imported only when
a session is made (the rendering-only venv has none)."""


def session(model, threads=2, profile_prefix=None):
    """InferenceSession for `model` (a path, or a serialised ModelProto as bytes).
    `profile_prefix`: turn on ORT's profiling, written to `<profile_prefix>_*.json` when the
    caller calls `end_profiling()`."""
    import onnxruntime as ort
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.enable_cpu_mem_arena = True
    if profile_prefix:
        so.enable_profiling = True
        so.profile_file_prefix = profile_prefix
    return ort.InferenceSession(model, so, providers=["CPUExecutionProvider"])
