"""Tests of the GradNet model, losses, pre/post-processing and ONNX export (gdrecon_py/gradnet.py,
mulaw.py, pipeline.py, export.py, the committed onnx/*.onnx). Small sizes: a few seconds on 2 cores.

    ~/.cache/gdrecon/venv/bin/python -m pytest -q onnx/tests/test_gradnet.py
"""
import json
import math
import os

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from gdrecon_py import ONNX_DIR, REPO  # noqa: E402
from gdrecon_py import export as ex  # noqa: E402
from gdrecon_py import gradnet as gn  # noqa: E402
from gdrecon_py import mulaw as ml  # noqa: E402
from gdrecon_py import pipeline as pl  # noqa: E402
from gdrecon_py.metrics import relmse  # noqa: E402
from gdrecon_py.runtime import session  # noqa: E402

SAMPLE = os.path.join(REPO, "examples", "data", "sample.exr")
VAL = os.path.expanduser("~/.cache/gdrecon/data/val")
SIZES = [(8, 8), (16, 24), (40, 16)]   # (H, W): multiples of 8, square and not
TOL = 1e-4

torch.set_num_threads(2)


# ---------------------------------------------------------------- mu-law

def test_mulaw_roundtrip():
    x = np.concatenate([np.linspace(0, 1, 101), np.logspace(-6, 4, 50)]).astype(np.float64)
    assert np.allclose(ml.mulaw_inv(ml.mulaw(x)), x, rtol=1e-9, atol=1e-12)
    t = torch.tensor(x)
    assert torch.allclose(ml.mulaw_inv(ml.mulaw(t)), t, rtol=1e-9, atol=1e-12)
    assert abs(float(ml.mulaw(1.0)) - 1.0) < 1e-12 and float(ml.mulaw(0.0)) == 0.0
    s = np.array([-3.0, -0.5, 0.0, 0.25, 2.0])
    assert np.allclose(ml.mulaw_signed(s), np.sign(s) * np.log1p(16 * np.abs(s)) / np.log(17))
    # the pipeline's float32 numpy forms agree with the torch ones
    assert np.allclose(ml.C_inv(ml.C(x.astype(np.float32))), x.astype(np.float32), rtol=1e-5, atol=1e-6)
    assert np.allclose(ml.S(s.astype(np.float32)), ml.mulaw_signed(torch.tensor(s)).numpy(), atol=1e-6)


# ---------------------------------------------------------------- losses by hand

def _C(v):
    return math.log(1 + 16 * v) / math.log(17)


def _S(v):
    return math.copysign(_C(abs(v)), v) if v != 0 else 0.0


def _Cinv(v):
    return (17 ** v - 1) / 16


Y = [[0.2, 0.5, 0.1], [0.4, 0.3, 0.7]]          # 1 x 1 x 2 x 3, compressed output
I = [[0.1, 0.6, 0.0], [0.3, 0.2, 1.5]]          # linear noisy colour
DX = [[0.5, -0.4, 0.0], [-0.1, 0.9, 0.0]]
DY = [[0.2, -0.3, 0.7], [0.0, 0.0, 0.0]]


def _t(a):
    return torch.tensor(a, dtype=torch.float64)[None, None]


def test_loss_data_by_hand():
    want = sum(abs(Y[r][c] - _C(I[r][c])) for r in range(2) for c in range(3)) / 6
    assert abs(gn.loss_data(_t(Y), _t(I)).item() - want) < 1e-12


def test_loss_grad_by_hand():
    lx = [abs(_S(_Cinv(Y[r][c + 1]) - _Cinv(Y[r][c])) - _S(DX[r][c])) for r in range(2) for c in range(2)]
    ly = [abs(_S(_Cinv(Y[1][c]) - _Cinv(Y[0][c])) - _S(DY[0][c])) for c in range(3)]
    want = sum(lx) / len(lx) + sum(ly) / len(ly)
    assert abs(gn.loss_grad(_t(Y), _t(DX), _t(DY)).item() - want) < 1e-12


