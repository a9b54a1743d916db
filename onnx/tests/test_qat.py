"""Quantisation-aware fine-tuning (gdrecon_py.qat): the simulation must be the deployed int8
graph's arithmetic (checked against ONNX Runtime's quantiser and kernels), must vanish when off,
and a run must resume exactly."""
import json

import numpy as np
import pytest
import torch

from gdrecon_py import ONNX_DIR, pack, qat
from gdrecon_py.export import net_from_onnx

INT8 = f"{ONNX_DIR}/gradnet_int8.onnx"
FP32 = f"{ONNX_DIR}/gradnet.onnx"


def inputs(seed, h=32, w=48):
    """Smooth, image-like network inputs (mu-law colour in [0, 1], features, small gradients)."""
    g = torch.Generator().manual_seed(seed)
    base = torch.nn.functional.interpolate(torch.rand(1, 8, h // 8, w // 8, generator=g), size=(h, w),
                                           mode="bilinear", align_corners=False)
    data = (base + 0.05 * torch.rand(1, 8, h, w, generator=g)).clamp(0, 1)
    grad = 0.1 * (torch.rand(1, 2, h, w, generator=g) - 0.5)
    return data, grad


def test_off_is_the_fp32_network():
    torch.manual_seed(0)
    from gdrecon_py import gradnet as gn
    net = gn.GradNet().eval()
    ranges = {k: (0.01, 10) for k in qat.ACT_NAMES}
    sim = qat.QATGradNet(net, ranges).eval()
    sim.quant = False
    d, g = inputs(1)
    with torch.no_grad():
        assert torch.equal(sim(d, g), net(d, g))


def test_fake_act_is_quantizelinear_then_dequantizelinear():
    import onnx
    import onnxruntime as ort
    from onnx import TensorProto, helper
    scale, zp = 0.0123, 37
    x = np.concatenate([np.linspace(-1, 3.5, 4001, dtype=np.float32),
                        ((np.arange(-40, 220) + 0.5) * scale).astype(np.float32)])  # ties
    nodes = [helper.make_node("QuantizeLinear", ["x", "s", "z"], ["q"]),
             helper.make_node("DequantizeLinear", ["q", "s", "z"], ["y"])]
    graph = helper.make_graph(nodes, "qdq", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [x.size])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [x.size])],
                              [helper.make_tensor("s", TensorProto.FLOAT, [], [scale]),
                               helper.make_tensor("z", TensorProto.UINT8, [], [zp])])
    m = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    m.ir_version = 8
    want = ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, {"x": x})[0]
    got = qat.fake_act(torch.from_numpy(x), torch.tensor(scale), torch.tensor(zp, dtype=torch.int32)).numpy()
    assert np.array_equal(got, want)


def test_weight_scales_are_those_of_the_shipped_int8_graph():
    """The per-channel weight scales stored in `onnx/gradnet_int8.onnx` (ONNX Runtime's quantiser
    on export.py's sub-pixel decoder) are those the simulation computes from the same weights:
    the grouping of a transposed kernel's taps into sub-pixel channels is the graph's. (The
    dequantised weights are the graph's; ONNX Runtime's symmetric scales make max |q| = 127.)"""
    import onnx
    from onnx import numpy_helper
    net = qat.net_from_int8(INT8)
    inits = {i.name: numpy_helper.to_array(i) for i in onnx.load(INT8).graph.initializer}

    def same(ours, theirs):
        a = np.sort(np.asarray(ours, np.float64).ravel())
        b = np.sort(np.asarray(theirs, np.float64).ravel())
        return a.shape == b.shape and np.allclose(a, b, rtol=1e-6, atol=0)

    assert same(qat.weight_scale(net.d2[0].weight, False).numpy(), inits["d2.0.weight_scale"])
    assert same(qat.weight_scale(net.res[2].c1.weight, False).numpy(), inits["res.2.c1.weight_scale"])
    # u1: 512 distinct (channel, parity) scales, each once in the 2 x 2 sub-pixel conv
    s = qat.weight_scale(net.u1[0].weight, True)[0, :, :2, :2].numpy()
    assert same(s, inits["u1.0.conv.weight_scale"])
    s = qat.weight_scale(net.u3[0].weight, True)[0, :, :2, :2].numpy()
    assert same(s, np.concatenate([inits[f"u3.w{a}{b}_scale"] for a in range(2) for b in range(2)]))


