"""Reference pre/post-processing around the GradNet graph (numpy only; the Rust side is tested
against these functions). The ONNX graph contains only the network; everything here is outside.

Steps, for one frame (arrays H x W x C, float32, linear radiance):
 1. sanitise: NaN/Inf -> 0 in every layer, negative colour -> 0 (gradients stay signed).
 2. feature normalisation (per frame): clamp features to [-1e5, 1e5]; albedo clamped to [0, 1]
    (deviation from the release, see `normalize_features`);
    normal -> normal * 0.5 + 0.5; depth -> (depth - min) / (max - min) (0 if max == min).
 3. mu-law (mu = 16): data channel C(I_c), gradient channels S(dx_c), S(dy_c).
 4. pad bottom/right to multiples of 8 (`pad_frame`): colour and features with reflect
    (numpy 'reflect', edge not repeated); gradients with the mirror that is consistent with the
    reflected colour: along their own axis anti-symmetric (dx'(x) = -dx(2W-3-x) for x >= W-1,
    so the stored-zero last column is replaced too), along the other axis plain reflect.
    Nothing is changed when the size already is a multiple of 8.
 5. run the network with the per-channel batch: data N x 8 x H x W (N x 1 for the no-feature
    model), grad N x 2 x H x W, N = 3 (R, G, B); output N x 1 x H x W.
 6. crop to H x W, inverse mu-law C^-1, clamp >= 0.
 6b. (deviation from the release, `emitters`) where a base pixel is beyond the network's
    range (a channel above EMITTER_LIMIT = 2) and known to a relative standard deviation below
    EMITTER_NOISE = 0.1 (an emitter seen directly, not a firefly), the output takes the base
    colour: the mu-law input assumes radiance in [0, 1], the network cannot output an emitter,
    and the bias correction's gain would spread the missing energy over the frame.
 7. Gaussian bias correction: kernel radius 45, sigma 15 (91 taps, normalised), separable,
    zero-padded borders; gain = (blur(R+G+B of input colour) + 1e-9) /
    (blur(R+G+B of output) + 1e-9), multiplied into all three channels. (Deviation from the
    release, `beyond`:) pixels with a base channel above BIAS_LIMIT = 10 that step 6b did not
    keep (an emitter's partly covered edge, fireflies) enter neither blur: the network cannot
    output that light, and its missing energy raised the gain over a whole room lit by bulbs
    in view (10x the error on the `lamps` guard frame).
The library then clamps every method's output to the base image's noise band (`noise_band`,
src/recon/band.rs); that is not part of this reference, and the parity tests turn it off.
"""
import os

import numpy as np

from . import output_layer, runtime
from .mulaw import C, C_inv, S  # the float32 numpy mu-law (mu = 16)

FEAT_CLAMP = 1e5
BIAS_RADIUS = 45
BIAS_SIGMA = 15.0
EMITTER_LIMIT = 2.0
EMITTER_NOISE = 0.1
BIAS_LIMIT = 10.0


def read_frame(path):
    """Bundle -> dict of H x W x C float32 arrays (color, dx, dy, [albedo, normal, depth,
    reference]) plus 'spp'. Uses data/render.py's reader (imported here: it loads Mitsuba)."""
    from .data.render import read_bundle
    layers, header = read_bundle(path)
    out = {k: v for k, v in layers.items()}
    out["spp"] = header.get("spp")
    return out


def sanitize(frame):
    """NaN/Inf -> 0 everywhere, negative colour -> 0. Returns a new dict (arrays copied)."""
    out = dict(frame)
    for k in ("color", "dx", "dy", "albedo", "normal", "depth"):
        if k in out and out[k] is not None:
            a = np.nan_to_num(np.asarray(out[k], np.float32), nan=0.0, posinf=0.0, neginf=0.0)
            if k == "color":
                a = np.maximum(a, 0.0)
            out[k] = a
    return out


def has_features(frame):
    return all(frame.get(k) is not None for k in ("albedo", "normal", "depth"))


ALBEDO_RANGE = (0.0, 1.0)
TRAIN_ALBEDO_RANGE = (-FEAT_CLAMP, FEAT_CLAMP)   # what train.py used (the release's clamp)


