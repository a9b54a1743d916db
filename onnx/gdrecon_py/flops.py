"""Exact multiply-add count of an exported GradNet graph at a given size, and the sustained
convolution throughput of ONNX Runtime on this machine: together, the floor of the network's
run time (docs/gradnet.md, "Speed").

    source onnx/env.sh
    $GDRECON_PYTHON -m gdrecon_py.flops onnx/gradnet.onnx --size 1280x720 --measure

Counting: shapes come from ONNX shape inference with the inputs fixed to 1 x C x H x W (sizes
padded to a multiple of 8 first, as the pipeline does); a Conv costs N Cout Hout Wout (Cin /
group) kh kw multiply-adds, a ConvTranspose N Cin Hin Win (Cout / group) kh kw. Everything else
(activations, concatenations, slices) is listed by output elements, not FLOPs. One FLOP count =
2 x multiply-adds, x 3 for the three colour channels of a frame.

--measure times, with the settings the Rust path uses (intra-op threads 2, no spinning,
inter-op 1, ORT_ENABLE_ALL, CPU arena): a single 3 x 3 convolution 256 -> 256 at 1/8 of the
frame (the residual blocks' shape, 58 % of the work) and the whole graph, median of --runs.
--int8 times that convolution (with its LeakyRelu) in fp32 and quantised as `quantize.py` does
(QDQ u8s8, QDQ s8s8, QOperator u8s8; per-channel weights, calibrated on the random input),
interleaved, median of --runs: the int8 throughput behind the int8 floor (docs/gradnet.md,
"Reduced precision").
"""
import argparse
import collections
import statistics
import time

import numpy as np
import onnx
from onnx import helper, shape_inference, TensorProto

from .runtime import session


def parse_size(s):
    w, h = s.lower().split("x")
    return int(w), int(h)


def pad8(n):
    return (n + 7) // 8 * 8


def count(path, width, height):
    m = onnx.load(path)
    for inp in m.graph.input:
        dims = inp.type.tensor_type.shape.dim
        dims[0].dim_value, dims[2].dim_value, dims[3].dim_value = 1, pad8(height), pad8(width)
    m = shape_inference.infer_shapes(m)
    shapes = {}
    for vi in list(m.graph.value_info) + list(m.graph.input) + list(m.graph.output):
        shapes[vi.name] = [d.dim_value for d in vi.type.tensor_type.shape.dim]
    inits = {i.name: list(i.dims) for i in m.graph.initializer}
    # a QDQ graph (quantize.py) feeds its convs through DequantizeLinear: count the weights behind it
    for node in m.graph.node:
        if node.op_type == "DequantizeLinear" and node.input[0] in inits:
            inits[node.output[0]] = inits[node.input[0]]
    macs = collections.Counter()
    rows = []
    elements = collections.Counter()
    for node in m.graph.node:
        attrs = {a.name: helper.get_attribute_value(a) for a in node.attribute}
        group = attrs.get("group", 1)
        if node.op_type in ("Conv", "ConvTranspose"):
            w = inits[node.input[1]]
            if node.op_type == "Conv":
                n, cout, ho, wo = shapes[node.output[0]]
                mac = n * cout * ho * wo * (w[1]) * w[2] * w[3]
            else:
                n, cin, hi, wi = shapes[node.input[0]]
                mac = n * cin * hi * wi * (w[1]) * w[2] * w[3]
            macs[node.op_type] += mac
            rows.append((node.name, node.op_type, w, mac))
        else:
            out = shapes.get(node.output[0])
            if out:
                elements[node.op_type] += int(np.prod(out))
    return macs, rows, elements


def median_time(fn, runs, warmup=2):
    for _ in range(warmup):
        fn()
    ts = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def conv_throughput(h, w, cin=256, cout=256, k=3, runs=20):
    """Median GFLOP/s of one k x k convolution cin -> cout on a 1 x cin x h x w input."""
    rng = np.random.default_rng(0)
    wt = helper.make_tensor("w", TensorProto.FLOAT, [cout, cin, k, k],
                            (rng.standard_normal(cout * cin * k * k) * 0.02).astype(np.float32))
    b = helper.make_tensor("b", TensorProto.FLOAT, [cout], np.zeros(cout, np.float32))
    node = helper.make_node("Conv", ["x", "w", "b"], ["y"], pads=[k // 2] * 4)
    g = helper.make_graph([node], "conv", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, cin, h, w])],
                          [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, cout, h, w])], [wt, b])
    model = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    s = session(model.SerializeToString())
    x = rng.random((1, cin, h, w), dtype=np.float32)
    t = median_time(lambda: s.run(None, {"x": x}), runs)
    return 2 * cin * cout * k * k * h * w / t / 1e9, t