def test_loss_first_order_by_hand():
    rng = np.random.default_rng(3)
    Fe = rng.random((7, 2, 3))
    G = rng.standard_normal((7, 2, 3))

    def term(p, q):
        dF = Fe[:, q[0], q[1]] - Fe[:, p[0], p[1]]
        w = math.exp(-9 * (I[q[0]][q[1]] - I[p[0]][p[1]]) ** 2)
        dy = Y[q[0]][q[1]] - Y[p[0]][p[1]]
        fwd = w * abs(dy - float(G[:, p[0], p[1]] @ dF))
        bwd = w * abs(-dy - float(G[:, q[0], q[1]] @ (-dF)))
        return fwd, bwd

    h = [term((r, c), (r, c + 1)) for r in range(2) for c in range(2)]
    v = [term((0, c), (1, c)) for c in range(3)]
    want = (sum(a for a, _ in h) + sum(b for _, b in h)) / len(h) + \
           (sum(a for a, _ in v) + sum(b for _, b in v)) / len(v)
    got = gn.loss_first_order(_t(Y), torch.tensor(Fe)[None], torch.tensor(G)[None], _t(I)).item()
    assert abs(got - want) < 1e-12


def test_first_order_zero_for_linear_model():
    # y exactly linear in the features with slope G -> loss 0
    rng = np.random.default_rng(0)
    Fe = torch.tensor(rng.random((1, 7, 5, 6)))
    g = torch.tensor(rng.standard_normal(7)).view(1, 7, 1, 1)
    y = (Fe * g).sum(1, keepdim=True)
    G = g.expand(1, 7, 5, 6)
    assert gn.loss_first_order(y, Fe, G, torch.rand(1, 1, 5, 6, dtype=torch.float64)).item() < 1e-12


# ---------------------------------------------------------------- architecture

def test_architecture():
    net = gn.GradNet()
    assert 6.28e6 < gn.n_params(net) < 6.30e6
    y = net(torch.rand(2, 8, 16, 24), torch.rand(2, 2, 16, 24))
    assert y.shape == (2, 1, 16, 24) and (y >= 0).all()
    nf = gn.GradNetNoFeat()
    assert nf(torch.rand(3, 1, 8, 8), torch.rand(3, 2, 8, 8)).shape == (3, 1, 8, 8)
    assert gn.GBranch()(torch.rand(1, 8, 8, 8), torch.rand(1, 2, 8, 8)).shape == (1, 7, 8, 8)


def test_make_inputs_channel_batch():
    c = torch.rand(2, 3, 8, 8)
    dx, dy, f = torch.randn(2, 3, 8, 8), torch.randn(2, 3, 8, 8), torch.rand(2, 7, 8, 8)
    d, g = gn.make_inputs(c, dx, dy, f)
    assert d.shape == (6, 8, 8, 8) and g.shape == (6, 2, 8, 8)
    assert torch.allclose(d[4, 0], ml.mulaw(c[1, 1])) and torch.equal(d[4, 1:], f[1])
    assert torch.allclose(g[5, 1], ml.mulaw_signed(dy[1, 2]))


# ---------------------------------------------------------------- pre/post-processing

def test_padding_consistent_with_reflected_colour():
    rng = np.random.default_rng(1)
    H, W = 13, 10
    img = rng.random((H, W, 3)).astype(np.float32)
    dx = np.zeros_like(img); dx[:, :-1] = img[:, 1:] - img[:, :-1]
    dy = np.zeros_like(img); dy[:-1] = img[1:] - img[:-1]
    ph, pw = 3, 6
    P = pl.pad_reflect(img, ph, pw)
    pdx, pdy = pl.pad_grad(dx, ph, pw, 1), pl.pad_grad(dy, ph, pw, 0)
    assert pdx.shape == P.shape == pdy.shape == (16, 16, 3)
    assert np.allclose(pdx[:, :-1], P[:, 1:] - P[:, :-1], atol=1e-6)
    assert np.allclose(pdy[:-1], P[1:] - P[:-1], atol=1e-6)
    assert np.array_equal(pl.pad_grad(dx, 0, 0, 1), dx)


