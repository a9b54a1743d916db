"""Quantisation-aware fine-tuning (QAT) of GradNet for its int8 graph (issue #19 item 3).

Post-training int8 (`quantize.py`) cost the GPU-trained model +2 / +6 / +13 % relMSE over fp32 at
4 / 16 / 64 spp on validation (docs/gradnet.md, "Reduced precision"), against a bar of 2 %.
Calibration choices did not close it: the error is spread over the graph. This module fine-tunes
the fp32 weights so that the int8 graph ONNX Runtime makes of them reproduces the fp32 model.

    # once, on any machine: the activation ranges of today's int8 graph, for the device
    $GDRECON_PYTHON -m gdrecon_py.qat ranges --int8 onnx/gradnet_int8.onnx --out RANGES.json
    # fine-tune (a lent GPU; resumable: re-run the same command)
    python -m gdrecon_py.qat train --train P.xz --model onnx/gradnet.onnx --ranges RANGES.json \\
        --out RUN --budget 300 --export $OUT
    # back here: the int8 graph of the fine-tuned weights, with the ranges it was tuned for
    $GDRECON_PYTHON -m gdrecon_py.qat quantize --ckpt RUN/last --ranges RANGES.json \\
        --out onnx/gradnet_int8.onnx

What the simulation reproduces of the deployed graph (`quantize.py`'s recipe, read off the QDQ
graph it writes):
- weights int8 symmetric per output channel, scale max|w| / 127, of every convolution except the
  first of each branch (`d1`, `g1`) and the output convolution (`out`). The decoder's transposed
  convolutions run as the sub-pixel convolutions of `export.py`, whose output channels are the
  (output channel, row parity, column parity) triples of the transposed kernel: scales per triple.
- activations uint8 asymmetric per tensor, at every tensor the QDQ graph quantises (41: each
  encoder convolution's output and its LeakyReLU's, the concatenations, each residual block's
  two convolutions, LeakyReLU and sum, each decoder layer's ReLU output, the four output phases
  of `u3`). Scales and zero points are fixed, taken from a QDQ graph (`ranges`): the fine-tuned
  weights are then quantised with exactly those (`TensorQuantOverrides`), so training and
  deployment quantise alike. Rounding half to even, as QuantizeLinear.
- straight-through gradients (zero outside an activation's range, as torch's fake quantisation).

Loss (`--loss`): distillation to the fp32 model itself, the teacher in strict fp32 (TF32 off):
`l1` (default), mean |y_int8-sim - y_fp32| in the network's output domain (mu-law); `relmse`, the
radiances' squared difference weighted as the relMSE metric weighs it. Self-supervised losses
would move the model away from what was chosen on validation; the bar is "int8 as accurate as
fp32".
Training crops: `train_gradnet.Crops` (the training split's pack, 8 rotations/mirrors, exposure
2^U(-2, 2)), batch 32 of 128^2; Adam, linear warm-up then cosine decay to 0 over a step count
sized by a probe of this device's rate (`--budget` seconds), recorded for resumes.

Result (twenty-fourth session, docs/gradnet.md): `l1`, lr 1e-4, 3731 steps on an H200 halved
the int8 graph's distance from fp32 on training frames, and its relMSE over fp32 went from +6.8
to +5.8 % on validation and from +10.4 to +7.0 % on test, still over 2 %. The shipped graph
was then fine-tuned further against references (`qat_ref.py`: +0.9 / +1.5 %); since the fp32
model was fine-tuned against them too, the int8 graph was that recipe applied to it (+3.3 /
+5.8 % over the new fp32 through the library), and since the thirty-ninth session that recipe
with narrowed pre-LeakyReLU ranges and learned scales (`qat_ref --negative-fraction 0.25
--learn-ranges 2e-3`: +0.9 / +3.8 %).
"""
import argparse
import copy
import json
import math
import os
import shutil
import sys
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from . import ONNX_DIR
from . import gradnet as gn
from . import output_layer

QMIN_W, QMAX_W = -127, 127      # ONNX Runtime's symmetric int8 weight range
QMIN_A, QMAX_A = 0, 255         # uint8 activations
FP32_CONVS = ("d1", "g1", "out")

