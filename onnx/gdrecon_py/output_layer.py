"""GradNet's output convolution outside the int8 graph (issue #19 item 3).

In `onnx/gradnet_int8.onnx` the output convolution (32 -> 1 channels, 3 x 3, kept in fp32) is not a
node: the graph ends at its quantised input, `u3`'s four output phases at half resolution
(output `phases`: N x 128 x H/2 x W/2 uint8, channel `(2 a + b) * 32 + c` holding channel `c` at
full-resolution rows of parity `a` and columns of parity `b`), and the convolution's weights, bias
and that tensor's scale and zero point travel in the graph's metadata (`output_layer.*`). The
caller applies it: `apply` here (the reference), `src/recon/gradnet/output_layer.rs` in the
library. Why: ONNX Runtime ran it as dequantisation (fp32, NCHW), a reorder to its blocked layout,
a convolution whose 4 outputs it pads to 16, and a reorder back: 73 of the 367 ms of one
1280 x 720 channel's run; done directly on the uint8 phases it is a few milliseconds (measured
in docs/gradnet.md, "Reduced precision"). The arithmetic is the same (the dequantised values,
the same weights and bias); only the order of the fp32 sums differs.

`split(model)` makes such a graph from a QDQ graph with the decoder of `export.py` (the output
convolution applied to the phases as one 3 x 3 convolution 128 -> 4, followed by a
DepthToSpace), checking that the phase form's weights are exactly the 3 x 3 kernel's.

The graph the library runs, `onnx/gradnet_int8_nhwc.onnx` (`nhwc.py`), returns the phases in
another layout, named by `output_layer.layout` (NHWC_PADDED): N x (h + 1) x (w + 1) x 128,
phase (a, b) at rows a .. a + h, columns b .. b + w; `apply` reads either (`canonical`).
"""
import numpy as np

OUTPUT = "phases"
CONV = "/out/conv/Conv"
PREFIX = "output_layer."
# `phases` layouts (`output_layer.layout`; absent: CANONICAL): `split`'s N x 4C x h x w, and
# `nhwc.py`'s N x (h + 1) x (w + 1) x 4C with phase (a, b) at rows a .. a + h, columns b .. b + w
CANONICAL = "nchw"
NHWC_PADDED = "nhwc_padded"


def _full_kernel(poly):
    """The 32 x 3 x 3 kernel whose phase form (`export.PolyphaseConv2d`) is `poly`
    (4 x 128 x 3 x 3), or ValueError."""
    ch = poly.shape[1] // 4
    # full-resolution tap r of output row parity 0 reads input phase pa at half-resolution
    # kernel row i: r = 2 (i - 1) + pa + 1
    tap = {0: (1, 0), 1: (0, 1), 2: (1, 1)}          # r -> (pa, i)
    w = np.zeros((ch, 3, 3), np.float32)
    for r, (pa, i) in tap.items():
        for s, (pb, j) in tap.items():
            w[:, r, s] = poly[0, (2 * pa + pb) * ch:(2 * pa + pb + 1) * ch, i, j]
    if not np.array_equal(phase_form(w), poly):
        raise ValueError("the output convolution is not the phase form of a 3 x 3 kernel")
    return w


def phase_form(w):
    """4 x 4C x 3 x 3: output phase (a, b), input phase (pa, pb), half-resolution taps (i, j)."""
    ch = w.shape[0]
    poly = np.zeros((4, 4 * ch, 3, 3), np.float32)
    for a in (0, 1):
        for b in (0, 1):
            for pa in (0, 1):
                for pb in (0, 1):
                    for i in range(3):
                        for j in range(3):
                            r, s = 2 * (i - 1) + pa - a + 1, 2 * (j - 1) + pb - b + 1
                            if 0 <= r < 3 and 0 <= s < 3:
                                poly[2 * a + b, (2 * pa + pb) * ch:(2 * pa + pb + 1) * ch, i, j] = w[:, r, s]
    return poly


def _floats(values):
    return " ".join(repr(float(v)) for v in np.asarray(values, np.float32).ravel())