def simulation_distances(path):
    """Mean |output| distances from ONNX Runtime's int8 output of the QDQ graph `path` on three
    inputs: the simulation of the graph (its own dequantised weights and activation ranges) and
    the fp32 network (`onnx/gradnet.onnx`), each a list."""
    from gdrecon_py import pipeline as pl
    sim = qat.QATGradNet(qat.net_from_int8(path), qat.ranges_from_int8(path)).eval()
    fp32 = net_from_onnx(FP32)
    s8 = pl.ort_runner(path)
    d8, d32 = [], []
    for seed in range(3):
        d, g = inputs(seed)
        o8 = s8(d.numpy(), g.numpy())
        with torch.no_grad():
            d8.append(np.abs(sim(d, g).numpy() - o8).mean())
            d32.append(np.abs(fp32(d, g).numpy() - o8).mean())
    return d8, d32


def test_simulation_is_onnxruntime_int8():
    """The simulation of the shipped int8 graph is ONNX Runtime's int8 output up to ties and
    int32 bias rounding: a small fraction of the int8 graph's distance from the fp32 network
    (measured 0.00005 against 0.0030 on a training frame, LeakyReLU graph)."""
    d8, d32 = simulation_distances(INT8)
    assert np.mean(d32) > 0
    assert np.mean(d8) < 0.1 * np.mean(d32), (d8, d32)


def test_run_resumes_exactly(tmp_path, leaky_int8):
    """Six steps in one go and three + a resumed three give the same weights and the same log."""
    rng = np.random.default_rng(3)
    H = W = 40
    frames = []
    for _ in range(2):
        img = torch.from_numpy(rng.random((1, 3, H, W)).astype(np.float32))
        dx = torch.zeros_like(img)
        dy = torch.zeros_like(img)
        dx[..., :, :-1] = img[..., :, 1:] - img[..., :, :-1]
        dy[..., :-1, :] = img[..., 1:, :] - img[..., :-1, :]
        frames.append(pack.round_half(torch.cat([img, dx, dy, torch.rand(1, 7, H, W)], 1).numpy()[0]))
    pack.write(str(tmp_path / "t.xz"), {f"{W}x{H}": np.stack(frames)}, {"kind": "train"})
    ranges = tmp_path / "r.json"
    ranges.write_text(json.dumps({"ranges": qat.ranges_from_int8(leaky_int8)}))

    def run(out, *extra):
        qat.main(["train", "--train", str(tmp_path / "t.xz"), "--model", FP32, "--ranges", str(ranges),
                  "--out", str(out), "--device", "cpu", "--steps", "6", "--batch", "1", "--patch", "32",
                  "--eval-batches", "1", "--log-every", "1", "--warmup", "2", "--lr", "1e-4",
                  "--threads", "1", *extra])

    run(tmp_path / "a")
    run(tmp_path / "b", "--stop-after", "3")
    run(tmp_path / "b", "--export", str(tmp_path / "exp"))
    a = torch.load(tmp_path / "a" / "last.pt", weights_only=False)
    b = torch.load(tmp_path / "b" / "last.pt", weights_only=False)
    assert a["step"] == b["step"] == 6
    for k, v in a["net"].items():
        assert torch.equal(v, b["net"][k]), k
    la = [json.loads(x) for x in open(tmp_path / "a" / "log.jsonl")]
    lb = [json.loads(x) for x in open(tmp_path / "b" / "log.jsonl")]
    losses = lambda rows: [r["loss"] for r in rows if r["kind"] == "train"]  # noqa: E731
    assert losses(la) == losses(lb) and len(losses(la)) == 6
    assert all(np.isfinite(losses(la)))
    from gdrecon_py.train_gradnet import merge_parts
    assert merge_parts(str(tmp_path / "exp" / "last"))["step"] == 6


