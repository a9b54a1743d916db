"""Quantisation-aware fine-tuning of GradNet's int8 graph against references (issue #19 item 3;
docs/gradnet.md, "Fine-tuning against references").

`qat.py` distils the int8 student to the fp32 model; that halved their distance but left the
whole pipeline's relMSE +5.9 % over fp32 on validation, because what remains of the difference
leans the way fp32 is already wrong (the cross term, which a loss without a reference cannot
see). This module continues from an int8 graph's own weights (`qat.net_from_int8`, its
activation ranges, `qat.ranges_from_int8`, as below) with a loss that has the reference in it:

    L = mean(clip(w (y - R)^2, c)) + d mean(w (y - T)^2),   w = 1 / (T^2 + 0.01)

y the simulated int8 output, T the fp32 teacher's, R the bundle's reference, all linear radiance
(inverse mu-law of the networks' outputs), per colour channel. The weight is relMSE's but taken
from the teacher, not the reference: 1024 spp references are noisy, and a weight that depends on
the target's noise biases the optimum low. The cap `c` keeps the references' fireflies from
steering a step; the distillation term (`d`) keeps the student near the model chosen on
validation. Families whose references are noisier than the network's error are left out
(`--skip`, default `aquarium` and `vitrine`: their 1024 spp references' relMSE at 144 x 144 is
about 0.03 and 0.007, against 0.001-0.006 for GradNet on validation; a first run with them in,
weighted by the reference, without the cap or the distillation term and at 3x the rate, raised
validation relMSE by 36 % in 100 steps).

    source onnx/env.sh
    $GDRECON_PYTHON -m gdrecon_py.data.render --scene train --size 144x144 --ref-spp 1024 \\
        --perturb-seed 1 --seed 40000 --out ~/.cache/gdrecon/data/qatref --skip-existing \\
        --spp 4,16,64 --perturb 100:110
    $GDRECON_PYTHON -m gdrecon_py.qat_ref --start START.onnx --out RUN --negative-fraction 0.25 \\
        --learn-ranges 2e-3 [--val ~/.cache/gdrecon/data/val]
    $GDRECON_PYTHON -m gdrecon_py.qat quantize --ckpt RUN/last.pt --out onnx/gradnet_int8.onnx

Activation ranges: the start graph's, each convolution output that feeds a LeakyReLU with the
negative side of its range cut to `--negative-fraction` (`qat.narrow_negatives`: the graph
quantises that output before the activation, so its full negative side, which the activation
scales by 0.01, made its steps 3-7 times the activation's); `--learn-ranges LR` learns the
scales (LSQ, zero points kept) at that peak rate. The checkpoint keeps the ranges it simulated
and `qat quantize` writes them into the graph (docs/gradnet.md, "Finer activation ranges").

`--fp32` fine-tunes the fp32 network itself with the same loss (the student unquantised, started
from the fp32 graph `--start`, the teacher that graph too unless `--teacher` says otherwise), and
`python -m gdrecon_py.export --ckpt RUN/last.pt --out onnx/gradnet.onnx` exports it:

    $GDRECON_PYTHON -m gdrecon_py.qat_ref --fp32 --start onnx/gradnet.onnx --out RUN

Re-running the same command resumes from RUN/last.pt (saved every `--save-every` steps with the
optimiser and the sampler's state): the result is the same as an uninterrupted run's.
Crops: `--batch` of `--patch`^2 from the bundles, one of the 8 rotations/mirrors with exact
gradients (`train_gradnet.dihedral_apply`) and an exposure 2^U(-e, e) on colour, gradients and
reference alike; Adam, linear warm-up over `--warmup` steps times a cosine decay to 0.
"""
import argparse
import glob
import json
import math
import os
import time

import numpy as np
import torch

from . import ONNX_DIR, pack, qat
from . import gradnet as gn
from . import pipeline as pl
from .mulaw import mulaw_inv

