"""The combiner: a small CNN that predicts, per pixel, how to weight reconstructions the library
already computes (the prior, L1 on the prior with two data-term weights; `mixed` = 3) and, in the
first variant tried (`mixed` = 4), the base image too.

Why weights and not colours: the candidates already hold the image; the network only has to
tell which one to trust where, which generalises from a small training set (Back et al. 2020
predict per-pixel kernels over an unbiased and a correlated estimate for the same reason).

What was measured before choosing the candidates (validation, `docs/benchmarks.md`, "The
combiner"): choosing per pixel among {prior, l1prior} by the reference (5 x 5 windows) could
reach 0.86 / 0.84 / 0.78x OIDN's relMSE at 4 / 16 / 64 spp; adding L1 with a weak data term
(prior_alpha 0.5) and the base image 0.70 / 0.67 / 0.59x. The network learns that choice from
inputs the frame has. Mixing the base image in cost the `glass` frames the most (1.2-1.3x the
prior), so the shipped model mixes three and reads the base image as an input only.

The ONNX graph holds the network proper (`Combiner.head`): input `features` N x 21 x H x W
float32 (`features` of the 27 stacked planes, `INPUTS` order), H and W multiples of `MULTIPLE`
(the two 2x poolings); output `logits` N x 3 x H x W. The input transforms and the softmax-weighted
sum of the candidates run natively around it (src/recon/combiner.rs; `combine` here is their
reference): in the graph they were 35 % of its time at 1280 x 720 (the softmax over channels
alone 11 %, the transforms' splits, slices and pads most of the rest), natively a few
milliseconds. `combine` runs the whole method as the library does; the torch model's `forward`
is the same function in one piece (training uses it).
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

# Input channels, in order (3 each): the candidates, then the frame's own layers.
CANDIDATES = ("prior", "l1prior", "l1weak", "color")
LAYERS = ("variance", "albedo", "normal", "dx", "dy")
INPUTS = CANDIDATES + LAYERS
IN_CHANNELS = 3 * len(INPUTS)
MULTIPLE = 4
# Radiance floor of the scale each pixel is measured in (the metric's own 0.01 is on R^2).
FLOOR = 0.01
FEATURES = 21


def _soft(x):
    """Signed compression to (-1, 1): keeps the sign and order of a relative difference while
    bounding emitters' and fireflies' huge ratios."""
    return x / (1.0 + x.abs())


def features(x):
    """N x 27 x H x W raw layers -> N x 21 x H x W network input (scale-free where it can be)."""
    prior, a, b, color, var, albedo, normal, dx, dy = torch.split(x, 3, dim=1)
    q = prior.mean(1, keepdim=True) + FLOOR  # the pixel's scale, from the least noisy estimate
    rel = [_soft((c - prior) / q) for c in (a, b, color)]
    level = torch.log(q)
    noise = torch.log(torch.sqrt(var.clamp(min=0).mean(1, keepdim=True)) / q + 1e-3)

    def residual(img, g, axis):
        # forward difference with the gradients' own convention: the last column / row is 0
        if axis == 3:
            d = F.pad(img[..., 1:] - img[..., :-1], (0, 1, 0, 0))
        else:
            d = F.pad(img[..., 1:, :] - img[..., :-1, :], (0, 0, 0, 1))
        return _soft((g - d).abs().mean(1, keepdim=True) / q)

    res = [residual(prior, dx, 3), residual(prior, dy, 2), residual(a, dx, 3), residual(a, dy, 2)]
    return torch.cat(rel + [level, noise] + res + [albedo.clamp(0, 1), normal.clamp(-1, 1)], 1)


def conv(cin, cout):
    return nn.Conv2d(cin, cout, 3, padding=1)


class Combiner(nn.Module):
    """Two-level encoder-decoder: thin at full resolution, its width at 1/2 and 1/4. With
    `taps` = 3 each candidate is weighted at its 3 x 3 neighbours too (a softmax over 4 x 9
    weights per pixel: a per-pixel kernel over the candidates, Back et al. 2020), else at the
    pixel alone."""

    def __init__(self, width=32, thin=16, taps=1, mixed=len(CANDIDATES)):
        super().__init__()
        self.taps = taps
        self.mixed = mixed
        self.inc = conv(FEATURES, thin)
        self.down1 = nn.Sequential(conv(thin, width), nn.ReLU(), conv(width, width), nn.ReLU())
        self.down2 = nn.Sequential(conv(width, width), nn.ReLU(), conv(width, width), nn.ReLU())
        self.up2 = nn.Sequential(conv(2 * width, width), nn.ReLU())
        self.up1 = nn.Sequential(conv(width + thin, thin), nn.ReLU())
        self.out = nn.Conv2d(thin, mixed * taps * taps, 1)

    def head(self, f):
        """The network proper (what the exported graph holds): N x 21 x H x W features ->
        N x mixed taps^2 x H x W logits."""
        f0 = F.relu(self.inc(f))
        f1 = self.down1(F.avg_pool2d(f0, 2))
        f2 = self.down2(F.avg_pool2d(f1, 2))
        u1 = self.up2(torch.cat([F.interpolate(f2, scale_factor=2.0, mode="nearest"), f1], 1))
        u0 = self.up1(torch.cat([F.interpolate(u1, scale_factor=2.0, mode="nearest"), f0], 1))
        return self.out(u0)

    def weights(self, x):
        """Per-pixel softmax weights over the candidates (and taps), N x mixed taps^2 x H x W."""
        return torch.softmax(self.head(features(x)), 1)

    def forward(self, x):
        w = self.weights(x)
        n, _, h, wd = x.shape
        k = self.mixed
        cands = x[:, : 3 * k]
        if self.taps > 1:
            r = self.taps // 2
            p = F.pad(cands, (r, r, r, r), mode="replicate")
            # candidate-major, then taps in row order: channel (c * taps^2 + t) * 3 + rgb
            shifted = [p[:, :, dy:dy + h, dx:dx + wd] for dy in range(self.taps) for dx in range(self.taps)]
            cands = torch.stack(shifted, 2).reshape(n, k, 3, self.taps * self.taps, h, wd)
            cands = cands.permute(0, 1, 3, 2, 4, 5).reshape(n, k * self.taps * self.taps, 3, h, wd)
            return (w.unsqueeze(2) * cands).sum(1)
        cands = cands.reshape(n, k, 3, h, wd)
        return (w.unsqueeze(2) * cands).sum(1)


class Head(nn.Module):
    """`model.head` as a module of its own: what `export` writes (features in, logits out)."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, f):
        return self.model.head(f)


