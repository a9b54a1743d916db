"""Export trained GradNet weights to ONNX (network only: mu-law, padding and the bias correction
are the caller's job, see gdrecon_py/pipeline.py and onnx/README.md).

    source onnx/env.sh
    $GDRECON_PYTHON -m gdrecon_py.export --ckpt $HOME/.cache/gdrecon/train_runs/full/last.pt \
        --out onnx/gradnet.onnx
    $GDRECON_PYTHON -m gdrecon_py.export --ckpt $HOME/.cache/gdrecon/train_runs/nofeat/last.pt \
        --out onnx/gradnet_nofeat.onnx

Writes <out>, <out>.sha256 (`sha256sum` format) and updates onnx/models.json (one entry per
model: file, sha256, bytes, variant, inputs/outputs, opset, IR version, decoder form
(`deconv`), torch/ORT parity, checkpoint provenance).
The graph: inputs `data` (N x 8 x H x W, or N x 1 for the no-feature model) and `grad`
(N x 2 x H x W), output `output` (N x 1 x H x W); N, H, W dynamic (H, W multiples of 8).
torch.onnx.export(dynamo=False, opset 17) writes IR version 8, which ONNX Runtime 1.31 accepts
(it rejects IR 14); the IR version is checked and pinned to <= 10 here.

Decoder rewrite (`--deconv`, export only; training code and checkpoints are unchanged). The three
ConvTranspose2d(k=4, stride=2, pad=1) layers are slow in ONNX Runtime's CPU EP (124-220 GFLOP/s
against ~350 for its NCHWc 3x3 convs). Each is replaced by the same computation made of ordinary
convolutions; the published weights are only rearranged (copied, never recomputed), and
`net_from_onnx` maps them back exactly. Per axis, output 2m is x[m-1] w[3] + x[m] w[1] and output
2m+1 is x[m] w[2] + x[m+1] w[0] (w: the transposed-conv kernel, Cin x Cout x 4 x 4, not flipped).
  subpixel-poly  (default) u1, u2 as `subpixel`; u3 as its four output phases (four 2x2 convs
                 with asymmetric pads, no crop) and the output 3x3 conv applied to the phases (one
                 3x3 conv 4*32 -> 4 channels at half resolution, then DepthToSpace to 1 channel),
                 so the largest tensor is never interleaved.
  subpixel       every layer: one 2x2 conv (pads 1, 4*Cout channels, the layer's ReLU fused
                 before the shuffle), DepthToSpace (CRD) and a 1-pixel crop (one Slice).
  convtranspose  the original graph.
Timings (1 x 8 x 720 x 1280, ORT 1.31, 2 threads): docs/gradnet.md; gdrecon_py/bench_deconv.py.
"""
import argparse
import copy
import hashlib
import json
import os

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from . import ONNX_DIR, runtime
from . import gradnet as gn

OPSET = 17
MAX_IR = 10
MANIFEST = os.path.join(ONNX_DIR, "models.json")


