"""Supervised training of the combiner (combiner.py) on the training split, relMSE against the
bundles' reference layer; checkpoints outside the repository, resumable bit for bit.

  $GDRECON_PYTHON -m gdrecon_py.train_combiner --out $HOME/.cache/gdrecon/train_runs/combiner
      [--data ~/.cache/gdrecon/data/train2] [--val ~/.cache/gdrecon/data/val] [--steps 4000]

Data: every bundle in --data with a reference layer, and its candidates (`python -m
gdrecon_py.candidates <folder>` writes them with the library itself). The training split is
`bash onnx/data/make_sets.sh train` (perturbations of the training families only;
docs/data.md). Validation (--val) is read every --eval-every steps, each frame run as the
library runs it (`combiner.combine`: the mean guard included), and the checkpoint with the
lowest geometric-mean relMSE ratio to the prior there is kept as `best.pt` (every evaluated
step's weights as `step_NNNNNN.pt`, with the worst frame's ratio in the log); the test split is
never read here. `--reevaluate` redoes the validation entries of a finished run (how the
twenty-first session's run, trained before the guard existed, was evaluated with it).

Each step: --batch random --patch x --patch crops (seeded), each scaled by a random exposure
2^U(-2, 2) (radiance layers times k, variance times k^2), so that the network sees radiance
levels beyond the training scenes'. No flips or rotations: they would change the gradients'
forward-difference convention. Adam, lr --lr with a cosine decay to 5 % over --steps.

Resume: rerunning the same command continues from `last.pt` (model, optimiser, step, the
numpy and torch generator states), so an interrupted run ends where an uninterrupted one would.
"""
from __future__ import annotations

import argparse
import glob
import json
import math
import os
import sys
import time

import numpy as np
import torch

from .combiner import CANDIDATES, LAYERS, Combiner, reference, relmse_loss
from .candidates import path as candidate_path


def load_frame(bundle):
    """(27 x H x W raw inputs, 3 x H x W reference or None) as float32, in combiner.INPUTS order."""
    from .data.render import read_bundle
    layers, _ = read_bundle(bundle)
    folder = os.path.dirname(bundle)
    stem = os.path.splitext(os.path.basename(bundle))[0]
    planes = []
    for name in CANDIDATES:
        if name == "color":
            planes.append(layers["color"])
        else:
            cand, _ = read_bundle(candidate_path(folder, stem, name))
            planes.append(cand[""])
    for name in LAYERS:
        planes.append(layers[name])
    x = np.concatenate(planes, -1).transpose(2, 0, 1)
    x = np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
    ref = layers.get("reference")
    return np.ascontiguousarray(x), None if ref is None else np.ascontiguousarray(ref.transpose(2, 0, 1))


def load_set(folder):
    files = sorted(glob.glob(os.path.join(folder, "*_*spp.exr")))
    frames = []
    for f in files:
        x, ref = load_frame(f)
        if ref is not None:
            frames.append((os.path.basename(f)[:-4], x, ref))
    return frames


def exposure(x, ref, k):
    """Scales radiance layers by k and the variance by k^2 (the first 12 + last 6 channels are
    radiance or its differences, channels 12-14 variance, 15-20 albedo and normal)."""
    x = x.copy()
    x[:12] *= k
    x[12:15] *= k * k
    x[21:27] *= k
    return x, ref * k


def sample(frames, rng, batch, patch):
    xs, rs = [], []
    for _ in range(batch):
        _, x, ref = frames[rng.integers(len(frames))]
        h, w = ref.shape[1:]
        y0 = int(rng.integers(0, h - patch + 1))
        x0 = int(rng.integers(0, w - patch + 1))
        k = float(2.0 ** rng.uniform(-2, 2))
        xc, rc = exposure(x[:, y0:y0 + patch, x0:x0 + patch], ref[:, y0:y0 + patch, x0:x0 + patch], k)
        xs.append(xc)
        rs.append(rc)
    return torch.from_numpy(np.stack(xs)), torch.from_numpy(np.stack(rs))


def evaluate(model, frames):
    """{stem: (relMSE combiner, relMSE prior)} over whole frames."""
    res = {}
    model.eval()
    for stem, x, ref in frames:
        out = reference(x, model)  # as the library runs it, the mean guard included
        r = torch.from_numpy(ref)
        res[stem] = (float(relmse_loss(torch.from_numpy(out), r)), float(relmse_loss(torch.from_numpy(x[:3]), r)))
    model.train()
    return res


def geo_ratio(res):
    return math.exp(np.mean([math.log(a / b) for a, b in res.values()]))


def validation(model, val):
    """A log entry's validation fields: the geometric-mean ratio to the prior (all frames and
    per spp) and the worst frame's."""
    res = evaluate(model, val)
    worst = max(res, key=lambda k: res[k][0] / res[k][1])
    entry = {"val_vs_prior": geo_ratio(res), "val_worst": [worst, res[worst][0] / res[worst][1]]}
    for spp in (4, 16, 64):
        sub = {k: v for k, v in res.items() if k.endswith(f"_{spp}spp")}
        if sub:
            entry[f"val_vs_prior_{spp}"] = geo_ratio(sub)
    return entry