# The activation tensors the QDQ graph quantises, by their ONNX names (export.py's graph,
# subpixel-poly decoder), in the order the forward pass meets them.
ACT_NAMES = (
    [f"/{b}{i}/{b}{i}.{k}/{op}_output_0" for i in (1, 2, 3) for b in ("d", "g")
     for k, op in ((0, "Conv"), (1, "LeakyRelu"))]
    + ["/Concat_output_0"]
    + [f"/res/res.{i}/{t}_output_0" for i in range(4) for t in ("c1/Conv", "LeakyRelu", "c2/Conv", "Add")]
    + ["/Concat_1_output_0", "/u1/u1.0/Relu_output_0", "/u1/u1.0/Slice_output_0",
       "/Concat_2_output_0", "/u2/u2.0/Relu_output_0", "/u2/u2.0/Slice_output_0",
       "/Concat_3_output_0"]
    + [f"/u3/Relu{s}_output_0" for s in ("", "_1", "_2", "_3")]       # phases 00, 01, 10, 11
    + ["/u3/Concat_output_0"])


# Each sub-pixel layer's crop is quantised as its shuffle's input (`quantize.py`,
# `share_shuffle_quantization`): {crop: shuffle input}.
SHARED = {"/u1/u1.0/Slice_output_0": "/u1/u1.0/Relu_output_0",
          "/u2/u2.0/Slice_output_0": "/u2/u2.0/Relu_output_0"}


# The convolution outputs that feed a LeakyReLU (slope 0.01), each with that activation's output.
# The graph quantises both: the convolution's range covers its negative side in full (down to
# -4.2 where the activation keeps -0.042), so its uint8 step is 3-7 times the activation's.
PRE_LRELU = {**{f"/{b}{i}/{b}{i}.0/Conv_output_0": f"/{b}{i}/{b}{i}.1/LeakyRelu_output_0"
                for i in (1, 2, 3) for b in ("d", "g")},
             **{f"/res/res.{i}/c1/Conv_output_0": f"/res/res.{i}/LeakyRelu_output_0" for i in range(4)}}


# The ReLU graph (`gradnet.GradNet(activation="relu")`, docs/gradnet.md, "A ReLU graph for int8"):
# ONNX Runtime's quantiser removes each ReLU and quantises its convolution's output once, at the
# ReLU's range (zero point 0, so the clamp is the ReLU), under the ReLU's output name; each
# PRE_LRELU pair is one tensor there. {LeakyReLU output: the ReLU graph's tensor}
RELU_OF = {v: v.replace("LeakyRelu", "Relu") for v in PRE_LRELU.values()}
ACT_NAMES_RELU = tuple(RELU_OF.get(k, k) for k in ACT_NAMES if k not in PRE_LRELU)


def act_names(activation):
    """The tensors the int8 graph of a GradNet with this encoder activation quantises."""
    return ACT_NAMES_RELU if activation == "relu" else ACT_NAMES


def relu_ranges(ranges):
    """The ReLU graph's ranges from a LeakyReLU graph's `ranges` (ACT_NAMES): each activation's
    positive side kept at its step count, zero point 0 (s, z) -> (s (255 - z) / 255, 0); the other
    tensors' unchanged."""
    out = {}
    for k in ACT_NAMES_RELU:
        if k in RELU_OF.values():
            s, z = ranges[k.replace("Relu", "LeakyRelu")]
            out[k] = (float(np.float32(s * (QMAX_A - z) / QMAX_A)), 0)
        else:
            out[k] = ranges[k]
    return out


def with_activation(net, activation):
    """A GradNet with `net`'s weights and the encoder activation `activation` (`net` itself if it
    has it already): the ReLU graph starts from a LeakyReLU graph's weights."""
    if net.activation == activation:
        return net
    out = gn.GradNet(data_ch=net.data_ch, activation=activation)
    out.load_state_dict(net.state_dict())
    return out.train(net.training)


def narrow_negatives(ranges, fraction):
    """`ranges` with each PRE_LRELU tensor's negative side cut to `fraction` of its length, the
    positive side kept, so that the 256 steps are finer: (s, z) -> (s', z') with
    s' = (fraction s z + s (255 - z)) / 255, z' = round(fraction s z / s'). 1 changes nothing."""
    out = dict(ranges)
    if fraction == 1:
        return out
    if not 0 < fraction < 1:
        raise ValueError(f"negative fraction {fraction}: not in (0, 1]")
    for k in PRE_LRELU:
        s, z = ranges[k]
        lo, hi = fraction * s * z, s * (255 - z)
        s2 = float(np.float32((lo + hi) / 255))
        out[k] = (s2, int(round(lo / s2)))
    return out


def deployed(ranges):
    """`ranges` as the deployed graph quantises: each crop with its shuffle input's range (the
    crop's own quantisation is then the identity)."""
    return {k: ranges[SHARED.get(k, k)] for k in ranges}


# ------------------------------------------------------------------------------------------
# the deployed graph's activation quantisation