def test_feature_normalisation():
    a = np.full((2, 2, 3), 0.5, np.float32)
    n = np.array([[[-1, 0, 1]] * 2] * 2, np.float32)
    d = np.array([[[2.0], [4.0]], [[np.float32(3e5)], [2.0]]], np.float32)
    f = pl.normalize_features(a, n, d)
    assert f.shape == (2, 2, 7)
    assert np.allclose(f[0, 0, 3:6], [0, 0.5, 1])
    assert np.isclose(f[..., 6].max(), 1) and np.isclose(f[..., 6].min(), 0)
    assert np.isclose(f[0, 1, 6], 2.0 / (1e5 - 2))   # clamped at 1e5 before min-max
    a2 = a.copy(); a2[0, 0] = [551.0, -0.5, 0.3]
    assert np.allclose(pl.normalize_features(a2, n, d)[0, 0, :3], [1.0, 0.0, 0.3])   # inference: [0, 1]
    assert np.allclose(pl.normalize_features(a2, n, d, pl.TRAIN_ALBEDO_RANGE)[0, 0, :3], [551.0, -0.5, 0.3])


def test_bias_correction():
    rng = np.random.default_rng(2)
    col = rng.random((20, 30, 3)).astype(np.float32)
    assert np.allclose(pl.bias_correct(col, col), col, rtol=1e-6)
    out = pl.bias_correct(0.5 * col, col)      # a global scale is undone exactly
    assert np.allclose(out, col, rtol=1e-5)
    k = pl.gaussian_kernel()
    assert len(k) == 91 and abs(k.sum() - 1) < 1e-12
    # zero-padded borders: a constant image blurs to less than itself at the edges
    b = pl.blur2d(np.ones((10, 10)))
    assert b[0, 0] < b[5, 5] < 1.0


# ---------------------------------------------------------------- ONNX parity

def _parity(net, path, sizes, seed=0):
    sess = session(path)
    rng = np.random.default_rng(seed)
    worst = 0.0
    for (h, w) in sizes:
        d = rng.random((3, net.data_ch, h, w), dtype=np.float32)
        g = rng.random((3, 2, h, w), dtype=np.float32) - 0.5
        with torch.no_grad():
            ref = net(torch.from_numpy(d), torch.from_numpy(g)).numpy()
        got = sess.run(["output"], {"data": d, "grad": g})[0]
        assert got.shape == (3, 1, h, w)
        worst = max(worst, float(np.abs(ref - got).max()))
    return worst


@pytest.mark.parametrize("data_ch", [8, 1])
def test_export_untrained_parity(tmp_path, data_ch):
    torch.manual_seed(0)
    net = gn.GradNet(data_ch=data_ch).eval()
    path = str(tmp_path / "m.onnx")
    m = ex.export_model(net, path)
    assert m.ir_version <= 10 and m.opset_import[0].version == 17
    assert [i.name for i in m.graph.input] == ["data", "grad"]
    assert [o.name for o in m.graph.output] == ["output"]
    assert _parity(net, path, SIZES) < TOL
    # weights round-trip through the file's initializers
    back = ex.net_from_onnx(path)
    for k, v in net.state_dict().items():
        assert torch.equal(v, back.state_dict()[k])


# ---------------------------------------------------------------- decoder rewrite (export.py --deconv)

ODD_EVEN = [(5, 7), (6, 8), (1, 1), (9, 4)]   # (H, W) of the transposed conv's input


@pytest.mark.parametrize("relu", [False, True])
def test_subpixel_equals_convtranspose(relu):
    torch.manual_seed(3)
    for cin, cout in [(16, 8), (3, 5)]:
        ct = torch.nn.ConvTranspose2d(cin, cout, 4, stride=2, padding=1)
        sub = ex.SubpixelConvTranspose2d(ct, relu=relu)
        for (h, w) in ODD_EVEN:
            x = torch.randn(2, cin, h, w)
            with torch.no_grad():
                ref = ct(x)
                ref = torch.relu(ref) if relu else ref
                got = sub(x)
            assert got.shape == ref.shape == (2, cout, 2 * h, 2 * w)
            assert float((got - ref).abs().max()) < 1e-5
        w_back, b_back = ex.SubpixelConvTranspose2d.deconv_params(sub.conv.weight.detach(), sub.conv.bias.detach())
        assert torch.equal(w_back, ct.weight.detach()) and torch.equal(b_back, ct.bias.detach())


