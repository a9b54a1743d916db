"""The deployed int8 GradNet graph: `onnx/gradnet_int8.onnx`'s decoder rewritten in the layout
ONNX Runtime's int8 convolutions run in (issue #19 item 3).

    source onnx/env.sh
    $GDRECON_PYTHON -m gdrecon_py.nhwc                # onnx/gradnet_int8.onnx -> onnx/gradnet_int8_nhwc.onnx

ONNX Runtime runs every int8 convolution channels-last (NHWC) and wraps what it cannot run so
in transposes. In the QDQ graph `quantize.py` writes (the form quantisation-aware fine-tuning
reads and writes, `qat.py`), 31 % of one 1280 x 720 channel's run was such data movement
(docs/gradnet.md, "The deployed graph"): each sub-pixel layer's DepthToSpace (CRD) and crop ran
channels-first between two transposes, an element-by-element shuffle; `u3`'s four output phases
were concatenated channels-last (re-quantised to the concatenation's scale), then transposed to
the graph's channels-first output. Two rewrites, both to the uint8 graph:

1. `shuffle`: each sub-pixel layer's convolution gets its output channels in DCR order (channel
   `(2 i + j) C + c` for CRD's `4 c + 2 i + j`: a permutation of its int8 weights, their
   per-channel scales and its int32 bias), and its DepthToSpace and crop become a
   channels-last transpose of whole `C`-byte runs (Transpose, Reshape, Transpose, Reshape,
   Slice) between a transpose to NHWC and one back, which ONNX Runtime cancels against those
   around the convolutions. Exact: the same uint8 values move.
2. `merge_phases`: `u3`'s four phase convolutions (2 x 2, pads `(1 - a, 1 - b, a, b)`) become one
   2 x 2 convolution with pads 1 and 4 x 32 output channels over `(h + 1) x (w + 1)`, quantised
   once with the concatenation's scale, returned channels-last: `phases` is `N x (h + 1) x
   (w + 1) x 128`, phase `(a, b)` (channels `(2 a + b) 32 ..`) at rows `a .. a + h`, columns
   `b .. b + w`. Not exact: the phases were rounded twice (to their own scale, then to the
   concatenation's), now once; 0.56 % of the values move by one step (`--check`).

The output layer's metadata says the layout (`output_layer.layout` = `nhwc_padded`);
`output_layer.apply` (the reference) and `src/recon/gradnet/output_layer.rs` read it.

Writes <out> and <out>.sha256 (what gdrecon checks a model file against), and for a file in
onnx/ its models.json entry (its source's file and SHA-256).
"""
import argparse
import copy
import os

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from . import ONNX_DIR
from . import output_layer

LAYOUT = output_layer.NHWC_PADDED
SOURCE = os.path.join(ONNX_DIR, "gradnet_int8.onnx")
OUT = os.path.join(ONNX_DIR, "gradnet_int8_nhwc.onnx")


class _Graph:
    """Index of a graph's nodes and initializers, rebuilt after each edit."""

    def __init__(self, m):
        self.g = m.graph
        self.init = {i.name: i for i in self.g.initializer}
        self.producer = {o: n for n in self.g.node for o in n.output}
        self.readers = {}
        for n in self.g.node:
            for i in n.input:
                self.readers.setdefault(i, []).append(n)

    def array(self, name):
        """An initializer's or a Constant node's value."""
        if name in self.init:
            return numpy_helper.to_array(self.init[name])
        n = self.made_by(name, "Constant")
        return numpy_helper.to_array(helper.get_attribute_value(n.attribute[0]))

    def set_array(self, name, a):
        self.init[name].CopyFrom(numpy_helper.from_array(a, name))

    def only_reader(self, tensor, op):
        r = self.readers.get(tensor, [])
        if len(r) != 1 or r[0].op_type != op:
            raise ValueError(f"{tensor}: read by {[n.op_type for n in r]}, expected one {op}")
        return r[0]

    def made_by(self, tensor, op):
        n = self.producer.get(tensor)
        if n is None or n.op_type != op:
            raise ValueError(f"{tensor}: made by {n.op_type if n else None}, expected {op}")
        return n

    def splice(self, drop, new, at):
        """Replaces the nodes named in `drop` by `new`, inserted where node `at` was (the graph
        stays topologically sorted: `new` reads only tensors made before `at`)."""
        nodes = list(self.g.node)
        i = [n.name for n in nodes].index(at)
        nodes = nodes[:i] + new + nodes[i:]
        nodes = [n for n in nodes if n.name not in drop]
        read = {i for n in nodes for i in n.input} | {o.name for o in self.g.output}
        nodes = [n for n in nodes if n.op_type != "Constant" or n.output[0] in read]
        del self.g.node[:]
        self.g.node.extend(nodes)
        used = {i for n in self.g.node for i in n.input}
        kept = [i for i in self.g.initializer if i.name in used]
        del self.g.initializer[:]
        self.g.initializer.extend(kept)


