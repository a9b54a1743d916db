"""Int8 (QDQ) versions of the exported GradNet graphs: static quantisation with ONNX Runtime's
quantisation tool, calibrated on the training split only.

    source onnx/env.sh
    $GDRECON_PYTHON -m gdrecon_py.quantize --model onnx/gradnet.onnx --out onnx/gradnet_int8.onnx
    $GDRECON_PYTHON -m gdrecon_py.quantize --model onnx/gradnet_nofeat.onnx \
        --out onnx/gradnet_nofeat_int8.onnx

What it does (defaults; docs/gradnet.md, "Reduced precision", has the measurements behind them):
- weights int8, symmetric, per output channel; activations uint8 (asymmetric), per tensor
  (u8s8: the pair ONNX Runtime's x86 int8 convolutions run with AVX-512 VNNI; s8s8 ran at the
  same speed here); `reduce_range` off (VNNI has no 16-bit accumulation overflow to avoid).
- QDQ format (QuantizeLinear / DequantizeLinear pairs around float ops; ONNX Runtime fuses them
  into QLinearConv and friends when the session is made), so the graph keeps the fp32 graph's
  inputs, outputs, dynamic shapes, opset and IR version.
- calibration: Percentile ranges (onnxruntime's default 99.999th percentile of |activation|) of
  every activation over `--frames` bundles of the training split
  (`--data`, default ~/.cache/gdrecon/data/train2), never validation or test. The bundles are
  the sorted list taken at an even stride (every family, every spp), each prepared exactly like
  inference (`pipeline.sanitize` + `pipeline.prepare_inputs`), and fed one colour channel at a
  time (batch 1), R, G, B in turn. Deterministic: the same inputs give the same file (checked by
  `--check-deterministic`).
- `--exclude` names nodes kept in fp32: by default the first convolution of each branch (`/d1`,
  `/g1`: 8 and 2 input channels) and the output convolution (`/out`), 1.7 of 119.6 GMAC; with
  them in int8 the validation relMSE rose 3.75 % instead of 0.77 % (`--exclude ''`: none).
  In the QDQ format the output convolution, when kept in fp32, leaves the graph
  (`output_layer.py`): the graph ends at its quantised input and the caller applies it.
- each sub-pixel layer's shuffle and crop share their input's quantisation
  (`share_shuffle_quantization`), so that ONNX Runtime runs them on uint8.
- Percentile since the GPU-trained model (nineteenth session): its cleaner output left MinMax's
  int8 at +5 / +15 / +25 % relMSE over fp32 at 4 / 16 / 64 spp on validation, Percentile at
  +2 / +6 / +13 % (docs/gradnet.md, "Reduced precision"). Entropy, 48 bundles, the decoder or
  the encoder kept in fp32, or only Conv / ConvTranspose quantised were no better.

Writes <out>, <out>.sha256 (`sha256sum` format) and the models.json entry for <out> (source
model and its SHA-256, the calibration files and their SHA-256 digest, the options, the
onnxruntime version).
"""
import argparse
import collections
import hashlib
import json
import os
import tempfile

import numpy as np
import onnx

from . import ONNX_DIR
from . import output_layer
from . import pipeline as pl

DEFAULT_DATA = os.path.expanduser("~/.cache/gdrecon/data/train2")
DEFAULT_FRAMES = 24
DEFAULT_EXCLUDE = "/d1/d1.0/Conv,/g1/g1.0/Conv,/out/conv/Conv"