def split(m):
    """Cuts the output convolution off the QDQ GradNet graph `m` (in place): the graph's output
    becomes the convolution's quantised input (`phases`), the layer goes into the metadata."""
    from onnx import TensorProto, helper, numpy_helper
    g = m.graph
    inits = {i.name: numpy_helper.to_array(i) for i in g.initializer}
    by_output = {o: n for n in g.node for o in n.output}
    conv = next((n for n in g.node if n.name == CONV), None)
    if conv is None:
        raise ValueError(f"no {CONV}: not export.py's GradNet graph")
    dq = by_output.get(conv.input[0])
    q = by_output.get(dq.input[0]) if dq is not None else None
    if dq is None or dq.op_type != "DequantizeLinear" or q is None or q.op_type != "QuantizeLinear":
        raise ValueError(f"{CONV}: its input is not a quantised tensor")
    if len(conv.input) < 3 or conv.input[1] not in inits or conv.input[2] not in inits:
        raise ValueError(f"{CONV}: its weights and bias are not fp32 initializers")
    poly, bias = inits[conv.input[1]], inits[conv.input[2]]
    if poly.shape[0] != 4 or poly.shape[2:] != (3, 3) or bias.shape != (4,) or len(set(bias.tolist())) != 1:
        raise ValueError(f"{CONV}: weights {poly.shape} are not the phase form of a 3 x 3 kernel")
    w = _full_kernel(poly)
    scale, zero = inits[q.input[1]], inits[q.input[2]]
    # everything that reads the phases, transitively, goes (by index: the protobuf wrappers'
    # identities are not stable)
    dead, live = set(), {q.output[0]}
    for k, n in enumerate(g.node):        # the graph is topologically sorted
        if any(i in live for i in n.input):
            dead.add(k)
            live.update(n.output)
    # `apply` stands for exactly what goes: the dequantisation, the convolution, the shuffle of
    # its four phases and the ReLU, ending at the graph's one output
    gone = sorted(g.node[k].op_type for k in dead)
    if gone != sorted(["DequantizeLinear", "Conv", "DepthToSpace", "Relu"]) or \
            [o.name for o in g.output] != [g.node[max(dead)].output[0]]:
        raise ValueError(f"after {CONV}: {gone}, not the output layer `apply` computes")
    q.output[0] = OUTPUT
    keep = [n for k, n in enumerate(g.node) if k not in dead]
    del g.node[:]
    g.node.extend(keep)
    del g.output[:]
    g.output.append(helper.make_tensor_value_info(OUTPUT, TensorProto.UINT8, ["N", 4 * w.shape[0], "h", "w"]))
    used = {i for n in g.node for i in n.input}
    kept = [i for i in g.initializer if i.name in used]
    del g.initializer[:]
    g.initializer.extend(kept)
    shapes = [v for v in g.value_info if v.name not in live]
    del g.value_info[:]
    g.value_info.extend(shapes)
    props = {p.key: p.value for p in m.metadata_props}
    props.update({PREFIX + "weight": _floats(w), PREFIX + "bias": _floats(bias[:1]),
                  PREFIX + "scale": _floats(scale.reshape(1)),
                  PREFIX + "zero_point": str(int(zero.reshape(()))),
                  PREFIX + "channels": str(w.shape[0])})
    del m.metadata_props[:]
    for k in sorted(props):
        m.metadata_props.add(key=k, value=props[k])
    return m


def manifest_outputs(m):
    """The graph's outputs as its models.json entry records them."""
    meta = {p.key: p.value for p in m.metadata_props}
    if PREFIX + "channels" not in meta:
        return {"output": ["N", 1, "H", "W"]}
    ch = int(meta[PREFIX + "channels"])
    shape = (["N", "H/2 + 1", "W/2 + 1", 4 * ch] if meta.get(PREFIX + "layout") == NHWC_PADDED
             else ["N", 4 * ch, "H/2", "W/2"])
    return {OUTPUT: shape,
            "output_layer": f"uint8 phases; the 3 x 3 convolution {ch} -> 1 and ReLU after them are "
                            f"in the metadata ({PREFIX}*) and applied by the caller"}


def read(meta):
    """The layer from a graph's metadata ({key: value}), or None if the graph has its own."""
    if PREFIX + "weight" not in meta:
        return None
    ch = int(meta[PREFIX + "channels"])
    w = np.array(meta[PREFIX + "weight"].split(), np.float32).reshape(ch, 3, 3)
    layout = meta.get(PREFIX + "layout", CANONICAL)
    if layout not in (CANONICAL, NHWC_PADDED):
        raise ValueError(f"{PREFIX}layout {layout!r}: not {CANONICAL!r} or {NHWC_PADDED!r}")
    return {"weight": w, "bias": np.float32(meta[PREFIX + "bias"]),
            "scale": np.float32(meta[PREFIX + "scale"]), "zero_point": int(meta[PREFIX + "zero_point"]),
            "layout": layout}


def canonical(phases, layout):
    """`phases` in `layout` as N x 4C x h x w (CANONICAL)."""
    if layout == CANONICAL:
        return phases
    n, h1, w1, c4 = phases.shape
    ch = c4 // 4
    parts = [phases[:, a:a + h1 - 1, b:b + w1 - 1, (2 * a + b) * ch:(2 * a + b + 1) * ch]
             for a in (0, 1) for b in (0, 1)]
    return np.ascontiguousarray(np.concatenate(parts, axis=3).transpose(0, 3, 1, 2))


def apply(layer, phases):
    """The output convolution on the graph's `phases` (N x 4C x h x w uint8, or the layout the
    layer says): N x 1 x 2h x 2w float32, `relu(bias + conv3x3(dequantised full-resolution
    tensor, zero padded))`."""
    phases = canonical(phases, layer.get("layout", CANONICAL))
    w = layer["weight"]
    n, c4, h, wd = phases.shape
    ch = c4 // 4
    v = (phases.astype(np.float64) - layer["zero_point"]) * np.float64(layer["scale"])
    full = np.zeros((n, ch, 2 * h + 2, 2 * wd + 2))
    for pa in (0, 1):
        for pb in (0, 1):
            k = 2 * pa + pb
            full[:, :, 1 + pa:1 + 2 * h:2, 1 + pb:1 + 2 * wd:2] = v[:, k * ch:(k + 1) * ch]
    out = np.full((n, 2 * h, 2 * wd), np.float64(layer["bias"]))
    for r in range(3):
        for s in range(3):
            out += np.einsum("c,ncyx->nyx", w[:, r, s].astype(np.float64),
                             full[:, :, r:r + 2 * h, s:s + 2 * wd])
    return np.maximum(out, 0.0).astype(np.float32)[:, None]