def _const(name, values):
    return numpy_helper.from_array(np.array(values, np.int64), name)


def _conv_params(gr, conv):
    """The int8 weight and int32 bias initializers of a QDQ convolution, with their scales and
    zero points: [(quantised, scale, zero point)] for the weight, then the bias."""
    out = []
    for tensor in conv.input[1:3]:
        dq = gr.made_by(tensor, "DequantizeLinear")
        if any(i not in gr.init for i in dq.input):
            raise ValueError(f"{conv.name}: {tensor} is not a quantised initializer")
        out.append(list(dq.input))
    return out


def shuffle(m):
    """Rewrite 1 (module doc) on every sub-pixel layer: Q -> DQ -> DepthToSpace(CRD, 2) ->
    Slice(1 : -1 on H and W) -> Q (the same scale and zero point). Returns their count."""
    done = 0
    for d2s in [n for n in m.graph.node if n.op_type == "DepthToSpace"]:
        gr = _Graph(m)
        attrs = {a.name: helper.get_attribute_value(a) for a in d2s.attribute}
        if attrs.get("blocksize") != 2 or attrs.get("mode", b"DCR") != b"CRD":
            raise ValueError(f"{d2s.name}: not a CRD shuffle by 2")
        dq = gr.made_by(d2s.input[0], "DequantizeLinear")
        q = gr.made_by(dq.input[0], "QuantizeLinear")
        conv = gr.made_by(q.input[0], "Conv")
        crop = gr.only_reader(d2s.output[0], "Slice")
        q2 = gr.only_reader(crop.output[0], "QuantizeLinear")
        if list(q2.input[1:]) != list(q.input[1:]) or list(dq.input[1:]) != list(q.input[1:]):
            raise ValueError(f"{d2s.name}: the shuffle and crop do not share their input's "
                             "quantisation (quantize.share_shuffle_quantization)")
        starts, ends, axes = (gr.array(t).tolist() for t in crop.input[1:4])
        if (starts, ends, axes) != ([1, 1], [-1, -1], [2, 3]) or len(crop.input) > 4:
            raise ValueError(f"{crop.name}: not a crop of 1 on H and W")
        if len(gr.readers.get(q.output[0], [])) != 1:
            raise ValueError(f"{q.name}: read by more than the shuffle")
        # the convolution's output channels in DCR order
        (wq, ws, wz), (bq, bs, bz) = _conv_params(gr, conv)
        c4 = gr.array(wq).shape[0]
        c = c4 // 4
        perm = np.array([4 * k + 2 * i + j for i in range(2) for j in range(2) for k in range(c)])
        for name in (wq, ws, wz, bq, bs, bz):
            a = gr.array(name)
            if a.shape[:1] != (c4,):
                raise ValueError(f"{conv.name}: {name} is not per output channel")
            gr.set_array(name, a[perm])
        p = d2s.name.rsplit("/", 1)[0] + "/nhwc"
        shape_nhw = [p + "_nhw_start", p + "_nhw_end"]
        # NCHW [N, 4C, h, w] -> NHWC, split [N, h, w, i, j, C] (DCR), moved to [N, h, i, w, j, C],
        # merged [N, 2h, 2w, C], cropped, back to NCHW (ONNX Runtime cancels both transposes)
        new = [
            helper.make_node("Transpose", [q.output[0]], [p + "_in"], perm=[0, 2, 3, 1], name=p + "_in"),
            helper.make_node("Reshape", [p + "_in", p + "_split"], [p + "_split6"], name=p + "_split6"),
            helper.make_node("Transpose", [p + "_split6"], [p + "_moved"], perm=[0, 1, 3, 2, 4, 5],
                             name=p + "_moved"),
            helper.make_node("Shape", [p + "_in"], [p + "_shape"], name=p + "_shape"),
            helper.make_node("Slice", [p + "_shape"] + shape_nhw, [p + "_nhw"], name=p + "_nhw"),
            helper.make_node("Mul", [p + "_nhw", p + "_twice"], [p + "_nhw2"], name=p + "_nhw2"),
            helper.make_node("Concat", [p + "_nhw2", p + "_c"], [p + "_shape2"], axis=0, name=p + "_shape2"),
            helper.make_node("Reshape", [p + "_moved", p + "_shape2"], [p + "_full"], name=p + "_full"),
            helper.make_node("Slice", [p + "_full", p + "_first", p + "_last", p + "_hw"], [p + "_crop"],
                             name=p + "_crop"),
            helper.make_node("Transpose", [p + "_crop"], [q2.output[0]], perm=[0, 3, 1, 2], name=p + "_out"),
        ]
        m.graph.initializer.extend([
            _const(p + "_split", [0, 0, 0, 2, 2, c]), _const(p + "_nhw_start", [0]),
            _const(p + "_nhw_end", [3]), _const(p + "_twice", [1, 2, 2]), _const(p + "_c", [c]),
            _const(p + "_first", [1, 1]), _const(p + "_last", [-1, -1]), _const(p + "_hw", [1, 2])])
        gr.splice({dq.name, d2s.name, crop.name, q2.name}, new, dq.name)
        done += 1
    return done