def reevaluate(model, val, out, last):
    """--reevaluate: every logged step's weights (step_NNNNNN.pt) through `validation` again;
    the log in `last` and log.json get the new validation fields, `best.pt` the new best."""
    ck = torch.load(last, weights_only=False)
    best = float("inf")
    for entry in ck["log"]:
        model.load_state_dict(torch.load(os.path.join(out, f"step_{entry['step']:06d}.pt")))
        model.eval()
        entry.update(validation(model, val))
        if entry["val_vs_prior"] < best:
            best = entry["val_vs_prior"]
            torch.save(model.state_dict(), os.path.join(out, "best.pt"))
        print(json.dumps(entry), flush=True)
    ck["best"] = best
    torch.save(ck, last + ".tmp")
    os.replace(last + ".tmp", last)
    if os.path.exists(os.path.join(out, "log.json")):
        with open(os.path.join(out, "log.json"), "w") as f:
            json.dump(ck["log"], f, indent=1)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=os.path.expanduser("~/.cache/gdrecon/data/train2"),
                    help="training folder, or several separated by commas (their frames pooled)")
    ap.add_argument("--val", default=os.path.expanduser("~/.cache/gdrecon/data/val"))
    ap.add_argument("--out", required=True)
    ap.add_argument("--steps", type=int, default=4000)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--patch", type=int, default=96)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--eval-every", type=int, default=500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--taps", type=int, default=1, choices=(1, 3), help="combiner.Combiner's taps")
    ap.add_argument("--hinge", type=float, default=0.0,
                    help="weight of each crop's excess relMSE over the prior's (0: relMSE alone)")
    ap.add_argument("--width", type=int, default=32, help="combiner.Combiner's width")
    ap.add_argument("--mixed", type=int, default=4, choices=(3, 4),
                    help="candidates mixed: the first 3 (prior, l1prior, l1weak) or all 4 (and the base image)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reevaluate", action="store_true",
                    help="evaluate every saved step of the run in --out on --val again, as the library "
                         "runs the network now (e.g. with a mean guard added after training), and "
                         "replace the validation entries of its log (last.pt, log.json); no training")
    ap.add_argument("--stop-at", type=int, default=None,
                    help="end this invocation at this step (after its checkpoint); rerun to resume")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    os.makedirs(args.out, exist_ok=True)
    t0 = time.time()
    train = [f for folder in args.data.split(",") for f in load_set(folder)]
    val = load_set(args.val) if args.val else []
    print(f"{len(train)} training frames, {len(val)} validation frames, loaded in {time.time() - t0:.0f} s", flush=True)
    if not train:
        sys.exit(f"no bundles with a reference layer in {args.data}")

    torch.manual_seed(args.seed)
    model = Combiner(width=args.width, taps=args.taps, mixed=args.mixed)
    opt = torch.optim.Adam(model.parameters(), lr=args.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(s, args.steps) / args.steps)))
    rng = np.random.default_rng(args.seed)
    step, best, log = 0, float("inf"), []
    last = os.path.join(args.out, "last.pt")
    if os.path.exists(last):
        ck = torch.load(last, weights_only=False)
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["opt"])
        sched.load_state_dict(ck["sched"])
        rng.bit_generator.state = ck["rng"]
        torch.set_rng_state(ck["torch_rng"])
        step, best, log = ck["step"], ck["best"], ck["log"]
        print(f"resumed at step {step}", flush=True)

    if args.reevaluate:
        reevaluate(model, val, args.out, last)
        return

    running, t_train = [], time.time()
    while step < min(args.steps, args.stop_at or args.steps):
        x, ref = sample(train, rng, args.batch, args.patch)
        out = model(x)
        loss = relmse_loss(out, ref)
        if args.hinge > 0:
            # Each crop's excess over the prior's error, added with weight --hinge: losing to the
            # prior anywhere costs more than winning elsewhere gains.
            per = lambda img: ((img - ref) ** 2 / (ref ** 2 + 0.01)).mean((1, 2, 3))
            loss = loss + args.hinge * torch.relu(per(out) - per(x[:, :3])).mean()
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        step += 1
        running.append(loss.item())
        if step % args.eval_every == 0 or step == args.steps:
            entry = {"step": step, "train_loss": float(np.mean(running)), "seconds": time.time() - t_train}
            running = []
            if val:
                entry.update(validation(model, val))
                if entry["val_vs_prior"] < best:
                    best = entry["val_vs_prior"]
                    torch.save(model.state_dict(), os.path.join(args.out, "best.pt"))
            log.append(entry)
            torch.save(model.state_dict(), os.path.join(args.out, f"step_{step:06d}.pt"))
            print(json.dumps(entry), flush=True)
            torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
                        "rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state(),
                        "step": step, "best": best, "log": log, "args": vars(args)}, last + ".tmp")
            os.replace(last + ".tmp", last)
    if step < args.steps:
        print(f"stopped at step {step} (--stop-at); rerun to resume")
        return
    with open(os.path.join(args.out, "log.json"), "w") as f:
        json.dump(log, f, indent=1)
    print(f"done: {time.time() - t_train:.0f} s of training, best validation ratio to the prior {best:.4f}")


if __name__ == "__main__":
    main()