def sha256_file(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


# ------------------------------------------------------------------------------------------
# decoder rewrite: ConvTranspose2d(k=4, s=2, p=1) -> ordinary convolutions (export only)

DECONV_FORMS = ("subpixel-poly", "subpixel", "convtranspose")
DEFAULT_DECONV = "subpixel-poly"


def _check_deconv(ct):
    ok = (isinstance(ct, nn.ConvTranspose2d) and tuple(ct.kernel_size) == (4, 4)
          and tuple(ct.stride) == (2, 2) and tuple(ct.padding) == (1, 1)
          and tuple(ct.output_padding) == (0, 0) and tuple(ct.dilation) == (1, 1) and ct.groups == 1)
    if not ok:
        raise ValueError(f"only ConvTranspose2d(k=4, stride=2, pad=1) is rewritten, got {ct}")


def _tap(a, t):
    """Index into the 4-tap transposed kernel of tap t (0, 1) of output parity a, along one axis:
    parity 0 reads x[m-1], x[m] with w[3], w[1]; parity 1 reads x[m], x[m+1] with w[2], w[0]."""
    return 3 - a - 2 * t


def _phase_kernel(w, a, b):
    """Cout x Cin x 2 x 2 conv kernel of output phase (a, b) of a Cin x Cout x 4 x 4 kernel."""
    k = w.new_empty(w.shape[1], w.shape[0], 2, 2)
    for t in range(2):
        for s in range(2):
            k[:, :, t, s] = w[:, :, _tap(a, t), _tap(b, s)].t()
    return k


def _phase_kernel_inverse(k, w, a, b):
    """Write the taps of phase kernel `k` (Cout x Cin x 2 x 2) back into `w` (Cin x Cout x 4 x 4)."""
    for t in range(2):
        for s in range(2):
            w[:, :, _tap(a, t), _tap(b, s)] = k[:, :, t, s].t()


class _Crop1(torch.autograd.Function):
    """y[:, :, 1:-1, 1:-1], exported as one Slice (plain indexing exports as two)."""

    @staticmethod
    def forward(ctx, y):
        return y[:, :, 1:-1, 1:-1].clone()

    @staticmethod
    def symbolic(g, y):
        def c(v):
            return g.op("Constant", value_t=torch.tensor(v, dtype=torch.int64))
        return g.op("Slice", y, c([1, 1]), c([-1, -1]), c([2, 3]))


class _PadConv2d(torch.autograd.Function):
    """Stride-1 2x2 conv with asymmetric zero padding (top, left, bottom, right), exported as one
    Conv with `pads` (F.pad + conv2d exports a Pad node that ORT 1.31 leaves unfused)."""

    @staticmethod
    def forward(ctx, x, w, b, pads):
        t, l, bo, r = pads
        return F.conv2d(F.pad(x, (l, r, t, bo)), w, b)

    @staticmethod
    def symbolic(g, x, w, b, pads):
        return g.op("Conv", x, w, b, kernel_shape_i=[2, 2], pads_i=list(pads), strides_i=[1, 1],
                    dilations_i=[1, 1], group_i=1)


class SubpixelConvTranspose2d(nn.Module):
    """ConvTranspose2d(Cin -> Cout, 4, stride 2, pad 1) as conv 2x2 (pads 1, 4 Cout channels) ->
    [ReLU] -> pixel shuffle (DepthToSpace CRD) -> crop 1 pixel on every side. Any H, W.

    On the 1-padded input the 2x2 conv has (H+1) x (W+1) positions; position k (per axis) gives
    output 2k with the parity-0 taps (x[k-1] w[3] + x[k] w[1]) and output 2k-1 with the parity-1
    taps (x[k-1] w[2] + x[k] w[0]). With parity 1 in the first shuffle slot of each pair the
    shuffled axis is out(-1), out(0), ..., out(2H-1), out(2H): one crop of 1 finishes it. Channel
    4 c + 2 i + j = output channel c, slot (i, j) = parity (1 - i, 1 - j). The bias is stored
    4 times (each output element still gets it once)."""

    def __init__(self, ct, relu=False):
        super().__init__()
        _check_deconv(ct)
        w = ct.weight.detach()
        cin, cout = w.shape[:2]
        k = w.new_empty(cout, 2, 2, cin, 2, 2)
        for i in range(2):
            for j in range(2):
                k[:, i, j] = _phase_kernel(w, 1 - i, 1 - j)
        b = ct.bias.detach() if ct.bias is not None else w.new_zeros(cout)
        self.conv = nn.Conv2d(cin, 4 * cout, 2, padding=1)
        with torch.no_grad():
            self.conv.weight.copy_(k.reshape(4 * cout, cin, 2, 2))
            self.conv.bias.copy_(b.repeat_interleave(4))
        self.relu = relu

    def forward(self, x):
        y = self.conv(x)
        if self.relu:
            y = F.relu(y)
        return _Crop1.apply(F.pixel_shuffle(y, 2))

    @staticmethod
    def deconv_params(conv_w, conv_b):
        """(weight Cin x Cout x 4 x 4, bias Cout) of the ConvTranspose2d; exact (taps copied)."""
        cout4, cin = conv_w.shape[:2]
        cout = cout4 // 4
        k = conv_w.reshape(cout, 2, 2, cin, 2, 2)
        w = conv_w.new_empty(cin, cout, 4, 4)
        for i in range(2):
            for j in range(2):
                _phase_kernel_inverse(k[:, i, j], w, 1 - i, 1 - j)
        b = conv_b.reshape(cout, 4)
        if not bool((b == b[:, :1]).all()):
            raise ValueError("subpixel bias: the four copies differ")
        return w, b[:, 0].clone()


class PhaseConvTranspose2d(nn.Module):
    """ConvTranspose2d(Cin -> Cout, 4, stride 2, pad 1) [+ ReLU], returned as its four output
    phases at input resolution, concatenated phase-major: channel (2 a + b) Cout + c at (m, n) is
    output (c, 2m + a, 2n + b). Phase (a, b) is one 2x2 conv with pads (top, left, bottom, right)
    = (1 - a, 1 - b, a, b): exactly H x W outputs, no crop. Consumed by `PolyphaseConv2d`."""

    def __init__(self, ct, relu=False):
        super().__init__()
        _check_deconv(ct)
        w = ct.weight.detach()
        for a in range(2):
            for b in range(2):
                self.register_parameter(f"w{a}{b}", nn.Parameter(_phase_kernel(w, a, b)))
        self.bias = nn.Parameter(ct.bias.detach().clone() if ct.bias is not None
                                 else w.new_zeros(w.shape[1]))
        self.relu = relu

    def forward(self, x):
        ph = []
        for a in range(2):
            for b in range(2):
                y = _PadConv2d.apply(x, getattr(self, f"w{a}{b}"), self.bias, (1 - a, 1 - b, a, b))
                ph.append(F.relu(y) if self.relu else y)
        return torch.cat(ph, 1)

    @staticmethod
    def deconv_params(ks, bias):
        """ks: {(a, b): Cout x Cin x 2 x 2} -> (weight Cin x Cout x 4 x 4, bias); exact."""
        cout, cin = ks[0, 0].shape[:2]
        w = ks[0, 0].new_empty(cin, cout, 4, 4)
        for (a, b), k in ks.items():
            _phase_kernel_inverse(k, w, a, b)
        return w, bias.clone()


class PolyphaseConv2d(nn.Module):
    """Conv2d(C -> Cout, 3, stride 1, pad 1) applied to a full-resolution tensor given as its four
    phases (`PhaseConvTranspose2d` layout, 4 C channels at half resolution): one 3x3 conv
    4 C -> 4 Cout at half resolution (output channel 4 o + 2 a + b = phase (a, b) of channel o),
    then DepthToSpace (CRD). Full-resolution row 2m + a + r - 1 (tap r) is phase
    p = (a + r - 1) mod 2, half-resolution row m + (a + r - 1 - p) / 2; 27 of the 36 taps of each
    (output phase, input phase) pair are zero, and the half-resolution zero padding is exactly the
    full-resolution one."""

    def __init__(self, conv):
        super().__init__()
        if not (isinstance(conv, nn.Conv2d) and tuple(conv.kernel_size) == (3, 3)
                and tuple(conv.stride) == (1, 1) and tuple(conv.padding) == (1, 1)
                and tuple(conv.dilation) == (1, 1) and conv.groups == 1):
            raise ValueError(f"only Conv2d(k=3, stride=1, pad=1) is rewritten, got {conv}")
        w = conv.weight.detach()
        cout, cin = w.shape[:2]
        k = w.new_zeros(cout, 2, 2, 4, cin, 3, 3)
        for (a, b, p, u, v, r, s) in self.taps():
            k[:, a, b, p, :, u, v] = w[:, :, r, s]
        bias = conv.bias.detach() if conv.bias is not None else w.new_zeros(cout)
        self.conv = nn.Conv2d(4 * cin, 4 * cout, 3, padding=1)
        with torch.no_grad():
            self.conv.weight.copy_(k.reshape(4 * cout, 4 * cin, 3, 3))
            self.conv.bias.copy_(bias.repeat_interleave(4))

    @staticmethod
    def taps():
        """(a, b, p, u, v, r, s): output phase (a, b), input phase p = 2 pa + pb, half-resolution
        tap (u, v) <- full-resolution tap (r, s)."""
        out = []
        for a in range(2):
            for b in range(2):
                for r in range(3):
                    for s in range(3):
                        pa, pb = (a + r - 1) % 2, (b + s - 1) % 2
                        u, v = 1 + (a + r - 1 - pa) // 2, 1 + (b + s - 1 - pb) // 2
                        out.append((a, b, 2 * pa + pb, u, v, r, s))
        return out

    def forward(self, x):
        return F.pixel_shuffle(self.conv(x), 2)

    @classmethod
    def conv_params(cls, conv_w, conv_b):
        """(weight Cout x C x 3 x 3, bias Cout) of the original conv; exact, zero taps checked."""
        cout, cin = conv_w.shape[0] // 4, conv_w.shape[1] // 4
        k = conv_w.reshape(cout, 2, 2, 4, cin, 3, 3)
        w = conv_w.new_empty(cout, cin, 3, 3)
        used = torch.zeros(k.shape, dtype=torch.bool)
        for (a, b, p, u, v, r, s) in cls.taps():
            if (a, b) == (0, 0):
                w[:, :, r, s] = k[:, a, b, p, :, u, v]
            elif not torch.equal(k[:, a, b, p, :, u, v], w[:, :, r, s]):
                raise ValueError("polyphase conv: the phases disagree")
            used[:, a, b, p, :, u, v] = True
        if bool((k[~used] != 0).any()):
            raise ValueError("polyphase conv: nonzero tap outside the pattern")
        b = conv_b.reshape(cout, 4)
        if not bool((b == b[:, :1]).all()):
            raise ValueError("polyphase conv bias: the four copies differ")
        return w, b[:, 0].clone()


def swap_deconv(net, form=DEFAULT_DECONV):
    """A copy of GradNet `net` (eval mode) with the decoder in `form` (DECONV_FORMS): the same
    function up to float rounding, the same weights rearranged. `net` is not modified."""
    if form not in DECONV_FORMS:
        raise ValueError(f"deconv form {form!r} not in {DECONV_FORMS}")
    net = copy.deepcopy(net).eval()
    if form == "convtranspose":
        return net
    for name in ("u1", "u2", "u3"):
        seq = getattr(net, name)   # Sequential(ConvTranspose2d, ReLU); the ReLU moves before the shuffle
        if not isinstance(seq[1], nn.ReLU):
            raise ValueError(f"{name}: expected ConvTranspose2d + ReLU")
        if form == "subpixel-poly" and name == "u3":
            # u3 feeds only `out` (GradNet.forward: relu(out(u3(.)))): keep u3 as four phases and
            # run `out` on them; the final ReLU stays after the DepthToSpace
            net.u3 = PhaseConvTranspose2d(seq[0], relu=True)
            net.out = PolyphaseConv2d(net.out)
        else:
            seq[0], seq[1] = SubpixelConvTranspose2d(seq[0], relu=True), nn.Identity()
    return net.eval()


def unswap_state_dict(params, form, data_ch):
    """GradNet state_dict from the parameters (name -> tensor) of a net rewritten by
    `swap_deconv(., form)`, e.g. the initializers of an exported file. Exact (taps copied back)."""
    if form not in DECONV_FORMS:
        raise ValueError(f"deconv form {form!r} not in {DECONV_FORMS}")
    keys = gn.GradNet(data_ch=data_ch).state_dict().keys()
    if form == "convtranspose":
        return {k: params[k] for k in keys}
    sd = {k: params[k] for k in keys if k in params}
    for name in ("u1", "u2", "u3"):
        if form == "subpixel-poly" and name == "u3":
            ks = {(a, b): params[f"u3.w{a}{b}"] for a in range(2) for b in range(2)}
            sd["u3.0.weight"], sd["u3.0.bias"] = PhaseConvTranspose2d.deconv_params(ks, params["u3.bias"])
            sd["out.weight"], sd["out.bias"] = PolyphaseConv2d.conv_params(params["out.conv.weight"],
                                                                           params["out.conv.bias"])
        else:
            sd[f"{name}.0.weight"], sd[f"{name}.0.bias"] = SubpixelConvTranspose2d.deconv_params(
                params[f"{name}.0.conv.weight"], params[f"{name}.0.conv.bias"])
    return {k: sd[k] for k in keys}


def export_model(net, path, metadata=None, deconv=DEFAULT_DECONV):
    """Export GradNet `net` to `path` with its decoder rewritten by `swap_deconv(net, deconv)`
    (`net` itself is not changed); returns the ONNX ModelProto as written."""
    import onnx
    dch = net.data_ch
    net = swap_deconv(net, deconv)
    data = torch.zeros(3, dch, 32, 48)
    grad = torch.zeros(3, 2, 32, 48)
    dyn = {"data": {0: "N", 2: "H", 3: "W"}, "grad": {0: "N", 2: "H", 3: "W"},
           "output": {0: "N", 2: "H", 3: "W"}}
    torch.onnx.export(net, (data, grad), path, input_names=["data", "grad"], output_names=["output"],
                      dynamic_axes=dyn, opset_version=OPSET, dynamo=False, do_constant_folding=True,
                      export_params=True)
    m = onnx.load(path)
    if m.ir_version > MAX_IR:
        m.ir_version = MAX_IR
    meta = {"mu": "16", "data_channels": str(dch), "size_multiple": "8", "deconv": deconv,
            "producer_note": "gdrecon GradNet (Guo et al. 2019); see onnx/README.md"}
    if net.activation != "leaky_relu":
        # only then: the release's graphs keep their metadata (and files) as they were
        meta["activation"] = net.activation
    meta.update(metadata or {})
    del m.metadata_props[:]
    for k, v in meta.items():
        p = m.metadata_props.add()
        p.key, p.value = k, str(v)
    onnx.checker.check_model(m)
    onnx.save(m, path)  # weights inline (a single file, < 2 GB)
    return m


def load_checkpoint(path):
    ck = torch.load(path, map_location="cpu", weights_only=False)
    variant = ck.get("variant", "full")
    net = gn.GradNet() if variant == "full" else gn.GradNetNoFeat()
    net.load_state_dict(ck["net"])
    return net.eval(), ck


def net_from_onnx(path):
    """Rebuild the original torch model (ConvTranspose2d decoder) from the weights stored in an
    exported ONNX file. Initializer names are the state_dict keys of the rewritten net (metadata
    `deconv`; absent = convtranspose); `unswap_state_dict` copies the taps back."""
    import onnx
    from onnx import numpy_helper
    m = onnx.load(path)
    inits = {i.name: torch.from_numpy(np.array(numpy_helper.to_array(i))) for i in m.graph.initializer}
    meta = {p.key: p.value for p in m.metadata_props}
    dch = int(meta.get("data_channels", "8"))
    try:
        sd = unswap_state_dict(inits, meta.get("deconv", "convtranspose"), dch)
    except KeyError as e:
        raise KeyError(f"{path}: initializers missing: {e}") from None
    net = gn.GradNet(data_ch=dch, activation=gn.activation_of(meta))
    missing = [k for k in net.state_dict() if k not in sd]
    if missing:
        raise KeyError(f"{path}: initializers missing for {missing[:5]}")
    net.load_state_dict({k: sd[k] for k in net.state_dict()})
    return net.eval()


def provenance(ck, manifest=MANIFEST):
    """How a checkpoint's weights were made, as the manifest records it: a training run's variant,
    epochs, seconds and arguments; for a fine-tuning run (`qat_ref --fp32`: the checkpoint names
    the graph it started from by `start_sha256`), the entry of that graph, looked up in the
    manifest by its digest, with the fine-tuning appended to its `fine_tuned` list."""
    if "start_sha256" not in ck:
        return {"variant": ck.get("variant", "full"), "epochs_trained": ck["epoch"] + 1,
                "train_seconds": round(ck.get("elapsed", 0.0)), "train_args": ck.get("args", {})}
    if ck.get("precision", "fp32") != "fp32":
        raise SystemExit("an int8 fine-tuning checkpoint: quantise it (python -m gdrecon_py.qat quantize)")
    models = {}
    if os.path.exists(manifest):
        with open(manifest) as f:
            models = json.load(f).get("models", {})
    start = next((e for e in models.values() if e.get("sha256") == ck["start_sha256"]), None)
    if start is None:
        raise SystemExit(f"the graph the fine-tuning started from (sha256 {ck['start_sha256']}) "
                         f"is not in {manifest}: its training is unknown")
    keep = ("variant", "epochs_trained", "train_seconds", "train_args")
    run = {"how": ck["fine_tuned"], "start_sha256": ck["start_sha256"], "teacher_sha256": ck.get("model_sha256"),
           "steps": ck["step"], "seconds": round(ck.get("elapsed", 0.0)), "device": ck.get("device_name", "cpu"),
           "args": ck.get("args", {})}
    return {**{k: start[k] for k in keep if k in start}, "fine_tuned": list(start.get("fine_tuned", [])) + [run]}


def update_manifest(entry, manifest=MANIFEST):
    d = {"models": {}}
    if os.path.exists(manifest):
        with open(manifest) as f:
            d = json.load(f)
    d.setdefault("models", {})[entry["file"]] = entry
    d["preprocessing"] = ("see onnx/README.md and onnx/pipeline.py: sanitise, feature normalisation, "
                          "mu-law mu=16, pad to multiple of 8 (reflect / anti-symmetric gradients), "
                          "crop, inverse mu-law, Gaussian bias correction radius 45 sigma 15")
    with open(manifest, "w") as f:
        json.dump(d, f, indent=1, sort_keys=True)
        f.write("\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ckpt", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--deconv", choices=DECONV_FORMS, default=DEFAULT_DECONV,
                    help="decoder form in the graph (default %(default)s, see above)")
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    net, ck = load_checkpoint(args.ckpt)
    prov = provenance(ck)
    meta = {"variant": prov["variant"], "epochs_trained": prov["epochs_trained"],
            "train_seconds": prov["train_seconds"], "train_args": json.dumps(prov["train_args"], sort_keys=True)}
    if "fine_tuned" in prov:
        meta["fine_tuned"] = json.dumps(prov["fine_tuned"], sort_keys=True)
    m = export_model(net, args.out, meta, deconv=args.deconv)

    # self-check with onnxruntime
    sess = runtime.session(args.out)
    rng = np.random.default_rng(0)
    worst = 0.0
    for (h, w) in [(16, 24), (40, 32)]:
        d = rng.random((3, net.data_ch, h, w), dtype=np.float32)
        g = (rng.random((3, 2, h, w), dtype=np.float32) - 0.5)
        ref = net(torch.from_numpy(d), torch.from_numpy(g)).detach().numpy()
        got = sess.run(["output"], {"data": d, "grad": g})[0]
        worst = max(worst, float(np.abs(ref - got).max()))
    print(f"{args.out}: IR {m.ir_version}, opset {m.opset_import[0].version}, "
          f"max |torch - ort| = {worst:.2e}", flush=True)
    if worst > 1e-4:
        raise SystemExit("parity check failed")

    digest = sha256_file(args.out)
    base = os.path.basename(args.out)
    with open(args.out + ".sha256", "w") as f:
        f.write(f"{digest}  {base}\n")
    dch = net.data_ch
    entry = {"file": base, "sha256": digest, "bytes": os.path.getsize(args.out),
             "ir_version": m.ir_version, "opset": m.opset_import[0].version,
             "inputs": {"data": ["N", dch, "H", "W"], "grad": ["N", 2, "H", "W"]},
             "outputs": {"output": ["N", 1, "H", "W"]},
             "parity_max_abs": worst, "deconv": args.deconv, **prov}
    update_manifest(entry)
    print(f"sha256 {digest}  {base}", flush=True)


if __name__ == "__main__":
    main()