def test_phase_and_polyphase_equal_convtranspose_then_conv():
    torch.manual_seed(4)
    cin, cout = 12, 8
    ct = torch.nn.ConvTranspose2d(cin, cout, 4, stride=2, padding=1)
    out = torch.nn.Conv2d(cout, 3, 3, padding=1)
    ph, poly = ex.PhaseConvTranspose2d(ct, relu=True), ex.PolyphaseConv2d(out)
    for (h, w) in ODD_EVEN:
        x = torch.randn(2, cin, h, w)
        with torch.no_grad():
            u = torch.relu(ct(x))
            p = ph(x)
            # phase (a, b) of channel c = u[c, a::2, b::2]
            ref_p = torch.cat([u[:, :, a::2, b::2] for a in range(2) for b in range(2)], 1)
            assert p.shape == ref_p.shape and float((p - ref_p).abs().max()) < 1e-5
            got, ref = poly(p), out(u)
        assert got.shape == ref.shape == (2, 3, 2 * h, 2 * w)
        assert float((got - ref).abs().max()) < 1e-5
    ks = {(a, b): getattr(ph, f"w{a}{b}").detach() for a in range(2) for b in range(2)}
    w_back, b_back = ex.PhaseConvTranspose2d.deconv_params(ks, ph.bias.detach())
    assert torch.equal(w_back, ct.weight.detach()) and torch.equal(b_back, ct.bias.detach())
    w_back, b_back = ex.PolyphaseConv2d.conv_params(poly.conv.weight.detach(), poly.conv.bias.detach())
    assert torch.equal(w_back, out.weight.detach()) and torch.equal(b_back, out.bias.detach())


@pytest.mark.parametrize("form", ex.DECONV_FORMS)
def test_swapped_net_and_export(tmp_path, form):
    torch.manual_seed(5)
    net = gn.GradNet().eval()
    sw = ex.swap_deconv(net, form)
    assert isinstance(net.u1[0], torch.nn.ConvTranspose2d)        # the original is untouched
    n_ct = sum(isinstance(m, torch.nn.ConvTranspose2d) for m in sw.modules())
    assert n_ct == (3 if form == "convtranspose" else 0)
    rng = np.random.default_rng(6)
    d = rng.random((1, 8, 40, 56), dtype=np.float32)
    g = rng.random((1, 2, 40, 56), dtype=np.float32) - 0.5
    with torch.no_grad():
        ref = net(torch.from_numpy(d), torch.from_numpy(g)).numpy()
        assert float(np.abs(sw(torch.from_numpy(d), torch.from_numpy(g)).numpy() - ref).max()) < 1e-5
    path = str(tmp_path / f"{form}.onnx")
    m = ex.export_model(net, path, deconv=form)
    assert {p.key: p.value for p in m.metadata_props}["deconv"] == form
    assert m.ir_version == 8 and m.opset_import[0].version == 17
    ops = {n.op_type for n in m.graph.node}
    assert ("ConvTranspose" in ops) == (form == "convtranspose")
    got = session(path).run(["output"], {"data": d, "grad": g})[0]
    assert got.shape == (1, 1, 40, 56) and float(np.abs(got - ref).max()) < TOL
    back = ex.net_from_onnx(path)
    for k, v in net.state_dict().items():
        assert torch.equal(v, back.state_dict()[k])


SHIPPED = [f for f in ("gradnet.onnx", "gradnet_nofeat.onnx") if os.path.exists(os.path.join(ONNX_DIR, f))]


def test_shipped_models_present():
    assert "gradnet.onnx" in SHIPPED, "onnx/gradnet.onnx (trained) must be committed"


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_model_hash_and_parity(name):
    path = os.path.join(ONNX_DIR, name)
    digest = ex.sha256_file(path)
    with open(path + ".sha256") as f:
        assert f.read().split()[0] == digest
    with open(os.path.join(ONNX_DIR, "models.json")) as f:
        man = json.load(f)["models"][name]
    assert man["sha256"] == digest and man["epochs_trained"] >= 1
    m = onnx.load(path)
    assert m.ir_version <= 10 and os.path.getsize(path) < 32e6
    assert {p.key: p.value for p in m.metadata_props}.get("deconv", "convtranspose") == \
        man.get("deconv", "convtranspose")
    net = ex.net_from_onnx(path)
    assert _parity(net, path, [(8, 16), (24, 24)], seed=1) < TOL


