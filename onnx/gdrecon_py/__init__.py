"""gdrecon's Python side: GradNet (model, training, export), its reference pipeline, and the
Mitsuba renderer of the data sets. Lives in onnx/; installed in editable mode into the project's
venv by onnx/setup.sh, so every script runs as `$GDRECON_PYTHON -m gdrecon_py.<module>`.

Shared definitions, one of each: `mulaw` (C, S, C^-1), `metrics.relmse`, `runtime.session`
(ONNX Runtime). The trained models and their manifest stay in onnx/ (`ONNX_DIR`).
"""
import os

ONNX_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))   # onnx/: *.onnx, models.json
REPO = os.path.dirname(ONNX_DIR)