def mix(logits, x, drop=None):
    """The softmax of `logits` (N x k x H x W) over the first k candidates of `x` (N x 27 x H x W):
    the weighted sum the library computes natively around the graph, N x 3 x H x W. Where `drop`
    (N x k x H x W booleans, `dropped`) is set, that candidate's weight is 0 and the others'
    share the whole."""
    n, k = logits.shape[:2]
    h, w = x.shape[2:]
    if drop is not None:
        logits = logits.masked_fill(drop, float("-inf"))
    return (torch.softmax(logits, 1).unsqueeze(2) * x[:, : 3 * k].reshape(n, k, 3, h, w)).sum(1)


# The mean guard (inference only; chosen on validation, docs/benchmarks.md, twenty-first
# session): an L1 candidate is dropped where its mean over the MEAN_WINDOW x MEAN_WINDOW window
# around the pixel (channels averaged, windows clamped at the frame's edges) departs from the
# prior's by more than `tolerance` times the prior's (+ FLOOR). A reconstruction that follows
# the gradients keeps a region's energy where they carry it; where they miss it (caustics seen
# through glass, lit by paths the shifts cannot follow) the weak L1 loses or moves it, and the
# network, which sees the base image agree with it between fireflies, trusted it.
MEAN_WINDOW = 9
MEAN_TOLERANCE = 0.4


def box_mean(img, size=MEAN_WINDOW):
    """Mean of a float64 H x W plane over the size x size window around each pixel, the window
    clamped to the plane (edge pixels repeated): sums along rows, then down columns, each in
    window order, then divided by the window's area (the library's order, so that the two
    agree to the last bit)."""
    import numpy as np
    r = size // 2
    h, w = img.shape
    p = np.pad(img, r, mode="edge")
    rows = p[:, 0:w].copy()
    for j in range(1, size):
        rows = rows + p[:, j:j + w]
    out = rows[0:h].copy()
    for j in range(1, size):
        out = out + rows[j:j + h]
    return out / float(size * size)