def conv_int8_throughput(h, w, runs=15, cin=256, cout=256):
    """{form: (GOP/s, seconds)} of a 3x3 conv cin -> cout + LeakyRelu on 1 x cin x h x w, fp32
    and int8 forms, interleaved."""
    import os
    import tempfile
    from onnxruntime.quantization import (CalibrationDataReader, QuantFormat, QuantType,
                                          quantize_static)
    rng = np.random.default_rng(0)
    wt = helper.make_tensor("w", TensorProto.FLOAT, [cout, cin, 3, 3],
                            (rng.standard_normal(cout * cin * 9) * 0.02).astype(np.float32))
    b = helper.make_tensor("b", TensorProto.FLOAT, [cout], np.zeros(cout, np.float32))
    nodes = [helper.make_node("Conv", ["x", "w", "b"], ["c"], pads=[1] * 4),
             helper.make_node("LeakyRelu", ["c"], ["y"], alpha=0.01)]
    g = helper.make_graph(nodes, "conv", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, cin, h, w])],
                          [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, cout, h, w])], [wt, b])
    model = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    x = rng.random((1, cin, h, w), dtype=np.float32)

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.it = iter([{"x": x}])

        def get_next(self):
            return next(self.it, None)
    forms = {"fp32": ("fp32", None, None), "qdq_u8s8": ("qdq", QuantFormat.QDQ, QuantType.QUInt8),
             "qdq_s8s8": ("qdq", QuantFormat.QDQ, QuantType.QInt8),
             "qop_u8s8": ("qop", QuantFormat.QOperator, QuantType.QUInt8)}
    sess = {}
    with tempfile.TemporaryDirectory() as tmp:
        src = os.path.join(tmp, "conv.onnx")
        onnx.save(model, src)
        for name, (_, fmt, act) in forms.items():
            path = src
            if fmt is not None:
                path = os.path.join(tmp, f"{name}.onnx")
                quantize_static(src, path, Reader(), quant_format=fmt, per_channel=True,
                                reduce_range=False, activation_type=act, weight_type=QuantType.QInt8)
            sess[name] = session(path)
    ts = {k: [] for k in sess}
    for s in sess.values():
        s.run(None, {"x": x})
        s.run(None, {"x": x})
    for _ in range(runs):
        for k, s in sess.items():
            t = time.perf_counter()
            s.run(None, {"x": x})
            ts[k].append(time.perf_counter() - t)
    ops = 2 * cin * cout * 9 * h * w
    return {k: (ops / statistics.median(v) / 1e9, statistics.median(v)) for k, v in ts.items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model")
    ap.add_argument("--size", default="1280x720", type=parse_size)
    ap.add_argument("--measure", action="store_true")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--int8", action="store_true", help="time the residual conv in int8 forms too")
    args = ap.parse_args(argv)
    width, height = args.size
    macs, rows, elements = count(args.model, width, height)
    total = sum(macs.values())
    res = sum(r[3] for r in rows if "/res/" in r[0])
    print(f"{args.model} at {width} x {height} (padded {pad8(width)} x {pad8(height)}), one channel:")
    for name, op, w, mac in rows:
        print(f"  {name:40s} {op:14s} {str(w):22s} {mac / 1e9:8.3f} GMAC")
    for op, mac in macs.items():
        print(f"  total {op}: {mac / 1e9:.2f} GMAC ({100 * mac / total:.1f} %)")
    print(f"  residual blocks: {res / 1e9:.2f} GMAC ({100 * res / total:.1f} %)")
    print(f"  other ops, output elements: " + ", ".join(f"{k} {v / 1e6:.1f} M" for k, v in elements.most_common()))
    frame_flop = 2 * 3 * total
    print(f"frame (3 channels): {3 * total / 1e9:.1f} GMAC = {frame_flop / 1e12:.3f} TFLOP")
    if args.int8:
        for k, (gops, t) in conv_int8_throughput(pad8(height) // 8, pad8(width) // 8).items():
            print(f"3x3 conv 256->256 + LeakyRelu at {pad8(width) // 8} x {pad8(height) // 8}, {k}: "
                  f"{t * 1e3:.1f} ms, {gops:.0f} GOP/s (median of 15, interleaved)")
    if args.measure:
        gflops, t = conv_throughput(pad8(height) // 8, pad8(width) // 8)
        print(f"3x3 conv 256->256 at {pad8(width) // 8} x {pad8(height) // 8}: {t * 1e3:.1f} ms, {gflops:.0f} GFLOP/s (median of 20)")
        floor = frame_flop / (gflops * 1e9)
        print(f"floor at that throughput: {floor:.2f} s per frame; 1.3 x floor = {1.3 * floor:.2f} s")
        s = session(args.model)
        rng = np.random.default_rng(0)
        dch = s.get_inputs()[0].shape[1]
        data = rng.random((1, dch, pad8(height), pad8(width)), dtype=np.float32)
        grad = (rng.standard_normal((1, 2, pad8(height), pad8(width))) * 0.1).astype(np.float32)
        t = median_time(lambda: s.run(None, {"data": data, "grad": grad}), args.runs, warmup=1)
        print(f"whole graph, one channel: {t:.3f} s (median of {args.runs}), {2 * total / t / 1e9:.0f} GFLOP/s; "
              f"x 3 channels = {3 * t:.2f} s = {3 * t / floor:.2f} x floor")


if __name__ == "__main__":
    main()