def normalize_features(albedo, normal, depth, albedo_range=ALBEDO_RANGE):
    """-> H x W x 7 float32: albedo (3) clamped to `albedo_range`, normal*0.5+0.5 (3), depth
    min-max normalised (1); all clamped to [-1e5, 1e5] first (the release).
    Inference clamps albedo to [0, 1]: Mitsuba's aov albedo of rough / anisotropic conductors
    reaches 204 in our training set (0.4 % of its pixels > 1) and 551 on the `metals` validation
    frame, far outside what the network learnt, and the release's clamp at 1e5 let the output
    explode there (metals relMSE 5.4 / 8.1 / 1.7 at 4 / 16 / 64 spp, 0.026 / 0.011 / 0.0060
    with the [0, 1] clamp; frames whose albedo is within [0, 1] are unchanged)."""
    a = np.clip(np.clip(albedo, -FEAT_CLAMP, FEAT_CLAMP), *albedo_range).astype(np.float32)
    n = np.clip(normal, -FEAT_CLAMP, FEAT_CLAMP).astype(np.float32) * 0.5 + 0.5
    d = np.clip(depth, -FEAT_CLAMP, FEAT_CLAMP).astype(np.float32)
    if d.ndim == 2:
        d = d[..., None]
    d = d[..., :1]
    lo, hi = float(d.min()), float(d.max())
    d = (d - lo) / (hi - lo) if hi > lo else np.zeros_like(d)
    return np.concatenate([a, n, d.astype(np.float32)], -1)


def _pad_amount(n, m=8):
    return (-n) % m


def pad_reflect(a, ph, pw):
    """a: H x W x C, reflect-pad bottom/right."""
    if ph == 0 and pw == 0:
        return a
    return np.pad(a, ((0, ph), (0, pw), (0, 0)), mode="reflect")


def pad_grad(a, ph, pw, axis):
    """Pad a forward-difference image (axis=1: dx along x, axis=0: dy along y) bottom/right so
    that it stays the forward difference of the reflect-padded colour. Along its own axis:
    g'(k) = -g(2n-3-k) for k >= n-1; along the other axis: plain reflect."""
    a = np.asarray(a, np.float32)
    H, W = a.shape[:2]
    if axis == 1:
        if pw > 0:
            idx = np.arange(W - 1, W + pw)
            a = np.concatenate([a[:, :W - 1], -a[:, 2 * W - 3 - idx]], 1)
        if ph > 0:
            a = np.pad(a, ((0, ph), (0, 0), (0, 0)), mode="reflect")
    else:
        if ph > 0:
            idx = np.arange(H - 1, H + ph)
            a = np.concatenate([a[:H - 1], -a[2 * H - 3 - idx]], 0)
        if pw > 0:
            a = np.pad(a, ((0, 0), (0, pw), (0, 0)), mode="reflect")
    return a


def prepare_inputs(frame, use_features=True):
    """Sanitised frame -> (data N x Cd x Hp x Wp, grad N x 2 x Hp x Wp, (H, W)), N = 3."""
    H, W = frame["color"].shape[:2]
    ph, pw = _pad_amount(H), _pad_amount(W)
    if (ph and H < 3) or (pw and W < 3):
        raise ValueError(f"frame {W}x{H} too small to pad to a multiple of 8")
    col = pad_reflect(frame["color"], ph, pw)
    dx = pad_grad(frame["dx"], ph, pw, axis=1)
    dy = pad_grad(frame["dy"], ph, pw, axis=0)
    c = C(col).transpose(2, 0, 1)[:, None]                         # 3 x 1 x Hp x Wp
    g = np.stack([S(dx).transpose(2, 0, 1), S(dy).transpose(2, 0, 1)], 1)  # 3 x 2 x Hp x Wp
    if use_features:
        f = normalize_features(frame["albedo"], frame["normal"], frame["depth"])
        f = pad_reflect(f, ph, pw).transpose(2, 0, 1)[None]     # 1 x 7 x Hp x Wp
        data = np.concatenate([c, np.repeat(f, 3, 0)], 1)
    else:
        data = c
    return np.ascontiguousarray(data, np.float32), np.ascontiguousarray(g, np.float32), (H, W)


def gaussian_kernel(radius=BIAS_RADIUS, sigma=BIAS_SIGMA):
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    k = np.exp(-x * x / (2 * sigma * sigma))
    return k / k.sum()


def _conv_same_zero(a, k, axis):
    # np.convolve(mode='same') with a kernel longer than the signal returns len(kernel) when
    # the signal is shorter: do it by explicit zero padding instead.
    r = len(k) // 2
    pad = [(0, 0)] * a.ndim
    pad[axis] = (r, r)
    p = np.pad(a, pad)
    out = np.zeros_like(a)
    n = a.shape[axis]
    for i, w in enumerate(k):
        sl = [slice(None)] * a.ndim
        sl[axis] = slice(i, i + n)
        out += w * p[tuple(sl)]
    return out