def dropped(x, k=3, tolerance=MEAN_TOLERANCE):
    """The mean guard's verdict for the 27 x H x W input (unpadded): k x H x W booleans, True
    where candidate i (1 .. k-1; the prior, 0, is never dropped) is dropped; none when
    `tolerance` is 0. (Tolerance and floor are the library's float32 values.)"""
    import numpy as np
    h, w = x.shape[1:]
    drop = np.zeros((k, h, w), bool)
    if tolerance <= 0:
        return drop
    tol, floor = float(np.float32(tolerance)), float(np.float32(FLOOR))

    def mean(i):
        c = x[3 * i:3 * i + 3].astype(np.float64)
        return box_mean((c[0] + c[1] + c[2]) / 3.0)

    prior = mean(0)
    for i in range(1, k):
        drop[i] = np.abs(mean(i) - prior) > tol * (prior + floor)
    return drop


def relmse_loss(out, ref):
    """The project's metric (docs/CONVENTIONS.md) as a training loss."""
    return ((out - ref) ** 2 / (ref ** 2 + 0.01)).mean()


# --- the reference around the graph (the Rust side, src/recon/combiner.rs, is tested against it)

def stack(frame, candidates):
    """27 x H x W float32 graph input from a frame dict (H x W x 3 layers: color, variance,
    albedo, normal, dx, dy; already sanitised as the library does) and the candidates dict
    (prior, l1prior, l1weak; H x W x 3)."""
    import numpy as np
    planes = [candidates[n] if n != "color" else frame["color"] for n in CANDIDATES]
    planes += [frame[n] for n in LAYERS]
    return np.ascontiguousarray(np.concatenate(planes, -1).transpose(2, 0, 1), np.float32)


def pad(x):
    """The 27 x H x W input padded at the bottom and right to multiples of MULTIPLE by repeating
    the last row and column (every channel alike), as 1 x 27 x H' x W'."""
    import numpy as np
    h, w = x.shape[1:]
    ph, pw = (-h) % MULTIPLE, (-w) % MULTIPLE
    return np.pad(x, ((0, 0), (0, ph), (0, pw)), mode="edge")[None]


def combine(x, run, tolerance=MEAN_TOLERANCE):
    """The library's output (3 x H x W) for the 27 x H x W input: `pad`, the features, `run`
    (the graph: N x 21 x h x w features -> N x k x h x w logits), cropped, then `mix` with the
    mean guard's `dropped` candidates, negative values set to 0 (as the library's plan does to
    every output: radiance is never negative)."""
    import numpy as np
    h, w = x.shape[1:]
    with torch.no_grad():
        f = features(torch.from_numpy(pad(x))).numpy()
        logits = torch.from_numpy(np.asarray(run(f)))[:, :, :h, :w]
        drop = torch.from_numpy(dropped(x, logits.shape[1], tolerance))[None]
        out = mix(logits, torch.from_numpy(x)[None], drop).clamp(min=0)
    return out.numpy()[0]


def reference(x, model, tolerance=MEAN_TOLERANCE):
    """The torch model's head on the padded input, cropped and mixed as `combine` mixes (3 x H x
    W): what `combine` through onnxruntime must equal."""
    return combine(x, lambda f: model.head(torch.from_numpy(f)).numpy(), tolerance)


OPSET = 17
MAX_IR = 10