def test_learned_scale_gets_lsq_gradient_and_the_same_forward():
    """With the scale learned the output is `fake_act`'s bit for bit; x's gradient is the
    straight-through one, the scale's LSQ's (computed here in numpy): round(x/s) - x/s inside the
    range, qmin - z below it, qmax - z above."""
    scale, zp = 0.0123, 37
    x = np.concatenate([np.linspace(-1, 3.5, 4001), (np.arange(-40, 220) + 0.5) * scale]).astype(np.float32)
    c = np.random.default_rng(0).standard_normal(x.size).astype(np.float32)
    s = torch.tensor(scale, dtype=torch.float32, requires_grad=True)
    xt = torch.from_numpy(x).requires_grad_(True)
    y = qat.fake_act(xt, s, torch.tensor(zp, dtype=torch.int32))
    fixed = qat.fake_act(torch.from_numpy(x), torch.tensor(scale), torch.tensor(zp, dtype=torch.int32))
    assert torch.equal(y.detach(), fixed)
    (y * torch.from_numpy(c)).sum().backward()
    r = x / np.float32(scale)
    q = np.round(r) + zp
    inside = (q >= 0) & (q <= 255)
    ds = np.where(inside, q - zp - r, np.where(q < 0, 0 - zp, 255 - zp))
    assert np.array_equal(xt.grad.numpy(), c * inside)
    assert inside.any() and (~inside).any()
    want = float((c.astype(np.float64) * ds).sum())
    assert abs(float(s.grad) - want) <= 1e-4 * np.abs(c * ds).sum(), (float(s.grad), want)


def test_learned_ranges_start_at_the_graph_and_a_crop_follows_its_shuffle():
    """`learn_ranges`: the simulation starts at the graph's ranges (its output equal to the fixed
    ranges' up to float32 rounding of exp(log s)), every scale gets a gradient, and a crop keeps
    its shuffle input's scale however the scales move."""
    sim = qat.QATGradNet(qat.net_from_int8(INT8), qat.ranges_from_int8(INT8), learn_ranges=True)
    fixed = qat.QATGradNet(qat.net_from_int8(INT8), qat.ranges_from_int8(INT8)).eval()
    want = qat.deployed(qat.ranges_from_int8(INT8))
    got = sim.ranges()
    assert tuple(got) == sim.names == qat.act_names(sim.net.activation)
    for k in sim.names:
        assert abs(got[k][0] - want[k][0]) <= 1e-6 * want[k][0] and got[k][1] == want[k][1], k
    d, g = inputs(4)
    with torch.no_grad():
        assert (sim.eval()(d, g) - fixed(d, g)).abs().max() < 1e-3
    sim.train()
    sim(d, g).mean().backward()
    used = {sim._tie[i] for i in range(len(sim.names))}
    assert all(float(sim.log_scales.grad[i]) != 0 for i in used)
    with torch.no_grad():
        sim.log_scales.add_(0.1 * torch.arange(len(sim.names)))
    moved = sim.ranges()
    for crop, shuffle in qat.SHARED.items():
        assert moved[crop] == moved[shuffle] and moved[crop][0] != got[crop][0]


def test_narrowed_negatives_keep_the_positive_side_with_a_finer_step(leaky_int8):
    """`narrow_negatives`: each pre-LeakyReLU convolution output keeps its positive extent (to a
    step), its negative extent becomes the fraction asked (to a step) and its step is finer;
    every other range is untouched; 1 is the identity and a fraction outside (0, 1] is refused."""
    r = qat.ranges_from_int8(leaky_int8)
    n = qat.narrow_negatives(r, 0.5)
    assert set(qat.PRE_LRELU) <= set(qat.ACT_NAMES) and set(qat.PRE_LRELU.values()) <= set(qat.ACT_NAMES)
    for k in qat.ACT_NAMES:
        (s, z), (s2, z2) = r[k], n[k]
        if k not in qat.PRE_LRELU:
            assert (s2, z2) == (s, z), k
            continue
        assert s2 < s and 0 <= z2 < z, k
        assert abs(s2 * (255 - z2) - s * (255 - z)) <= s2, k
        assert abs(s2 * z2 - 0.5 * s * z) <= s2, k
    assert qat.narrow_negatives(r, 1.0) == r
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="negative fraction"):
            qat.narrow_negatives(r, bad)