def ranges_from_int8(path):
    """{ONNX tensor name: (scale, zero_point)} of every activation QuantizeLinear in a QDQ graph."""
    import onnx
    from onnx import numpy_helper
    m = onnx.load(path)
    inits = {i.name: np.array(numpy_helper.to_array(i)) for i in m.graph.initializer}
    out = {}
    for n in m.graph.node:
        if n.op_type == "QuantizeLinear" and n.input[0] not in inits:
            s, z = inits[n.input[1]], inits[n.input[2]]
            if s.size != 1 or z.dtype != np.uint8:
                raise ValueError(f"{path}: {n.input[0]} is not per-tensor uint8")
            out[n.input[0]] = (float(s.reshape(())), int(z.reshape(())))
    names = act_names(gn.activation_of({p.key: p.value for p in m.metadata_props}))
    missing = [k for k in names if k not in out]
    if missing:
        raise ValueError(f"{path}: no quantisation of {missing[:3]}: not export.py's subpixel-poly graph?")
    return {k: out[k] for k in names}


class _FakeAct(torch.autograd.Function):
    """y = (clamp(round(x / s) + z, 0, 255) - z) s; the gradient passes where x is inside the
    range. x / s rather than x * (1 / s) (torch's fake_quantize_per_tensor_affine): the latter
    rounds some ties the other way from QuantizeLinear. When the scale is learned (it requires a
    gradient) its gradient is LSQ's (Esser et al. 2020): dy/ds = round(x / s) - x / s inside the
    range, (qmin - z) or (qmax - z) where x is clipped."""

    @staticmethod
    def forward(ctx, x, scale, zp):
        r = x / scale
        q = torch.round(r) + zp
        inside = (q >= QMIN_A) & (q <= QMAX_A)
        ctx.save_for_backward(inside, *((r, q, zp) if ctx.needs_input_grad[1] else ()))
        return (q.clamp(QMIN_A, QMAX_A) - zp) * scale

    @staticmethod
    def backward(ctx, g):
        inside, *lsq = ctx.saved_tensors
        ds = None
        if lsq:
            r, q, zp = lsq
            step = torch.where(inside, q - zp - r, torch.where(q < QMIN_A, QMIN_A - zp, QMAX_A - zp))
            ds = (g * step).sum().reshape(())
        return g * inside, ds, None


def net_from_int8(path):
    """The torch GradNet whose weights and biases are a QDQ graph's dequantised ones (int8 weight
    x scale; int32 bias x its scale): with the graph's activation ranges, `QATGradNet` over it
    simulates that graph whatever fp32 weights it was made from."""
    import onnx
    from onnx import numpy_helper
    from .export import unswap_state_dict
    m = onnx.load(path)
    inits = {i.name: np.array(numpy_helper.to_array(i)) for i in m.graph.initializer}
    params = {}
    for n in m.graph.node:
        if n.op_type == "DequantizeLinear" and n.input[0] in inits:
            q = inits[n.input[0]].astype(np.float64)
            sc = inits[n.input[1]].astype(np.float64)
            zp = inits[n.input[2]].astype(np.float64) if len(n.input) > 2 else 0.0
            if sc.ndim == 1 and q.ndim > 1:
                shape = [1] * q.ndim
                axis = next((a.i for a in n.attribute if a.name == "axis"), 1)
                shape[axis] = -1
                sc, zp = sc.reshape(shape), np.reshape(zp, shape) if np.ndim(zp) else zp
            params[n.output[0]] = torch.from_numpy(((q - zp) * sc).astype(np.float32))
    # a weight read through a DequantizeLinear is named by its output (`u3.w00_DequantizeLinear_Output`);
    # a bias keeps its own name; the layers kept in fp32 read their float initializers directly
    named = {k.replace("_DequantizeLinear_Output", ""): v for k, v in params.items()}
    named.update({k: torch.from_numpy(v) for k, v in inits.items() if v.dtype == np.float32 and k not in named})
    # a sub-pixel layer's bias is its transposed convolution's, once per output phase; int32
    # rounding at each channel's own scale leaves the copies a fraction of a step apart: their mean
    for k in ("u1.0.conv.bias", "u2.0.conv.bias"):
        if k in named:
            b = named[k].reshape(-1, 4)
            named[k] = b.mean(1, keepdim=True).expand_as(b).reshape(-1).clone()
    meta = {p.key: p.value for p in m.metadata_props}
    layer = output_layer.read(meta)
    if layer is not None:
        # the output convolution travels in the metadata (`output_layer.py`), in its 3 x 3 form
        named["out.conv.weight"] = torch.from_numpy(output_layer.phase_form(layer["weight"]))
        named["out.conv.bias"] = torch.full((4,), float(layer["bias"]))
    sd = unswap_state_dict(named, meta.get("deconv", "convtranspose"), int(meta.get("data_channels", "8")))
    net = gn.GradNet(activation=gn.activation_of(meta))
    net.load_state_dict(sd)
    return net.eval()


