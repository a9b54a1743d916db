"""Shared fixtures of the Python suites."""
import pytest


@pytest.fixture(scope="session")
def leaky_int8(tmp_path_factory):
    """A LeakyReLU int8 graph, as `onnx/gradnet_int8.onnx` was before the fortieth session (the
    shipped one is the ReLU graph since): `onnx/gradnet.onnx` through `quantize.py`'s recipe,
    calibrated on two synthetic inputs (the tests that use it need its structure, not its
    accuracy). Returns its path."""
    import numpy as np

    from gdrecon_py import ONNX_DIR
    from gdrecon_py import quantize as qz
    rng = np.random.default_rng(11)
    feeds = [{"data": rng.random((1, 8, 32, 48), dtype=np.float32),
              "grad": (0.05 * rng.standard_normal((1, 2, 32, 48))).astype(np.float32)} for _ in range(2)]
    out = str(tmp_path_factory.mktemp("leaky") / "gradnet_leaky_int8.onnx")
    qz.quantize(f"{ONNX_DIR}/gradnet.onnx", out, feeds, exclude=qz.DEFAULT_EXCLUDE.split(","),
                method="percentile")
    return out