def _frame_parity(frame, name):
    path = os.path.join(ONNX_DIR, name)
    net = ex.net_from_onnx(path)
    use_feat = net.data_ch == 8
    a = pl.reconstruct(frame, pl.torch_runner(net), use_features=use_feat, correct_bias=False)
    b = pl.reconstruct(frame, pl.ort_runner(path), use_features=use_feat, correct_bias=False)
    # compare in the network's (compressed) domain, where the 1e-4 bound applies
    err = float(np.abs(ml.C(a) - ml.C(b)).max())
    assert np.isfinite(a).all() and err < TOL, err
    return a


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_model_on_sample_frame(name):
    if not os.path.exists(SAMPLE):
        pytest.skip("examples/data/sample.exr missing")
    fr = pl.read_frame(SAMPLE)
    H, W = fr["color"].shape[:2]
    out = _frame_parity(fr, name)
    assert out.shape == (H, W, 3)
    if "reference" in fr and name == "gradnet.onnx":
        # a trained model must improve on the noisy input of the bundled sample
        full = pl.reconstruct(fr, pl.ort_runner(os.path.join(ONNX_DIR, name)))
        assert relmse(full, fr["reference"]) < relmse(fr["color"], fr["reference"])


def test_validation_frame_parity():
    f = os.path.join(VAL, "textures_4spp.exr")
    if not os.path.exists(f):
        pytest.skip(f"validation set absent ({VAL})")
    if "gradnet.onnx" not in SHIPPED:
        pytest.skip("no shipped model")
    _frame_parity(pl.read_frame(f), "gradnet.onnx")


def test_emitters_are_quiet_bright_pixels_only():
    """Step 6b's mask: a bright, low-noise pixel (an emitter) is in it; a bright noisy one (a
    firefly) and a dim one are not; without a variance layer brightness alone decides; limit 0
    is the release (no pixel)."""
    color = np.array([[[5.0, 5.0, 5.0], [5.0, 0.1, 0.1], [0.5, 0.5, 0.5]]], np.float32)
    variance = np.array([[[0.01] * 3, [4.0, 1e-4, 1e-4], [0.0] * 3]], np.float32)
    assert pl.emitters(color, variance).tolist() == [[True, False, False]]
    assert pl.emitters(color, None).tolist() == [[True, True, False]]
    assert not pl.emitters(color, variance, limit=0).any()


def test_bias_limit_leaves_unkept_bright_pixels_out_of_the_gain():
    """Step 7's bias limit: a bright pixel the network could not output (the output is 1 where
    the input is 1000) raises the gain around it unless it is left out; the emitters step 6b
    keeps enter both sums, so they stay in; limit 0 is the release."""
    color = np.ones((40, 40, 3), np.float32)
    color[20, 20] = 1000.0
    out = np.ones_like(color)
    kept = np.zeros((40, 40), bool)
    skip = pl.beyond(color, kept=kept)
    assert skip.sum() == 1 and skip[20, 20]
    assert np.allclose(pl.bias_correct(out, color, skip), 1.0)
    assert pl.bias_correct(out, color)[19, 20, 0] > 2.0         # the release: the gain spreads it
    kept[20, 20] = True
    assert not pl.beyond(color, kept=kept).any()
    assert pl.beyond(color, limit=0) is None


# ---------------------------------------------------------------- int8 (gdrecon_py/quantize.py)

INT8 = os.path.join(ONNX_DIR, "gradnet_int8.onnx")


def test_int8_model_provenance():
    from gdrecon_py import quantize as qz
    if not os.path.exists(INT8):
        pytest.skip("onnx/gradnet_int8.onnx absent")
    digest = ex.sha256_file(INT8)
    with open(INT8 + ".sha256") as f:
        assert f.read().split()[0] == digest
    with open(os.path.join(ONNX_DIR, "models.json")) as f:
        man = json.load(f)["models"]
    entry = man["gradnet_int8.onnx"]
    assert entry["sha256"] == digest and entry["precision"] == "int8"
    # quantised from the shipped fp32 model, calibrated on the training split only
    assert entry["source"]["sha256"] == man["gradnet.onnx"]["sha256"]
    assert all(not b.startswith(("cornell", "metals", "glass", "textures", "indirect", "sunsky",
                                 "studio", "dusk")) for b in entry["calibration"]["bundles"])
    m = onnx.load(INT8)
    props = {p.key: p.value for p in m.metadata_props}
    assert props["precision"] == "int8" and props["source_sha256"] == man["gradnet.onnx"]["sha256"]
    assert props["data_channels"] == "8" and m.ir_version <= 10
    ops = {n.op_type for n in m.graph.node}
    assert {"QuantizeLinear", "DequantizeLinear"} <= ops
    # the layers kept in fp32 read float weights (no DequantizeLinear in front of them)
    dq_out = {n.output[0] for n in m.graph.node if n.op_type == "DequantizeLinear"}
    for node in m.graph.node:
        if node.name in entry["quantization"]["nodes_in_fp32"]:
            assert node.input[1] not in dq_out, node.name
    with pytest.raises(SystemExit):
        qz.calibration_files(VAL, 4)