def export(model, path, metadata=None):
    """Writes `model`'s head as ONNX (input `features` N x 21 x H x W, output `logits`
    N x mixed x H x W; N, H, W dynamic), `path`.sha256, and its entry in onnx/models.json;
    returns the max |torch - onnxruntime| over two random inputs, of the logits and of the whole
    method (`combine` against the model's forward; must be under 1e-4)."""
    import hashlib
    import json
    import os

    import numpy as np
    import onnx

    from . import runtime
    model = model.eval()
    if model.taps != 1:
        raise SystemExit("only taps = 1 exports: the library mixes one weight per candidate")
    dyn = {"features": {0: "N", 2: "H", 3: "W"}, "logits": {0: "N", 2: "H", 3: "W"}}
    torch.onnx.export(Head(model), torch.zeros(1, FEATURES, 32, 48), path,
                      input_names=["features"], output_names=["logits"], dynamic_axes=dyn,
                      opset_version=OPSET, dynamo=False, do_constant_folding=True,
                      export_params=True)
    m = onnx.load(path)
    m.ir_version = min(m.ir_version, MAX_IR)
    meta = {"inputs": ",".join(INPUTS), "features": str(FEATURES), "output": "logits",
            "size_multiple": str(MULTIPLE),
            "producer_note": "gdrecon combiner's head; see onnx/gdrecon_py/combiner.py"}
    meta.update(metadata or {})
    del m.metadata_props[:]
    for k, v in meta.items():
        p = m.metadata_props.add()
        p.key, p.value = k, str(v)
    onnx.checker.check_model(m)
    onnx.save(m, path)
    sess = runtime.session(path)
    rng = np.random.default_rng(0)
    worst = 0.0
    for (h, w) in [(16, 24), (40, 32)]:
        f = rng.standard_normal((2, FEATURES, h, w), dtype=np.float32)
        with torch.no_grad():
            ref = model.head(torch.from_numpy(f)).numpy()
        got = sess.run(["logits"], {"features": f})[0]
        worst = max(worst, float(np.abs(ref - got).max()))
        x = rng.random((IN_CHANNELS, h - 1, w - 3), dtype=np.float32) * 2
        got = combine(x, lambda a: sess.run(["logits"], {"features": a})[0])
        worst = max(worst, float(np.abs(reference(x, model) - got).max()))
    if worst > 1e-4:
        raise SystemExit(f"{path}: torch and onnxruntime differ by {worst:.2e}")
    digest = hashlib.sha256(open(path, "rb").read()).hexdigest()
    base = os.path.basename(path)
    with open(path + ".sha256", "w") as f:
        f.write(f"{digest}  {base}\n")
    manifest = os.path.join(os.path.dirname(os.path.abspath(path)), "models.json")
    d = json.load(open(manifest)) if os.path.exists(manifest) else {"models": {}}
    d["models"][base] = {"file": base, "sha256": digest, "bytes": os.path.getsize(path),
                         "ir_version": m.ir_version, "opset": m.opset_import[0].version,
                         "inputs": {"features": ["N", FEATURES, "H", "W"]},
                         "outputs": {"logits": ["N", model.mixed, "H", "W"]},
                         "parity_max_abs": worst, **(metadata or {})}
    with open(manifest, "w") as f:
        json.dump(d, f, indent=1, sort_keys=True)
        f.write("\n")
    return worst


FIXTURES = "tests/fixtures/combiner"
GUARD = "tests/data/guard"


def write_fixtures(model_path="onnx/combiner.onnx", gdrecon="target/release/gdrecon"):
    """The parity fixtures of tests/combiner.rs: for every guard frame (tests/data/guard/<stem>.exr)
    given the prior of tests/fixtures/prior/<stem>_oidn.npy as its `prior` layer (so OIDN's
    instruction-set differences stay out), the candidates as the library computes them (the
    CLI), then `combine` through onnxruntime, checked against torch (1e-4), written as
    tests/fixtures/combiner/<stem>.npy (H x W x 3 float32); with combiner_int8.onnx beside the
    model, `combine` through it too, as <stem>_int8.npy."""
    import glob
    import os
    import shutil
    import subprocess
    import tempfile

    import numpy as np

    from . import runtime
    from .candidates import CANDIDATES as RUNS
    from .data.render import add_layers, read_bundle
    from .pipeline import sanitize
    sess = runtime.session(model_path)
    int8_path = os.path.join(os.path.dirname(model_path), "combiner_int8.onnx")
    int8 = runtime.session(int8_path) if os.path.exists(int8_path) else None
    model = model_from_onnx(model_path)
    os.makedirs(FIXTURES, exist_ok=True)
    for path in sorted(glob.glob(os.path.join(GUARD, "*.exr"))):
        stem = os.path.splitext(os.path.basename(path))[0]
        with tempfile.TemporaryDirectory() as tmp:
            bundle = os.path.join(tmp, stem + ".exr")
            shutil.copy(path, bundle)
            add_layers(bundle, {"prior": np.load(f"tests/fixtures/prior/{stem}_oidn.npy")})
            cands = {}
            for name, opts in RUNS.items():
                out = os.path.join(tmp, f"{name}.exr")
                subprocess.run([gdrecon, "reconstruct", bundle, "-o", out, "-q", "--threads", "2",
                                *opts], check=True)
                cands[name] = read_bundle(out)[0][""]
            layers, _ = read_bundle(bundle)
        x = stack(sanitize(layers) | {"variance": layers["variance"]}, cands)
        got = combine(x, lambda a: sess.run(["logits"], {"features": a})[0])
        ref = reference(x, model)
        worst = float(np.max(np.abs(got - ref) / (np.abs(ref) + 1e-3)))
        if worst > 1e-4:
            raise SystemExit(f"{stem}: onnxruntime and torch differ by {worst:.2e} (relative)")
        np.save(os.path.join(FIXTURES, f"{stem}.npy"), np.ascontiguousarray(got.transpose(1, 2, 0)))
        print(f"{stem}: written; |onnxruntime - torch| <= {worst:.1e} relative")
        if int8 is not None:
            q = combine(x, lambda a: int8.run(["logits"], {"features": a})[0])
            np.save(os.path.join(FIXTURES, f"{stem}_int8.npy"), np.ascontiguousarray(q.transpose(1, 2, 0)))
            off = float(np.max(np.abs(q - got) / (np.abs(got) + 1e-3)))
            print(f"{stem}: int8 written; |int8 - fp32| <= {off:.1e} relative")