def merge_phases(m):
    """Rewrite 2 (module doc): the graph's output `phases` = Q(Concat(DQ(Q(Conv_k)))) over the
    four phase convolutions k = 2 a + b becomes one convolution, returned channels-last."""
    gr = _Graph(m)
    out = output_layer.OUTPUT
    q = gr.made_by(out, "QuantizeLinear")
    cat = gr.made_by(q.input[0], "Concat")
    convs, phase_q = [], []
    for k, t in enumerate(cat.input):
        dq = gr.made_by(t, "DequantizeLinear")
        pq = gr.made_by(dq.input[0], "QuantizeLinear")
        conv = gr.made_by(pq.input[0], "Conv")
        a, b = divmod(k, 2)
        attrs = {x.name: helper.get_attribute_value(x) for x in conv.attribute}
        if attrs.get("kernel_shape") != [2, 2] or attrs.get("pads") != [1 - a, 1 - b, a, b] or \
                attrs.get("strides", [1, 1]) != [1, 1] or attrs.get("group", 1) != 1 or \
                attrs.get("dilations", [1, 1]) != [1, 1]:
            raise ValueError(f"{conv.name}: not phase ({a}, {b}) of a sub-pixel layer")
        if len(gr.readers[pq.output[0]]) != 1 or len(gr.readers[conv.output[0]]) != 1:
            raise ValueError(f"{conv.name}: its output is read by more than the concatenation")
        convs.append(conv)
        phase_q.append(pq)
    if len({c.input[0] for c in convs}) != 1:
        raise ValueError(f"{cat.name}: the phases read different inputs")
    # the phases' quantisation clamps at zero (their ReLU); so must the merged one
    for t in [pq.input[2] for pq in phase_q] + [q.input[2]]:
        if gr.array(t).item() != 0:
            raise ValueError(f"{t}: a phase's ReLU is its zero point 0; this one is not")
    parts = [_conv_params(gr, c) for c in convs]
    p = "/u3/merged"
    names = [[p + "_w", p + "_w_scale", p + "_w_zero_point"], [p + "_b", p + "_b_scale", p + "_b_zero_point"]]
    for which in range(2):
        for j in range(3):
            a = np.concatenate([gr.array(part[which][j]) for part in parts])
            m.graph.initializer.append(numpy_helper.from_array(a, names[which][j]))
    ch = len(gr.array(parts[0][0][0])) * len(parts)
    new = [
        helper.make_node("DequantizeLinear", names[0], [p + "_weight"], axis=0, name=p + "_weight"),
        helper.make_node("DequantizeLinear", names[1], [p + "_bias"], axis=0, name=p + "_bias"),
        helper.make_node("Conv", [convs[0].input[0], p + "_weight", p + "_bias"], [p + "_conv"],
                         dilations=[1, 1], kernel_shape=[2, 2], pads=[1, 1, 1, 1], name=p + "_conv"),
        helper.make_node("QuantizeLinear", [p + "_conv"] + list(q.input[1:]), [p + "_q"], name=p + "_q"),
        helper.make_node("Transpose", [p + "_q"], [out], perm=[0, 2, 3, 1], name=p + "_nhwc"),
    ]
    drop = {n.name for n in convs} | {n.name for n in phase_q} | {cat.name, q.name} | {
        gr.made_by(t, "DequantizeLinear").name for t in cat.input} | {
        gr.made_by(c.input[i], "DequantizeLinear").name for c in convs for i in (1, 2)}
    gr.splice(drop, new, convs[0].name)
    del m.graph.output[:]
    m.graph.output.append(helper.make_tensor_value_info(out, TensorProto.UINT8, ["N", "h1", "w1", ch]))
    del m.graph.value_info[:]