def test_int8_output_layer_outside_the_graph(tmp_path):
    """A QDQ graph whose output convolution was cut off (`output_layer.split`) and applied by
    `output_layer.apply` gives the uncut graph's output (only the order of fp32 sums differs);
    each sub-pixel crop carries its shuffle's quantisation; a kernel that is not the phase form of
    a 3 x 3 one is refused. An untrained model, quantised on random inputs."""
    from gdrecon_py import output_layer as ol
    from gdrecon_py import quantize as qz
    torch.manual_seed(1)
    net = gn.GradNet().eval()
    src = str(tmp_path / "m.onnx")
    ex.export_model(net, src)
    rng = np.random.default_rng(2)
    feeds = [{"data": rng.random((1, 8, 32, 48), dtype=np.float32),
              "grad": rng.random((1, 2, 32, 48), dtype=np.float32) - 0.5} for _ in range(3)]
    exclude = qz.DEFAULT_EXCLUDE.split(",")
    cut, whole = str(tmp_path / "cut.onnx"), str(tmp_path / "whole.onnx")
    m = qz.quantize(src, cut, feeds, exclude=exclude)
    qz.quantize(src, whole, feeds, exclude=exclude, split_output=False)
    assert [o.name for o in m.graph.output] == [ol.OUTPUT]
    assert ol.CONV not in {n.name for n in m.graph.node}
    qparams = {n.input[0]: n.input[1:] for n in m.graph.node if n.op_type == "QuantizeLinear"}
    pairs = qz.shuffle_pairs(onnx.load(whole))
    assert len(pairs) == 2 and all(qparams[crop] == qparams[src] for crop, src in pairs)
    d = rng.random((2, 8, 40, 56), dtype=np.float32)
    g = rng.random((2, 2, 40, 56), dtype=np.float32) - 0.5
    a, b = pl.ort_runner(cut)(d, g), pl.ort_runner(whole)(d, g)
    assert a.shape == b.shape == (2, 1, 40, 56) and np.abs(a).max() > 0
    assert float(np.abs(a - b).max()) < 1e-6
    poly = ol.phase_form(net.out.weight.detach().numpy()[0])
    assert np.array_equal(ol.phase_form(ol._full_kernel(poly)), poly)
    poly[1, 0, 0, 0] += 1.0            # a tap the 3 x 3 kernel cannot give
    with pytest.raises(ValueError):
        ol._full_kernel(poly)