def model_from_onnx(path):
    """The torch model with the weights stored in an exported graph (initialisers by name: the
    head's graph names them `model.<name>`; graphs of the whole model, before 0.3, `<name>`)."""
    import numpy as np
    import onnx
    from onnx import numpy_helper
    m = onnx.load(path)
    inits = {i.name.removeprefix("model."): torch.from_numpy(np.array(numpy_helper.to_array(i)))
             for i in m.graph.initializer}
    meta = {p.key: p.value for p in m.metadata_props}
    model = Combiner(mixed=int(meta.get("mixed", len(CANDIDATES))))
    sd = model.state_dict()
    missing = [k for k in sd if k not in inits]
    if missing:
        raise KeyError(f"{path}: initialisers missing for {missing[:4]}")
    model.load_state_dict({k: inits[k] for k in sd})
    return model.eval()


INT8_EXCLUDE = ("/model/inc/Conv", "/model/out/Conv")
CALIBRATION = "~/.cache/gdrecon/data/train2-calib"


def quantize_int8(model_path, out, data, exclude=INT8_EXCLUDE):
    """The head in int8 (QDQ; `quantize.quantize`'s defaults: int8 weights per output channel,
    uint8 activations, MinMax), calibrated on the features of every bundle in `data` (training
    split only; the candidates beside them, `candidates.py`), padded as `combine` pads. The
    first convolution (21 inputs of unlike scales) and the logits' stay fp32 (`exclude`):
    they cost nothing measurable in speed. Writes `out`, `out`.sha256 and its models.json entry."""
    import hashlib
    import os

    import onnxruntime

    from . import quantize as q
    from .export import update_manifest
    from .train_combiner import load_frame
    files = q.calibration_files(os.path.expanduser(data), 0)
    feeds = []
    for f in files:
        x, _ = load_frame(f)
        with torch.no_grad():
            feeds.append({"features": features(torch.from_numpy(pad(x))).numpy()})
    m = q.quantize(model_path, out, feeds, exclude=list(exclude))
    digest = q.sha256_file(out)
    base = os.path.basename(out)
    with open(out + ".sha256", "w") as fh:
        fh.write(f"{digest}  {base}\n")
    update_manifest({
        "file": base, "sha256": digest, "bytes": os.path.getsize(out), "precision": "int8",
        "ir_version": m.ir_version, "opset": m.opset_import[0].version,
        "inputs": {"features": ["N", FEATURES, "H", "W"]},
        "outputs": {"logits": ["N", 3, "H", "W"]},
        "source": {"file": os.path.basename(model_path), "sha256": q.sha256_file(model_path)},
        "quantization": {"tool": f"onnxruntime.quantization {onnxruntime.__version__}",
                         "format": "qdq", "weights": "int8 symmetric per channel",
                         "activations": "u8 asymmetric per tensor", "reduce_range": False,
                         "calibration": "minmax", "nodes_in_fp32": list(exclude)},
        "calibration": {"split": "training only",
                        "dir": data.replace(os.path.expanduser("~"), "~"),
                        "bundles": [os.path.basename(f) for f in files],
                        "bundles_sha256": hashlib.sha256("\n".join(
                            q.sha256_file(f) for f in files).encode()).hexdigest()}},
        os.path.join(os.path.dirname(os.path.abspath(out)), "models.json"))
    print(f"{out}: {len(files)} calibration bundles, sha256 {digest}")