def sha256_file(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def calibration_files(data, frames):
    """`frames` bundles of `data` (sorted names, even stride). Refuses a validation or test
    directory by name: calibration sees the training split only."""
    parts = os.path.normpath(os.path.abspath(data)).split(os.sep)
    if any(p in ("val", "test") for p in parts):
        raise SystemExit(f"{data}: calibration reads the training split only, not val or test")
    files = sorted(f for f in os.listdir(data) if f.endswith(".exr"))
    if not files:
        raise SystemExit(f"{data}: no .exr bundles")
    if frames <= 0 or frames >= len(files):
        return [os.path.join(data, f) for f in files]
    step = len(files) / frames
    return [os.path.join(data, files[int(i * step)]) for i in range(frames)]


def calibration_inputs(files, use_features):
    """[{'data': 1 x Cd x Hp x Wp, 'grad': 1 x 2 x Hp x Wp}], three per file (R, G, B)."""
    out = []
    for f in files:
        fr = pl.sanitize(pl.read_frame(f))
        data, grad, _ = pl.prepare_inputs(fr, use_features)
        for c in range(data.shape[0]):
            out.append({"data": data[c:c + 1], "grad": grad[c:c + 1]})
    return out


def quantize(model, out, feeds, activation="u8", fmt="qdq", exclude=(), method="minmax",
             per_channel=True, reduce_range=False, overrides=None, split_output=True):
    """Static quantisation of `model` to `out` with `feeds` as calibration data. `overrides`:
    {tensor name: [{"scale": float32, "zero_point": uint8}]}, ranges that calibration does not
    set (ONNX Runtime's TensorQuantOverrides; `qat.py` passes the ranges it tuned for).
    `split_output`: a GradNet output convolution kept in fp32 leaves the graph
    (`output_layer.split`)."""
    from onnxruntime.quantization import (CalibrationDataReader, CalibrationMethod, QuantFormat,
                                          QuantType, quantize_static)

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.it = iter(feeds)

        def get_next(self):
            return next(self.it, None)

    methods = {"minmax": CalibrationMethod.MinMax, "percentile": CalibrationMethod.Percentile,
               "entropy": CalibrationMethod.Entropy}
    acts = {"u8": QuantType.QUInt8, "s8": QuantType.QInt8}
    with tempfile.TemporaryDirectory() as tmp:
        # quantize_static writes its augmented calibration model next to a temporary copy
        src = os.path.join(tmp, "src.onnx")
        onnx.save(onnx.load(model), src)
        quantize_static(src, out, Reader(),
                        quant_format=QuantFormat.QDQ if fmt == "qdq" else QuantFormat.QOperator,
                        per_channel=per_channel, reduce_range=reduce_range,
                        activation_type=acts[activation], weight_type=QuantType.QInt8,
                        nodes_to_exclude=list(exclude), calibrate_method=methods[method],
                        extra_options={"WeightSymmetric": True, "ActivationSymmetric": False,
                                       **({"TensorQuantOverrides": overrides} if overrides else {})})
    # keep the source's metadata (mu, data_channels, size_multiple, ...) and say what this is
    src_m = onnx.load(model)
    m = onnx.load(out)
    props = {p.key: p.value for p in src_m.metadata_props}
    props.update({"precision": "int8", "quant_format": fmt, "activation_type": activation,
                  "source_sha256": sha256_file(model)})
    del m.metadata_props[:]
    for k in sorted(props):
        m.metadata_props.add(key=k, value=props[k])
    m.ir_version = min(m.ir_version, src_m.ir_version)
    if fmt == "qdq":
        share_shuffle_quantization(m)
        if split_output and output_layer.CONV in exclude and \
                any(n.name == output_layer.CONV for n in m.graph.node):
            output_layer.split(m)
    onnx.save(m, out)
    return m


def shuffle_pairs(m):
    """[(crop output, shuffle input)]: the decoder's sub-pixel layers (`export.py`), each a
    DepthToSpace whose output only a Slice reads, named by the tensors the QDQ graph quantises
    (the Slice's output and the DepthToSpace's input, a ReLU's output)."""
    by_output = {o: n for n in m.graph.node for o in n.output}
    readers = collections.Counter(i for n in m.graph.node for i in n.input)
    pairs = []
    for n in m.graph.node:
        if n.op_type != "Slice":
            continue
        shuffle = by_output.get(n.input[0])
        if shuffle is None or shuffle.op_type != "DepthToSpace" or readers[shuffle.output[0]] != 1:
            continue
        src = by_output.get(shuffle.input[0])
        if src is not None and src.op_type == "DequantizeLinear":
            src = by_output.get(src.input[0])
            if src is not None and src.op_type == "QuantizeLinear":
                pairs.append((n.output[0], src.input[0]))
    return pairs


def share_shuffle_quantization(m):
    """Gives each sub-pixel layer's crop (Slice, the only reader of the shuffle in
    `export.py`'s graph) the quantisation of its shuffle's input, so
    that ONNX Runtime drops the DequantizeLinear / QuantizeLinear pair around the shuffle and the
    crop and runs both on the uint8 tensor: 11 % of the int8 GradNet graph's time at 1280 x 720
    (docs/gradnet.md, "Reduced precision"). Both only move values, so the tensor's range is its
    input's; with a scale of its own (calibration sees a cropped range) the shuffle ran in fp32
    between a dequantisation and a requantisation, which was also one more rounding."""
    qparams = {n.input[0]: (n.input[1], n.input[2]) for n in m.graph.node
               if n.op_type == "QuantizeLinear"}
    quantised = {n.output[0]: n.input[0] for n in m.graph.node if n.op_type == "QuantizeLinear"}
    for crop, src in shuffle_pairs(m):
        scale, zero = qparams[src]
        for n in m.graph.node:
            if (n.op_type == "QuantizeLinear" and n.input[0] == crop) or \
                    (n.op_type == "DequantizeLinear" and quantised.get(n.input[0]) == crop):
                n.input[1], n.input[2] = scale, zero
    used = {i for n in m.graph.node for i in n.input}
    keep = [i for i in m.graph.initializer if i.name in used]
    del m.graph.initializer[:]
    m.graph.initializer.extend(keep)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=os.path.join(ONNX_DIR, "gradnet.onnx"))
    ap.add_argument("--out", required=True)
    ap.add_argument("--data", default=DEFAULT_DATA, help="training split (default %(default)s)")
    ap.add_argument("--frames", type=int, default=DEFAULT_FRAMES,
                    help="calibration bundles, 0 = all (default %(default)s)")
    ap.add_argument("--activation", choices=("u8", "s8"), default="u8")
    ap.add_argument("--format", choices=("qdq", "qop"), default="qdq")
    ap.add_argument("--method", choices=("minmax", "percentile", "entropy"), default="percentile")
    ap.add_argument("--exclude", default=DEFAULT_EXCLUDE,
                    help="comma-separated node names kept in fp32 (default %(default)s)")
    ap.add_argument("--no-manifest", action="store_true", help="do not write .sha256 / models.json")
    ap.add_argument("--check-deterministic", action="store_true",
                    help="quantise twice and compare the files")
    args = ap.parse_args(argv)
    import onnxruntime

    src = onnx.load(args.model)
    dch = src.graph.input[0].type.tensor_type.shape.dim[1].dim_value
    files = calibration_files(args.data, args.frames)
    feeds = calibration_inputs(files, use_features=dch == 8)
    exclude = [n for n in args.exclude.split(",") if n]
    opts = dict(activation=args.activation, fmt=args.format, exclude=exclude, method=args.method)
    m = quantize(args.model, args.out, feeds, **opts)
    digest = sha256_file(args.out)
    print(f"{args.out}: {len(files)} calibration bundles ({len(feeds)} channel inputs), "
          f"sha256 {digest}", flush=True)
    if args.check_deterministic:
        with tempfile.TemporaryDirectory() as tmp:
            again = os.path.join(tmp, "again.onnx")
            quantize(args.model, again, feeds, **opts)
            if sha256_file(again) != digest:
                raise SystemExit("quantisation is not deterministic: two runs gave different files")
        print("deterministic: a second run gave the same file", flush=True)
    if args.no_manifest:
        return
    base = os.path.basename(args.out)
    with open(args.out + ".sha256", "w") as f:
        f.write(f"{digest}  {base}\n")
    names = [os.path.basename(f) for f in files]
    from .export import update_manifest
    entry = {"file": base, "sha256": digest, "bytes": os.path.getsize(args.out),
             "precision": "int8", "ir_version": m.ir_version, "opset": m.opset_import[0].version,
             "inputs": {"data": ["N", dch, "H", "W"], "grad": ["N", 2, "H", "W"]},
             "outputs": output_layer.manifest_outputs(m),
             "source": {"file": os.path.basename(args.model), "sha256": sha256_file(args.model)},
             "quantization": {"tool": f"onnxruntime.quantization {onnxruntime.__version__}",
                              "format": args.format, "weights": "int8 symmetric per channel",
                              "activations": f"{args.activation} asymmetric per tensor",
                              "reduce_range": False, "calibration": args.method,
                              "nodes_in_fp32": exclude},
             "calibration": {"split": "train2 (training only)", "dir": args.data.replace(os.path.expanduser("~"), "~"),
                             "bundles": names, "channel_inputs": len(feeds),
                             "bundles_sha256": hashlib.sha256("\n".join(
                                 sha256_file(f) for f in files).encode()).hexdigest()}}
    update_manifest(entry)


if __name__ == "__main__":
    main()