# A frame's planes: the training planes (colour, dx, dy, the 7 normalised features), then the
# reference's three.
REF = slice(pack.TRAIN_PLANES, pack.TRAIN_PLANES + 3)


def load_frames(folder, skip):
    """Every bundle with a reference in `folder`, sorted by name, families in `skip` left out ->
    N x 19 x H x W float32: the training planes inference would prepare (`pack.train_planes`)
    and the reference."""
    frames, names = [], []
    for f in sorted(glob.glob(os.path.join(folder, "*.exr"))):
        name = os.path.basename(f)
        if name.split("_")[0] in skip:
            continue
        fr = pl.read_frame(f)
        if fr.get("reference") is None:
            raise SystemExit(f"{f}: no reference layer (render with --ref-spp)")
        ref = np.nan_to_num(fr["reference"].astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        frames.append(np.concatenate([pack.train_planes(fr), ref.transpose(2, 0, 1)]))
        names.append(name)
    if not frames:
        raise SystemExit(f"{folder}: no bundles")
    return torch.from_numpy(np.stack(frames)), names


def sample(arr, gen, batch, patch, exposure):
    """batch x 19 x patch x patch augmented crops (the generator `gen` decides everything)."""
    from .train_gradnet import dihedral_apply
    n, _, H, W = arr.shape
    idx = torch.randint(0, n, (batch,), generator=gen)
    ys = torch.randint(0, H - patch + 1, (batch,), generator=gen)
    xs = torch.randint(0, W - patch + 1, (batch,), generator=gen)
    code = torch.randint(0, 8, (batch,), generator=gen)
    scale = torch.exp2((torch.rand(batch, generator=gen) * 2 - 1) * exposure)
    x = torch.stack([arr[i, :, y:y + patch, xx:xx + patch] for i, y, xx in zip(idx, ys, xs)])
    x = dihedral_apply(x, code)
    s = scale[:, None, None, None]
    x[:, :9] *= s
    x[:, REF] *= s
    return x


def loss_of(student, teacher, x, dist, clip):
    """The loss of the module docstring on crops `x` (B x 19 x P x P)."""
    from .train import split_batch
    data, grad = split_batch(x[:, :pack.TRAIN_PLANES])[:2]
    B, _, h, w = x.shape
    ref = x[:, REF].reshape(B * 3, 1, h, w)
    ly = mulaw_inv(student(data, grad))
    with torch.no_grad():
        lt = mulaw_inv(teacher(data, grad))
    wgt = 1.0 / (lt ** 2 + 0.01)
    e = (ly - ref) ** 2 * wgt
    if clip > 0:
        e = e.clamp(max=clip)
    loss = e.mean()
    if dist > 0:
        loss = loss + dist * ((ly - lt) ** 2 * wgt).mean()
    return loss


def lr_at(step, total, lr, warmup):
    """Linear warm-up times a cosine over the whole run (not `qat.lr_at`'s cosine after the
    warm-up: the shipped weights were made with this one)."""
    return lr * min(1.0, (step + 1) / warmup) * 0.5 * (1 + math.cos(math.pi * step / max(1, total)))


def validate(student, frames):
    """`train_gradnet.validate` with the student (the simulated int8 network, or fp32): relMSE of
    the whole reference pipeline per frame, geometric means per spp and over all frames."""
    from .train_gradnet import validate as validate_net
    score, geo, rows = validate_net(student, frames, "cpu")
    return {"all": score, **{f"{k}spp": v for k, v in geo.items()}, "rows": rows}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=os.path.expanduser("~/.cache/gdrecon/data/qatref"),
                    help="bundles with reference layers")
    ap.add_argument("--skip", default="aquarium,vitrine", help="families left out (comma-separated)")
    ap.add_argument("--start", required=True,
                    help="the int8 graph whose weights and ranges the run starts from (--fp32: an fp32 graph)")
    ap.add_argument("--teacher", default="", help="the fp32 graph of the distillation term and the weight "
                    "(default: onnx/gradnet.onnx; with --fp32, --start)")
    ap.add_argument("--fp32", action="store_true", help="fine-tune the fp32 network (no quantisation simulated)")
    ap.add_argument("--relu", action="store_true",
                    help="the ReLU graph: the encoder's and residual blocks' LeakyReLU replaced by ReLU, which "
                         "ONNX Runtime fuses into the int8 convolutions (one quantisation where the LeakyReLU "
                         "graph has two); from a LeakyReLU start graph its ranges become qat.relu_ranges'")
    ap.add_argument("--negative-fraction", type=float, default=1.0, metavar="F",
                    help="start with each pre-LeakyReLU convolution output's negative range cut to this "
                    "fraction (qat.narrow_negatives; 1: the start graph's ranges)")
    ap.add_argument("--learn-ranges", type=float, default=0.0, metavar="LR",
                    help="learn the activation scales too (LSQ, on their logarithm, at this peak rate "
                    "with the weights' schedule); 0: keep the start graph's")
    ap.add_argument("--out", required=True, help="run folder (last.pt, log.jsonl); re-running resumes")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--patch", type=int, default=128)
    ap.add_argument("--lr", type=float, default=1e-5)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--dist", type=float, default=1.0, help="weight of the distillation term")
    ap.add_argument("--clip", type=float, default=0.05, help="cap of a pixel's weighted error (0: none)")
    ap.add_argument("--exposure", type=float, default=2.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--val", default="", help="validation bundles, evaluated every --val-every steps")
    ap.add_argument("--val-every", type=int, default=100)
    ap.add_argument("--save-every", type=int, default=50)
    args = ap.parse_args(argv)
    if args.fp32 and (args.learn_ranges > 0 or args.negative_fraction != 1 or args.relu):
        raise SystemExit("--learn-ranges, --negative-fraction, --relu: an fp32 run has no activation ranges")
    if args.relu and args.negative_fraction != 1:
        raise SystemExit("--negative-fraction: the ReLU graph quantises no convolution output before its activation")
    if not args.fp32 and args.negative_fraction != 1:
        import onnx
        if gn.activation_of({p.key: p.value for p in onnx.load(args.start).metadata_props}) == "relu":
            raise SystemExit(f"--negative-fraction: {args.start} is a ReLU graph")
    from .export import net_from_onnx
    from .quantize import sha256_file
    if not args.teacher:
        args.teacher = args.start if args.fp32 else os.path.join(ONNX_DIR, "gradnet.onnx")
    torch.set_num_threads(args.threads)
    os.makedirs(args.out, exist_ok=True)
    t_start = time.time()

    arr, names = load_frames(args.data, set(filter(None, args.skip.split(","))))
    print(f"{arr.shape[0]} training frames ({time.time() - t_start:.1f} s)", flush=True)
    gen = torch.Generator().manual_seed(args.seed)
    if args.fp32:
        student = net_from_onnx(args.start)
    else:
        start = qat.net_from_int8(args.start)
        ranges = qat.ranges_from_int8(args.start)
        if args.relu and start.activation != "relu":
            ranges = qat.relu_ranges(ranges)
        ranges = qat.narrow_negatives(ranges, args.negative_fraction)
        start = qat.with_activation(start, "relu" if args.relu else start.activation)
        student = qat.QATGradNet(start, ranges, learn_ranges=args.learn_ranges > 0)
    teacher = net_from_onnx(args.teacher).eval()
    for p in teacher.parameters():
        p.requires_grad_(False)
    net = student if args.fp32 else student.net
    # each group follows the schedule from its own peak rate
    groups = [{"params": list(net.parameters()), "peak": args.lr}]
    if args.learn_ranges > 0:
        groups.append({"params": [student.log_scales], "peak": args.learn_ranges})
    opt = torch.optim.Adam(groups, lr=args.lr)
    val = []
    for f in sorted(glob.glob(os.path.join(args.val, "*.exr"))) if args.val else []:
        fr = pl.read_frame(f)
        val.append(({"file": os.path.basename(f), "spp": int(fr["spp"])}, fr))

    last = os.path.join(args.out, "last.pt")
    step, elapsed = 0, 0.0
    if os.path.exists(last):
        ck = torch.load(last, map_location="cpu", weights_only=False)
        net.load_state_dict(ck["net"])
        if ck.get("log_scales") is not None:
            with torch.no_grad():
                student.log_scales.copy_(ck["log_scales"])
        opt.load_state_dict(ck["opt"])
        gen.set_state(ck["sampler_rng"])
        step, elapsed = ck["step"], ck["elapsed"]
        print(f"resumed from {last} at step {step}", flush=True)
    log = open(os.path.join(args.out, "log.jsonl"), "a")

    def record(rec):
        log.write(json.dumps(rec) + "\n")
        log.flush()
        print(json.dumps({k: v for k, v in rec.items() if k != "rows"}), flush=True)

    teacher_sha, start_sha = sha256_file(args.teacher), sha256_file(args.start)

    what = (f"against {len(names)} bundles' references (gdrecon_py.qat_ref), from the fp32 graph sha256 "
            f"{start_sha}" if args.fp32 else
            f"quantisation-aware (gdrecon_py.qat_ref) against {len(names)} bundles' references and the "
            f"fp32 graph, from an int8 graph (sha256 {start_sha})"
            + (f", pre-LeakyReLU negative ranges cut to {args.negative_fraction:g}"
               if args.negative_fraction != 1 else "")
            + (", its LeakyReLUs replaced by ReLUs (the ReLU graph)" if args.relu else "")
            + (", activation ranges learned (LSQ)" if args.learn_ranges > 0 else ""))

    def save():
        ck = {"net": net.state_dict(), "variant": "full", "precision": "fp32" if args.fp32 else "int8",
              "opt": opt.state_dict(), "sampler_rng": gen.get_state(), "step": step, "total": args.steps,
              "elapsed": elapsed, "args": vars(args),
              "model_sha256": teacher_sha, "start_sha256": start_sha, "frames": names, "device_name": "cpu",
              "fine_tuned": what}
        if not args.fp32:
            # the ranges simulated (`qat quantize` writes these into the graph) and the network
            # they are of
            ck["ranges"] = student.ranges()
            ck["activation"] = student.net.activation
            if student.log_scales is not None:
                ck["log_scales"] = student.log_scales.detach().clone()
        torch.save(ck, last + ".tmp")
        os.replace(last + ".tmp", last)

    if val and step == 0:
        record({"kind": "val", "step": 0, **validate(student, val)})
    student.train()
    t0, tot, n = time.time(), 0.0, 0
    while step < args.steps:
        lr = lr_at(step, args.steps, args.lr, args.warmup)
        for g in opt.param_groups:
            g["lr"] = lr_at(step, args.steps, g["peak"], args.warmup)
        loss = loss_of(student, teacher, sample(arr, gen, args.batch, args.patch, args.exposure),
                       args.dist, args.clip)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        tot, n = tot + float(loss.detach()), n + 1
        if step % 20 == 0:
            now = time.time()
            elapsed, t0 = elapsed + now - t0, now
            record({"kind": "train", "step": step, "loss": tot / n, "lr": lr, "elapsed": round(elapsed, 1)})
            tot, n = 0.0, 0
        if step % args.save_every == 0 or step == args.steps:
            elapsed, t0 = elapsed + time.time() - t0, time.time()
            save()
        if val and (step % args.val_every == 0 or step == args.steps):
            record({"kind": "val", "step": step, **validate(student, val)})
            t0 = time.time()
    log.close()


if __name__ == "__main__":
    main()