def blur2d(img, radius=BIAS_RADIUS, sigma=BIAS_SIGMA):
    """Separable Gaussian blur with zero padding, any size (float64)."""
    k = gaussian_kernel(radius, sigma)
    a = np.asarray(img, np.float64)
    return _conv_same_zero(_conv_same_zero(a, k, 1), k, 0)


def bias_correct(out, color_in, skip=None):
    """out, color_in: H x W x 3 linear. gain = (blur(sum in)+1e-9)/(blur(sum out)+1e-9), the
    pixels where `skip` (H x W bool) is set left out of both sums."""
    si, so = color_in.sum(-1), out.sum(-1)
    if skip is not None:
        si, so = np.where(skip, 0.0, si), np.where(skip, 0.0, so)
    bi = blur2d(si) + 1e-9
    bo = blur2d(so) + 1e-9
    return (out * (bi / bo)[..., None]).astype(np.float32)


def emitters(color, variance=None, limit=EMITTER_LIMIT, noise=EMITTER_NOISE):
    """H x W bool: any channel exceeds `limit` with a relative standard deviation below `noise`
    (no variance layer: brightness alone decides); none where `limit` is 0 or less."""
    if limit <= 0:
        return np.zeros(color.shape[:2], bool)
    bright = color > limit
    if variance is not None:
        bright &= np.sqrt(np.maximum(variance, 0.0)) < noise * color
    return bright.any(axis=-1)


def beyond(color, limit=BIAS_LIMIT, kept=None):
    """Step 7's pixels left out of the gain: a channel above `limit`, not in `kept` (H x W
    bool); None where `limit` is 0 or less (the release)."""
    if limit <= 0:
        return None
    mask = (color > limit).any(axis=-1)
    return mask if kept is None else mask & ~kept


def reconstruct(frame, run, use_features=None, correct_bias=True, range_limit=EMITTER_LIMIT,
                bias_limit=BIAS_LIMIT):
    """Full reference pipeline. `run(data, grad) -> N x 1 x Hp x Wp` (numpy in/out; a torch
    model or an onnxruntime session wrapped, see `torch_runner` / `ort_runner`).
    use_features=None: follow the model (runner's `data_channels`: 8 -> features, 1 -> none),
    else use them when the frame has them. Returns H x W x 3 float32."""
    fr = sanitize(frame)
    if use_features is None:
        dch = getattr(run, "data_channels", None)
        use_features = has_features(fr) if dch is None else dch == 8
        if use_features and not has_features(fr):
            raise ValueError("the model needs albedo, normal and depth; use the no-feature model")
    data, grad, (H, W) = prepare_inputs(fr, use_features)
    y = np.asarray(run(data, grad), np.float32)[:, 0, :H, :W]     # 3 x H x W
    out = np.maximum(C_inv(y), 0.0).transpose(1, 2, 0)
    out = np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)
    kept = emitters(fr["color"], fr.get("variance"), range_limit)
    out = np.where(kept[..., None], fr["color"], out).astype(np.float32)
    if correct_bias:
        out = bias_correct(out, fr["color"], beyond(fr["color"], bias_limit, kept))
    return out


def torch_runner(model, device="cpu"):
    """A torch model as `run`; `device` is where the model lives (inputs go there, the output
    comes back to the CPU as float32)."""
    import torch

    def run(data, grad):
        with torch.no_grad():
            y = model(torch.from_numpy(data).to(device), torch.from_numpy(grad).to(device))
            return y.float().cpu().numpy()
    run.data_channels = model.data_ch
    return run


def ort_runner(path_or_session):
    sess = path_or_session
    if isinstance(path_or_session, (str, os.PathLike)):
        sess = runtime.session(str(path_or_session))

    layer = output_layer.read(sess.get_modelmeta().custom_metadata_map)

    def run(data, grad):
        if layer is None:
            return sess.run(["output"], {"data": data, "grad": grad})[0]
        return output_layer.apply(layer, sess.run([output_layer.OUTPUT], {"data": data, "grad": grad})[0])
    shape = sess.get_inputs()[0].shape
    run.data_channels = shape[1] if isinstance(shape[1], int) else None
    return run