def relu_graph(tmp_path, leaky):
    """The ReLU graph of the LeakyReLU int8 graph `leaky`'s weights, quantised as `qat quantize`
    does (its ranges fixed by overrides to `relu_ranges` of `leaky`'s); returns its path."""
    from gdrecon_py import quantize as qz
    from gdrecon_py.export import export_model
    net = qat.with_activation(qat.net_from_int8(leaky), "relu")
    ranges = qat.relu_ranges(qat.ranges_from_int8(leaky))
    src, out = str(tmp_path / "relu.onnx"), str(tmp_path / "relu_int8.onnx")
    export_model(net, src)
    feeds = [{"data": d.numpy(), "grad": g.numpy()} for d, g in (inputs(s) for s in (7, 8))]
    overrides = {k: [{"scale": np.array(s, np.float32), "zero_point": np.array(z, np.uint8)}]
                 for k, (s, z) in qat.deployed(ranges).items()}
    qz.quantize(src, out, feeds, exclude=qz.DEFAULT_EXCLUDE.split(","), method="percentile", overrides=overrides)
    return out


def test_relu_graph_quantises_each_activation_once_and_is_simulated(tmp_path, leaky_int8):
    """The ReLU graph: ONNX Runtime's quantiser folds every encoder and residual ReLU into its
    convolution's output quantisation (31 tensors, the 41 less the ten pre-LeakyReLU ones, each
    at zero point 0), the graph says it is the ReLU one, and the simulation is its int8 output up
    to ties (as for the LeakyReLU graph). The simulation is of the graph's own weights: its
    int32 biases are rounded at the new input scales, and that alone (a shift under half a bias
    step) moved the output by 0.001 when simulated with the start graph's biases, the half of
    the int8 graph's distance from its own fp32 network: rounding is chaotic through the
    residual blocks (a flip fans out to 9 x 256 sums)."""
    import onnx
    path = relu_graph(tmp_path, leaky_int8)
    m = onnx.load(path)
    assert {p.key: p.value for p in m.metadata_props}["activation"] == "relu"
    assert not any(n.op_type == "LeakyRelu" for n in m.graph.node)
    got = qat.ranges_from_int8(path)
    assert tuple(got) == qat.ACT_NAMES_RELU and len(got) == len(qat.ACT_NAMES) - len(qat.PRE_LRELU)
    assert all(got[k][1] == 0 for k in qat.RELU_OF.values())
    assert qat.net_from_int8(path).activation == "relu"
    d8, d32 = simulation_distances(path)
    assert np.mean(d8) < 0.1 * np.mean(d32), (d8, d32)


def test_relu_ranges_keep_each_positive_side(leaky_int8):
    """`relu_ranges`: a LeakyReLU output's range becomes its positive side at zero point 0 (to a
    step), the convolution output before it is gone, every other range is untouched; the
    simulation off is the ReLU network exactly."""
    r = qat.ranges_from_int8(leaky_int8)
    rr = qat.relu_ranges(r)
    assert tuple(rr) == qat.ACT_NAMES_RELU
    for k in qat.ACT_NAMES_RELU:
        if k in qat.RELU_OF.values():
            s, z = r[k.replace("Relu", "LeakyRelu")]
            assert rr[k][1] == 0 and abs(rr[k][0] * 255 - s * (255 - z)) <= 1e-6 * s * 255, k
        else:
            assert rr[k] == r[k], k
    net = qat.with_activation(qat.net_from_int8(leaky_int8), "relu")
    sim = qat.QATGradNet(net, rr).eval()
    sim.quant = False
    d, g = inputs(4)
    with torch.no_grad():
        assert torch.equal(sim(d, g), net(d, g))
        assert not torch.equal(net(d, g), qat.net_from_int8(leaky_int8)(d, g))


def test_the_shipped_int8_graph_is_the_relu_graph():
    """`onnx/gradnet_int8.onnx` is the ReLU graph since the fortieth session (docs/gradnet.md):
    no LeakyReLU left, each activation quantised once at zero point 0, the teacher the fp32
    LeakyReLU model (`onnx/gradnet.onnx`, whose metadata names no activation)."""
    import onnx
    m = onnx.load(INT8)
    meta = {p.key: p.value for p in m.metadata_props}
    assert meta["activation"] == "relu" and not any(n.op_type == "LeakyRelu" for n in m.graph.node)
    got = qat.ranges_from_int8(INT8)
    assert tuple(got) == qat.ACT_NAMES_RELU and all(got[k][1] == 0 for k in qat.RELU_OF.values())
    assert "activation" not in {p.key for p in onnx.load(FP32).metadata_props}
    assert net_from_onnx(FP32).activation == "leaky_relu"