WORST = 1.05


def choose(log):
    """The checkpoint to export, by validation only (rule fixed before the test split was
    read): the lowest geometric-mean relMSE ratio to the prior among evaluated steps whose worst
    validation frame is at most WORST times the prior's relMSE; if there is none, the step with
    the lowest worst frame."""
    safe = [e for e in log if e["val_worst"][1] <= WORST]
    if safe:
        return min(safe, key=lambda e: e["val_vs_prior"])
    return min(log, key=lambda e: e["val_worst"][1])


def main(argv=None):
    """python -m gdrecon_py.combiner --ckpt RUN/last.pt --out onnx/combiner.onnx
    python -m gdrecon_py.combiner --fixtures      (run from the repository root)
    python -m gdrecon_py.combiner --from-onnx OLD.onnx --out onnx/combiner.onnx
    python -m gdrecon_py.combiner --int8 [--data DIR] --out onnx/combiner_int8.onnx

    Exports the evaluated step `choose` picks from the run's log; or, with --from-onnx, the
    weights and training metadata of an exported graph again (how the shipped head was made
    from the whole-model graph of 0.2: same weights, same outputs to 1e-6)."""
    import argparse
    import json
    import os
    ap = argparse.ArgumentParser(description="Export a trained combiner to ONNX, or write its parity fixtures")
    ap.add_argument("--ckpt")
    ap.add_argument("--out", default="onnx/combiner.onnx")
    ap.add_argument("--fixtures", action="store_true")
    ap.add_argument("--from-onnx", help="re-export the weights of this graph")
    ap.add_argument("--int8", action="store_true",
                    help="quantise onnx/combiner.onnx to --out, calibrated on --data")
    ap.add_argument("--data", default=CALIBRATION, help="training bundles (default %(default)s)")
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    if args.int8:
        quantize_int8(os.path.join(os.path.dirname(os.path.abspath(args.out)), "combiner.onnx"),
                      args.out, args.data)
        return
    if args.fixtures:
        write_fixtures(args.out)
        return
    if args.from_onnx:
        import onnx
        old = {p.key: p.value for p in onnx.load(args.from_onnx).metadata_props}
        keep = ("train_steps", "chosen_step", "val_vs_prior", "val_worst", "mixed", "train_args")
        # the graph's metadata holds strings: numbers and lists back as they were written
        import ast
        meta = {k: old[k] if k == "train_args" else ast.literal_eval(old[k])
                for k in keep if k in old}
        model = model_from_onnx(args.from_onnx)
        worst = export(model, args.out, meta)
        print(f"{args.out}: from {args.from_onnx}; max |torch - onnxruntime| = {worst:.2e}")
        return
    ck = torch.load(args.ckpt, map_location="cpu", weights_only=False)
    args_ = ck.get("args", {})
    model = Combiner(width=args_.get("width", 32), taps=args_.get("taps", 1), mixed=args_.get("mixed", 4))
    step = choose(ck["log"])
    run = os.path.dirname(args.ckpt)
    model.load_state_dict(torch.load(os.path.join(run, f"step_{step['step']:06d}.pt"), map_location="cpu"))
    meta = {"train_steps": ck["step"], "chosen_step": step["step"],
            "val_vs_prior": round(step["val_vs_prior"], 5), "val_worst": step["val_worst"],
            "mixed": model.mixed, "train_args": json.dumps(args_, sort_keys=True)}
    worst = export(model, args.out, meta)
    print(f"{args.out}: max |torch - onnxruntime| = {worst:.2e}; {json.dumps(meta)}")


if __name__ == "__main__":
    main()