def fake_act(x, scale, zp):
    """uint8 QuantizeLinear + DequantizeLinear of `x` (float32 math), straight-through inside the
    range. scale: 0-d float32 tensor, zp: 0-d tensor, on x's device; a scale that requires a
    gradient gets LSQ's."""
    return _FakeAct.apply(x.float(), scale, zp.float())


def weight_scale(w, transposed):
    """Per-channel symmetric scales (max|w| / 127) as the deployed graph's: a Conv2d weight
    (Cout x Cin x k x k) per output channel; a ConvTranspose2d(k=4, s=2) weight (Cin x Cout x 4 x 4)
    per (output channel, kernel row parity, kernel column parity), the output channels of its
    sub-pixel form. Returned broadcastable against w."""
    a = w.detach().abs()
    if not transposed:
        m = a.amax(dim=(1, 2, 3), keepdim=True)
    else:
        cin, cout, kh, kw = a.shape
        g = a.reshape(cin, cout, kh // 2, 2, kw // 2, 2).amax(dim=(0, 2, 4), keepdim=True)
        m = g.expand(1, cout, kh // 2, 2, kw // 2, 2).reshape(1, cout, kh, kw)
    return torch.where(m > 0, m / QMAX_W, torch.ones_like(m))


def fake_weight(w, transposed):
    """int8 symmetric fake quantisation of a weight, straight-through (nothing clips: the scale
    comes from max|w|)."""
    s = weight_scale(w, transposed)
    q = torch.clamp(torch.round(w / s), QMIN_W, QMAX_W) * s
    return w + (q - w).detach()


class QATGradNet(nn.Module):
    """GradNet's forward pass with the int8 graph's quantisation simulated (`quant` True) or not
    (then bit-for-bit `net`'s). `ranges`: {ONNX name: (scale, zero point)} for the tensors of
    `act_names(net.activation)`. `learn_ranges`: the scales become a parameter (`log_scales`,
    LSQ's gradient; a crop shares its shuffle input's, as deployed), the zero points stay."""

    def __init__(self, net, ranges, learn_ranges=False):
        super().__init__()
        self.net = net
        self.quant = True
        self.names = act_names(net.activation)
        ranges = deployed(ranges)
        s = torch.tensor([ranges[k][0] for k in self.names], dtype=torch.float32)
        z = torch.tensor([ranges[k][1] for k in self.names], dtype=torch.int32)
        self.register_buffer("scales", s)
        self.register_buffer("zps", z)
        self._index = {k: i for i, k in enumerate(self.names)}
        # the tensor whose scale each one uses (itself, or for a crop its shuffle input)
        self._tie = [self._index[SHARED.get(k, k)] for k in self.names]
        self.log_scales = nn.Parameter(torch.log(s)) if learn_ranges else None

    def scale(self, i):
        """The scale of self.names[i] (0-d float32 tensor)."""
        if self.log_scales is None:
            return self.scales[i]
        return torch.exp(self.log_scales[self._tie[i]])

    def ranges(self):
        """{ONNX name: (scale, zero point)} as simulated now (float32 scales), `deployed` form."""
        with torch.no_grad():
            return {k: (float(self.scale(i)), int(self.zps[i])) for i, k in enumerate(self.names)}

    @property
    def data_ch(self):
        """The wrapped network's data channels (what `pipeline.torch_runner` reads)."""
        return self.net.data_ch

    def _a(self, x, name):
        if not self.quant:
            return x
        i = self._index[name]
        return fake_act(x, self.scale(i), self.zps[i])

    def _w(self, conv, name, transposed=False):
        if not self.quant or name in FP32_CONVS:
            return conv.weight
        return fake_weight(conv.weight, transposed)

    def _down(self, name, x):
        conv = getattr(self.net, name)[0]
        y = F.conv2d(x, self._w(conv, name), conv.bias, stride=2, padding=1)
        if self.net.activation == "relu":
            return self._a(F.relu(y), f"/{name}/{name}.1/Relu_output_0")
        y = self._a(y, f"/{name}/{name}.0/Conv_output_0")
        return self._a(F.leaky_relu(y, gn.LRELU), f"/{name}/{name}.1/LeakyRelu_output_0")

    def _res(self, i, x):
        blk = self.net.res[i]
        p = f"/res/res.{i}/"
        y = F.conv2d(x, self._w(blk.c1, "c1"), blk.c1.bias, padding=1)
        if self.net.activation == "relu":
            y = self._a(F.relu(y), p + "Relu_output_0")
        else:
            y = self._a(F.leaky_relu(self._a(y, p + "c1/Conv_output_0"), gn.LRELU), p + "LeakyRelu_output_0")
        y = self._a(F.conv2d(y, self._w(blk.c2, "c2"), blk.c2.bias, padding=1), p + "c2/Conv_output_0")
        return self._a(x + y, p + "Add_output_0")

    def _up(self, name, x):
        ct = getattr(self.net, name)[0]
        return F.relu(F.conv_transpose2d(x, self._w(ct, name, True), ct.bias, stride=2, padding=1))

    def forward(self, data, grad):
        d1 = self._down("d1", data)
        g1 = self._down("g1", grad)
        d2 = self._down("d2", d1)
        g2 = self._down("g2", g1)
        d3 = self._down("d3", d2)
        g3 = self._down("g3", g2)
        r = self._a(torch.cat([d3, g3], 1), "/Concat_output_0")
        for i in range(len(self.net.res)):
            r = self._res(i, r)
        u = self._a(torch.cat([r, d3, g3], 1), "/Concat_1_output_0")
        u = self._a(self._a(self._up("u1", u), "/u1/u1.0/Relu_output_0"), "/u1/u1.0/Slice_output_0")
        u = self._a(torch.cat([u, d2, g2], 1), "/Concat_2_output_0")
        u = self._a(self._a(self._up("u2", u), "/u2/u2.0/Relu_output_0"), "/u2/u2.0/Slice_output_0")
        u = self._a(torch.cat([u, d1, g1], 1), "/Concat_3_output_0")
        u = self._up("u3", u)
        if self.quant:
            # the four output phases (row parity a, column parity b) are four tensors there
            q = u.clone()
            for k, (a, b) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
                q[..., a::2, b::2] = self._a(u[..., a::2, b::2], self.names[-5 + k])
            u = self._a(q, "/u3/Concat_output_0")
        out = self.net.out
        return F.relu(F.conv2d(u, out.weight, out.bias, padding=1))


# ------------------------------------------------------------------------------------------
# training

def _teacher(net, data, grad):
    """The fp32 model in strict fp32 (TF32 off for this call)."""
    prev = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    try:
        with torch.no_grad():
            return net(data, grad)
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = prev


def _inputs(x):
    from .train import split_batch
    data, grad = split_batch(x)[:2]
    return (data.contiguous(memory_format=torch.channels_last),
            grad.contiguous(memory_format=torch.channels_last))


def distill_loss(y, t, kind):
    """How far the student's output `y` is from the teacher's `t` (both mu-law): `l1`, the mean
    absolute difference there; `relmse`, the squared difference of the radiances weighted as the
    relMSE metric weighs it, 1 / (t^2 + 0.01) (`metrics.relmse`'s epsilon), the teacher standing
    in for the reference."""
    if kind == "l1":
        return (y - t).abs().mean()
    from .mulaw import mulaw_inv
    lt = mulaw_inv(t)
    return ((mulaw_inv(y) - lt) ** 2 / (lt ** 2 + 0.01)).mean()


def evaluate(student, teacher, batches):
    """Mean |y_sim - y_fp32|, its RMS and the `relmse` distance over fixed crops."""
    l1 = l2 = rel = n = 0.0
    with torch.no_grad():
        for x in batches:
            data, grad = _inputs(x)
            t = _teacher(teacher, data, grad)
            s = student(data, grad)
            l1 += float((s - t).abs().sum())
            l2 += float(((s - t) ** 2).sum())
            rel += float(distill_loss(s, t, "relmse")) * t.numel()
            n += t.numel()
    return {"mae": l1 / n, "rmse": math.sqrt(l2 / n), "relmse": rel / n}


def lr_at(step, total, lr, warmup):
    if step < warmup:
        return lr * (step + 1) / warmup
    p = min(1.0, (step - warmup) / max(1, total - warmup))
    return lr * 0.5 * (1 + math.cos(math.pi * p))


def train(args):
    from . import pack
    from .export import net_from_onnx
    from .train_gradnet import Crops, save_parts, sync
    t_start = time.time()
    device = torch.device(args.device)
    torch.set_num_threads(args.threads)
    torch.backends.cudnn.benchmark = True
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = True
    os.makedirs(args.out, exist_ok=True)
    with open(args.ranges) as f:
        ranges = {k: tuple(v) for k, v in json.load(f)["ranges"].items()}

    tarr = pack.read_train(args.train)
    print(f"data: {sum(a.shape[0] for a in tarr.values())} training frames, "
          f"{time.time() - t_start:.1f} s", flush=True)

    teacher = net_from_onnx(args.model).to(device, memory_format=torch.channels_last)
    for p in teacher.parameters():
        p.requires_grad_(False)
    torch.manual_seed(args.seed)
    student = QATGradNet(copy.deepcopy(teacher), ranges).to(device)
    for p in student.net.parameters():
        p.requires_grad_(True)
    opt = torch.optim.Adam(student.net.parameters(), lr=args.lr, betas=(0.9, 0.999))
    crops = Crops(tarr, device, seed=args.seed)
    held = Crops(tarr, device, seed=args.seed + 104729)
    eval_batches = [held.sample(args.batch, args.patch, args.exposure, True) for _ in range(args.eval_batches)]

    last = os.path.join(args.out, "last.pt")
    step, total, elapsed = 0, args.steps, 0.0
    log = open(os.path.join(args.out, "log.jsonl"), "a")
    if os.path.exists(last):
        ck = torch.load(last, map_location=device, weights_only=False)
        student.net.load_state_dict(ck["net"])
        opt.load_state_dict(ck["opt"])
        crops.gen.set_state(ck["sampler_rng"])
        torch.set_rng_state(ck["torch_rng"])
        step, total, elapsed = ck["step"], ck["total"], ck["elapsed"]
        print(f"resumed from {last} at step {step} of {total}", flush=True)
    else:
        e0 = evaluate(student, teacher, eval_batches)
        rec = {"kind": "eval", "step": 0, **e0}
        log.write(json.dumps(rec) + "\n")
        print(json.dumps(rec), flush=True)

    def save():
        ck = {"net": student.net.state_dict(), "opt": opt.state_dict(), "sampler_rng": crops.gen.get_state(),
              "torch_rng": torch.get_rng_state(), "step": step, "total": total, "elapsed": elapsed,
              "args": vars(args)}
        torch.save(ck, last + ".tmp")
        os.replace(last + ".tmp", last)

    student.train()
    t0, sums, n, probe_t = time.time(), 0.0, 0, None
    stopped, first = False, step
    while total <= 0 or step < total:
        if (args.deadline > 0 and time.time() - t_start > args.deadline) or \
                (args.stop_after > 0 and step - first >= args.stop_after):
            stopped = True
            break
        if total <= 0 and step in (args.probe_steps, 2 * args.probe_steps):
            # size the run from this device's rate, the first probe_steps (warm-up) excluded
            sync(device)
            if probe_t is None:
                probe_t = time.time()
            else:
                rate = (time.time() - probe_t) / args.probe_steps
                total = max(step + 1, int(args.budget / rate))
                print(f"probe: {rate * 1e3:.1f} ms a step; {total} steps", flush=True)
        x = crops.sample(args.batch, args.patch, args.exposure, True)
        data, grad = _inputs(x)
        t = _teacher(teacher, data, grad)
        lr = lr_at(step, total, args.lr, args.warmup) if total > 0 else lr_at(step, 1 << 40, args.lr, args.warmup)
        for g in opt.param_groups:
            g["lr"] = lr
        y = student(data, grad)
        loss = distill_loss(y, t, args.loss)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        sums += float(loss.detach())
        n += 1
        if step % args.log_every == 0:
            now = time.time()
            elapsed += now - t0
            t0 = now
            rec = {"kind": "train", "step": step, "total": total, "lr": lr, "loss": sums / n, "elapsed": elapsed}
            sums, n = 0.0, 0
            log.write(json.dumps(rec) + "\n")
            log.flush()
            print(json.dumps(rec), flush=True)
        if args.save_every > 0 and step % args.save_every == 0:
            save()
    sync(device)
    elapsed += time.time() - t0
    save()
    student.eval()
    e1 = evaluate(student, teacher, eval_batches)
    rec = {"kind": "eval", "step": step, "total": total, "stopped_early": stopped, "elapsed": elapsed, **e1}
    log.write(json.dumps(rec) + "\n")
    log.close()
    print(json.dumps(rec), flush=True)
    if args.export:
        os.makedirs(args.export, exist_ok=True)
        from .quantize import sha256_file
        save_parts({"net": student.net.state_dict(), "epoch": 0, "elapsed": elapsed, "variant": "full",
                    "model_sha256": sha256_file(args.model),
                    "args": vars(args), "step": step, "total": total,
                    "device_name": torch.cuda.get_device_name(0) if device.type == "cuda" else "cpu"},
                   os.path.join(args.export, "last"))
        shutil.copyfile(os.path.join(args.out, "log.jsonl"), os.path.join(args.export, "log.jsonl"))
        print(f"exported to {args.export} ({time.time() - t_start:.0f} s after the start)", flush=True)


# ------------------------------------------------------------------------------------------
# deployment

def quantize_ckpt(args):
    """Fine-tuned weights -> fp32 graph (temporary) -> QDQ int8 graph whose activation scales are
    the ranges the weights were tuned for (TensorQuantOverrides); the calibration data only
    serves ONNX Runtime's pass over the graph and does not set any quantised tensor's range."""
    import tempfile
    from . import quantize as qz
    from .export import export_model
    from .train_gradnet import merge_parts
    ck = merge_parts(args.ckpt) if not args.ckpt.endswith(".pt") else torch.load(args.ckpt, map_location="cpu",
                                                                                 weights_only=False)
    activation = ck.get("activation", "leaky_relu")
    net = gn.GradNet(activation=activation)
    net.load_state_dict(ck["net"])
    net.eval()
    if ck.get("ranges"):
        # a `qat_ref` run saves the ranges it simulated (narrowed or learned, maybe)
        rj = {"ranges": ck["ranges"]}
        origin = ("the run's own (its checkpoint's; source.fine_tuned says how they were set), starting "
                  f"from those of the int8 graph sha256 {ck.get('start_sha256')}")
    elif args.ranges:
        with open(args.ranges) as f:
            rj = json.load(f)
        origin = f"from {rj.get('source')} sha256 {rj.get('sha256')}"
    else:
        raise SystemExit(f"{args.ckpt}: the checkpoint holds no ranges; name them with --ranges")
    ranges = deployed({k: tuple(v) for k, v in rj["ranges"].items()})
    overrides = {k: [{"scale": np.array(s, np.float32), "zero_point": np.array(z, np.uint8)}]
                 for k, (s, z) in ranges.items()}
    files = qz.calibration_files(args.data, args.frames)
    feeds = qz.calibration_inputs(files, use_features=True)
    with tempfile.TemporaryDirectory() as tmp:
        src = os.path.join(tmp, "gradnet_qat_fp32.onnx")
        export_model(net, src, {"variant": "full", "qat_steps": str(ck.get("step", 0))})
        m = qz.quantize(src, args.out, feeds, exclude=qz.DEFAULT_EXCLUDE.split(","), method="percentile",
                        overrides=overrides if not args.recalibrate else None)
        src_sha = qz.sha256_file(src)
    got = ranges_from_int8(args.out)
    if not args.recalibrate:
        bad = [k for k in act_names(activation) if abs(got[k][0] - ranges[k][0]) > 1e-12 * max(1.0, ranges[k][0])
               or got[k][1] != ranges[k][1]]
        if bad:
            raise SystemExit(f"{args.out}: the overrides did not hold for {bad[:3]}")
    # the graph's metadata names the fp32 model it stands for (the teacher), and the fine-tuned
    # weights it was quantised from
    teacher_sha = ck.get("model_sha256") or qz.sha256_file(os.path.join(ONNX_DIR, "gradnet.onnx"))
    import onnx
    props = {p.key: p.value for p in m.metadata_props}
    props.update({"source_sha256": teacher_sha, "fine_tuned_sha256": src_sha,
                  "fine_tuning": f"{ck.get('fine_tuned', 'quantisation-aware, gdrecon_py.qat')}, {ck.get('step')} steps",
                  "calibration": "fixed activation ranges (TensorQuantOverrides)" if not args.recalibrate
                  else "percentile"})
    del m.metadata_props[:]
    for k in sorted(props):
        m.metadata_props.add(key=k, value=props[k])
    onnx.save(m, args.out)
    digest = qz.sha256_file(args.out)
    print(f"{args.out}: {len(files)} calibration bundles, source sha256 {src_sha}, sha256 {digest}", flush=True)
    if args.no_manifest:
        return
    import hashlib
    import onnxruntime
    from .export import update_manifest
    base = os.path.basename(args.out)
    with open(args.out + ".sha256", "w") as f:
        f.write(f"{digest}  {base}\n")
    targs = ck.get("args", {})
    entry = {"file": base, "sha256": digest, "bytes": os.path.getsize(args.out), "precision": "int8",
             "ir_version": m.ir_version, "opset": m.opset_import[0].version,
             "inputs": {"data": ["N", 8, "H", "W"], "grad": ["N", 2, "H", "W"]},
             "outputs": output_layer.manifest_outputs(m),
             **({"activation": activation} if activation != "leaky_relu" else {}),
             "source": {"file": "gradnet.onnx", "sha256": teacher_sha,
                        "fine_tuned": ck.get("fine_tuned", "quantisation-aware (gdrecon_py.qat), distilled from the fp32 graph"),
                        "qat_steps": ck.get("step"), "qat_seconds": round(ck.get("elapsed", 0.0)),
                        "qat_device": ck.get("device_name"), "qat_lr": targs.get("lr"),
                        "qat_batch": targs.get("batch"), "qat_patch": targs.get("patch"),
                        **({"qat_negative_fraction": targs["negative_fraction"]}
                           if targs.get("negative_fraction", 1.0) != 1.0 else {}),
                        **({"qat_learn_ranges": targs["learn_ranges"]} if targs.get("learn_ranges") else {}),
                        "fp32_of_fine_tuned_sha256": src_sha},
             "quantization": {"tool": f"onnxruntime.quantization {onnxruntime.__version__}", "format": "qdq",
                              "weights": "int8 symmetric per channel",
                              "activations": "u8 asymmetric per tensor",
                              "reduce_range": False,
                              "calibration": "percentile" if args.recalibrate else
                              "fixed: the ranges the weights were tuned for (TensorQuantOverrides), "
                              + origin,
                              "nodes_in_fp32": qz.DEFAULT_EXCLUDE.split(",")},
             "calibration": {"split": f"{os.path.basename(os.path.normpath(args.data))} (training only)",
                             "dir": args.data.replace(os.path.expanduser("~"), "~"),
                             "bundles": [os.path.basename(f) for f in files], "channel_inputs": 3 * len(files),
                             "bundles_sha256": hashlib.sha256("\n".join(
                                 qz.sha256_file(f) for f in files).encode()).hexdigest()}}
    update_manifest(entry)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("ranges", help="activation scales and zero points of a QDQ graph -> JSON")
    r.add_argument("--int8", required=True)
    r.add_argument("--out", required=True)
    t = sub.add_parser("train", help="fine-tune with the int8 graph simulated")
    t.add_argument("--train", required=True, nargs="+", help="training packs (gdrecon_py.pack train)")
    t.add_argument("--model", required=True, help="fp32 graph whose weights are the start and the teacher")
    t.add_argument("--ranges", required=True, help="JSON from `ranges`")
    t.add_argument("--out", required=True, help="run folder (checkpoint, log); re-running resumes")
    t.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    t.add_argument("--steps", type=int, default=0, help="total steps; 0: sized by a probe and --budget")
    t.add_argument("--budget", type=float, default=300.0, help="seconds of steps, with --steps 0")
    t.add_argument("--probe-steps", type=int, default=20)
    t.add_argument("--deadline", type=float, default=0.0, help="stop this many seconds after the start")
    t.add_argument("--stop-after", type=int, default=0, help="stop after this many steps (a chunk); 0: no limit")
    t.add_argument("--batch", type=int, default=32)
    t.add_argument("--patch", type=int, default=128)
    t.add_argument("--lr", type=float, default=2e-5)
    t.add_argument("--loss", choices=("l1", "relmse"), default="l1", help="distillation loss (distill_loss)")
    t.add_argument("--warmup", type=int, default=100)
    t.add_argument("--exposure", type=float, default=2.0)
    t.add_argument("--eval-batches", type=int, default=8)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--threads", type=int, default=2)
    t.add_argument("--log-every", type=int, default=100)
    t.add_argument("--save-every", type=int, default=1000)
    t.add_argument("--export", default="", help="folder for the weights in parts (last-*.pt) and the log")
    q = sub.add_parser("quantize", help="fine-tuned weights -> int8 QDQ graph with the tuned ranges")
    q.add_argument("--ckpt", required=True, help="a checkpoint (.pt) or the prefix of exported parts")
    q.add_argument("--ranges", default="",
                   help="JSON from `ranges` (ignored when the checkpoint holds its own: a qat_ref run's)")
    q.add_argument("--out", required=True)
    q.add_argument("--data", default=os.path.expanduser("~/.cache/gdrecon/data/train3"))
    q.add_argument("--frames", type=int, default=24)
    q.add_argument("--no-manifest", action="store_true", help="do not write .sha256 / models.json")
    q.add_argument("--recalibrate", action="store_true",
                   help="let Percentile calibration set the ranges instead of the tuned ones")
    args = ap.parse_args(argv)
    if args.cmd == "ranges":
        rg = ranges_from_int8(args.int8)
        from .quantize import sha256_file
        with open(args.out, "w") as f:
            json.dump({"source": os.path.basename(args.int8), "sha256": sha256_file(args.int8),
                       "ranges": rg}, f, indent=1)
        print(f"{args.out}: {len(rg)} activation ranges", flush=True)
    elif args.cmd == "train":
        train(args)
    else:
        quantize_ckpt(args)


if __name__ == "__main__":
    main(sys.argv[1:])