def rewrite(m):
    """Both rewrites on a copy of the int8 graph `m` (`quantize.py`'s, its output layer split
    off), with the layout in its metadata."""
    m = copy.deepcopy(m)
    meta = {p.key: p.value for p in m.metadata_props}
    if output_layer.PREFIX + "weight" not in meta:
        raise ValueError("not an int8 graph ending at its output layer's phases (output_layer.split)")
    if meta.get(output_layer.PREFIX + "layout", output_layer.CANONICAL) != output_layer.CANONICAL:
        raise ValueError("already rewritten")
    if shuffle(m) != 2:
        raise ValueError("expected the two sub-pixel layers u1 and u2")
    merge_phases(m)
    meta[output_layer.PREFIX + "layout"] = LAYOUT
    del m.metadata_props[:]
    for k in sorted(meta):
        m.metadata_props.add(key=k, value=meta[k])
    onnx.checker.check_model(m)
    return m


def check(source, rewritten, size=(72, 136), seed=0):
    """Both graphs in ONNX Runtime on one random input: (values compared, largest difference in
    quantisation steps, fraction that differ) of the phases in the canonical layout."""
    from . import runtime
    h, w = size
    rng = np.random.default_rng(seed)
    feed = {"data": rng.random((1, 8, h, w), dtype=np.float32),
            "grad": (rng.standard_normal((1, 2, h, w)) * 0.05).astype(np.float32)}
    a = runtime.session(source).run([output_layer.OUTPUT], feed)[0]
    b = output_layer.canonical(runtime.session(rewritten).run([output_layer.OUTPUT], feed)[0], LAYOUT)
    d = np.abs(a.astype(np.int32) - b.astype(np.int32))
    return d.size, int(d.max()), float((d > 0).mean())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=SOURCE)
    ap.add_argument("--out", default=OUT)
    ap.add_argument("--no-manifest", action="store_true", help="write neither .sha256 nor models.json")
    args = ap.parse_args(argv)
    from .export import update_manifest
    from .quantize import sha256_file
    src = onnx.load(args.model)
    m = rewrite(src)
    onnx.save(m, args.out)
    n, worst, frac = check(args.model, args.out)
    if worst > 1:
        raise SystemExit(f"{args.out}: phases differ from {args.model} by {worst} steps")
    digest = sha256_file(args.out)
    print(f"{args.out}: sha256 {digest}; against {args.model}: {frac:.4%} of {n} phase values one "
          "step apart, the rest equal", flush=True)
    if args.no_manifest:
        return
    base = os.path.basename(args.out)
    with open(args.out + ".sha256", "w") as f:
        f.write(f"{digest}  {base}\n")
    if os.path.dirname(os.path.abspath(args.out)) != os.path.abspath(ONNX_DIR):
        return        # a model of one's own: its .sha256 is what gdrecon checks it against
    entry = {"file": base, "sha256": digest, "bytes": os.path.getsize(args.out), "precision": "int8",
             "ir_version": m.ir_version, "opset": m.opset_import[0].version,
             "inputs": {"data": ["N", 8, "H", "W"], "grad": ["N", 2, "H", "W"]},
             "outputs": output_layer.manifest_outputs(m),
             "source": {"file": os.path.basename(args.model), "sha256": sha256_file(args.model),
                        "rewrite": "gdrecon_py.nhwc (the decoder channels-last; u3's phases "
                                   "merged and quantised once)",
                        "phases_one_step_apart": frac}}
    update_manifest(entry)


if __name__ == "__main__":
    main()