def test_nhwc_rewrite_moves_the_same_values(tmp_path):
    """`nhwc.rewrite` on a quantised graph (an untrained model, quantised on random inputs): its
    shuffles alone are exact (the same uint8 phases), the merged phases are at most one
    quantisation step from the canonical graph's, and the output layer reads both layouts to
    the same image within those steps; a graph already rewritten, or not split, is refused."""
    from gdrecon_py import nhwc, runtime
    from gdrecon_py import output_layer as ol
    from gdrecon_py import quantize as qz
    torch.manual_seed(3)
    net = gn.GradNet(activation="relu").eval()
    src = str(tmp_path / "m.onnx")
    ex.export_model(net, src)
    rng = np.random.default_rng(4)
    feeds = [{"data": rng.random((1, 8, 32, 48), dtype=np.float32),
              "grad": rng.random((1, 2, 32, 48), dtype=np.float32) - 0.5} for _ in range(3)]
    cut = str(tmp_path / "cut.onnx")
    m = qz.quantize(src, cut, feeds, exclude=qz.DEFAULT_EXCLUDE.split(","))
    shuffled = onnx.load(cut)
    assert nhwc.shuffle(shuffled) == 2
    assert "DepthToSpace" not in {n.op_type for n in shuffled.graph.node}
    onnx.save(shuffled, str(tmp_path / "shuffled.onnx"))
    deployed = str(tmp_path / "nhwc.onnx")
    onnx.save(nhwc.rewrite(m), deployed)
    d = rng.random((1, 8, 40, 56), dtype=np.float32)
    g = rng.random((1, 2, 40, 56), dtype=np.float32) - 0.5
    feed = {"data": d, "grad": g}
    run = {k: runtime.session(str(tmp_path / f"{k}.onnx")).run([ol.OUTPUT], feed)[0]
           for k in ("cut", "shuffled", "nhwc")}
    assert run["nhwc"].shape == (1, 21, 29, 128)
    assert np.array_equal(run["shuffled"], run["cut"]) and run["cut"].max() > 0
    # rounded once instead of twice (to the phase's scale s_p, then to the concatenation's s_c
    # >= s_p): one step at most, except where the canonical graph clipped a phase at its own
    # ceiling, 255 s_p, below the concatenation's (calibration ranges each tensor apart)
    scale = {i.name: float(onnx.numpy_helper.to_array(i)) for i in m.graph.initializer
             if i.name.startswith("/u3/") and i.name.endswith("_scale")}
    s_c = scale.pop("/u3/Concat_output_0_scale")
    assert len(scale) == 4 and max(scale.values()) <= s_c
    new = ol.canonical(run["nhwc"], ol.NHWC_PADDED).astype(int)
    old = run["cut"].astype(int)
    clipped = (old >= np.floor(255 * min(scale.values()) / s_c) - 1) & (new > old)
    assert ((np.abs(new - old) <= 1) | clipped).all() and (new != old).mean() < 0.25
    a, b = pl.ort_runner(cut)(d, g), pl.ort_runner(deployed)(d, g)
    assert a.shape == b.shape == (1, 1, 40, 56)
    layer = ol.read({p.key: p.value for p in m.metadata_props})
    bound = float(layer["scale"]) * float(np.abs(layer["weight"]).sum())
    assert float(np.abs(a - b).max()) <= bound
    with pytest.raises(ValueError, match="already"):
        nhwc.rewrite(onnx.load(deployed))
    with pytest.raises(ValueError, match="not an int8 graph"):
        nhwc.rewrite(onnx.load(src))


def test_deployed_int8_graph_is_the_rewrite_of_the_int8_graph():
    """`onnx/gradnet_int8_nhwc.onnx` (the graph the library embeds) is, byte for byte,
    `nhwc.rewrite` of `onnx/gradnet_int8.onnx`, and models.json says so."""
    from gdrecon_py import nhwc
    deployed = os.path.join(ONNX_DIR, "gradnet_int8_nhwc.onnx")
    if not os.path.exists(INT8) or not os.path.exists(deployed):
        pytest.skip("int8 graphs absent")
    digest = ex.sha256_file(deployed)
    with open(deployed + ".sha256") as f:
        assert f.read().split()[0] == digest
    with open(os.path.join(ONNX_DIR, "models.json")) as f:
        entry = json.load(f)["models"]["gradnet_int8_nhwc.onnx"]
    assert entry["sha256"] == digest and entry["source"]["sha256"] == ex.sha256_file(INT8)
    with open(deployed, "rb") as f:
        assert nhwc.rewrite(onnx.load(INT8)).SerializeToString() == f.read()
    # its phases against the int8 graph's (measured: 0.56 % one step apart, the rest equal)
    _, worst, moved = nhwc.check(INT8, deployed)
    assert worst <= 1 and moved < 0.01


def test_int8_close_to_fp32_on_sample_frame():
    if not os.path.exists(INT8) or not os.path.exists(SAMPLE):
        pytest.skip("int8 model or sample frame absent")
    fr = pl.read_frame(SAMPLE)
    a = pl.reconstruct(fr, pl.ort_runner(os.path.join(ONNX_DIR, "gradnet.onnx")))
    b = pl.reconstruct(fr, pl.ort_runner(INT8))
    assert np.isfinite(b).all()
    # measured (the quantisation-aware graph, twenty-fourth session): against the reference
    # 7.33e-4 vs fp32 6.37e-4 (+15 %; the post-training graph before it: +7.9 %). Its cost is
    # mixed per frame: lower on both splits' geometric means and worst frames, higher on
    # cornell-like frames such as this one (docs/gradnet.md, "Reduced precision")
    assert relmse(b, a) < 1e-3
    if "reference" in fr:
        ref = fr["reference"]
        assert relmse(b, ref) < 1.2 * relmse(a, ref)
