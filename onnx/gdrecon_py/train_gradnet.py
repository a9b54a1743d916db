"""GradNet training from packs (`gdrecon_py.pack`) on any torch device, sized for a lent GPU: the
whole training set lives on the device, crops are cut and augmented there, the network runs in
bf16 autocast, and the validation frames go through the inference pipeline after every epoch.

    $GDRECON_PYTHON -m gdrecon_py.pack train TRAIN.xz ~/.cache/gdrecon/data/train3 [--part 0/2]
    $GDRECON_PYTHON -m gdrecon_py.pack val   VAL.xz   ~/.cache/gdrecon/data/val
    python -m gdrecon_py.train_gradnet --train TRAIN.xz [TRAIN2.xz] --val VAL.xz --out RUN --device cuda \\
        --budget 420 --deadline 540 --export $OUT
    python -m gdrecon_py.train_gradnet --train TRAIN.xz --out RUN2 --init onnx/gradnet.onnx \\
        --epoch-offset 16 --lambda-cap 0.259 --g-warmup 1500 --schedule cosine --warmup-steps 300 --lr 1e-4 ...
    (a continuation of the shipped network: docs/gradnet.md, "Continuing the training")
    (re-run the same command to resume from RUN/last.pt; `--export` writes the weights in parts
    of under 16 MiB; `merge_parts` turns them back into a checkpoint for `gdrecon_py.export`)

Loss and schedule: those of `train.py` (the release's, Guo et al. 2019 Eq. 7): L_grad + alpha
L_data + lambda_F(epoch) L_1st, lambda_F keyed on the epoch as in the release, the G-branch
trained alone on L' after each epoch's main steps (`--g-steps` per `--steps`, the ratio train.py
used), Adam (0.9, 0.999), lr x0.95 every 2 epochs.

Differences from train.py, each named with why:
  * Batch `--batch` crops of `--patch`^2 (default 32 of 128^2, the release's batch size; the
    issue asks for crops of at least 128 px, GradNet's receptive field).
  * Steps per epoch: `--steps 0` measures this device's rate in a throw-away probe (its own
    model copy and random stream) and sizes the epochs so that `--epochs` of them take about
    `--budget` seconds. The chosen number is recorded in args.json; resuming reuses it.
  * Augmentation (the release has none; our training set has 240 views, the paper's 900):
    each crop gets one of the 8 rotations/mirrors of the square, with the gradients transformed
    exactly (a mirror along x turns dx(x) into -dx(W-2-x), the last column stays 0; a transpose
    swaps dx and dy), and an exposure scale 2^U(-e, e), `--exposure e` (default 2), on colour and
    gradients: GradNet is scale-dependent (docs/benchmarks.md "GradNet and HDR") and the
    validation and test sets hold emitters and dim rooms.
  * Features normalised as inference normalises them (albedo clamped to [0, 1]; train.py kept
    the release's +-1e5 clamp), by the pack.
  * bf16 autocast for the two networks on CUDA (`--bf16`, default on CUDA), losses in fp32; a
    step whose loss is not finite is skipped and counted (never seen is the hope, logged either
    way).
  * A continuation (`--init`, twenty-sixth session): the run starts from exported weights with a
    fresh optimiser (what came back from the device machine holds no Adam moments), trains the
    G-branch alone for `--g-warmup` steps (the export has none), keys lambda_F on
    epoch + `--epoch-offset` (the release's ramp carried on) and may decay the rate per step on
    a cosine (`--schedule cosine`, after `--warmup-steps`) instead of the release's step decay.
    `--snapshot-every E` exports the weights every E epochs as well, for choosing on validation
    elsewhere when the validation pack does not fit the call.
  * `--deadline` seconds after the start the run stops at the next step, saves, and exports:
    the device machine takes a command for at most 10 minutes.
"""
import argparse
import json
import math
import os
import shutil
import sys
import time

import numpy as np
import torch

from . import gradnet as gn
from . import pack
from .metrics import relmse
from .train import lambda_f, split_batch

G_RATIO = 25 / 80   # G-branch steps per main step, as train.py


# ------------------------------------------------------------------------------------------
# data on the device

class Crops:
    """The training pack on `device` (float16, N x 16 x H x W per frame size) and a sampler of
    augmented crops with its own seeded generator."""

    def __init__(self, arrays, device, seed):
        self.groups = [torch.from_numpy(a.astype(np.float16)).to(device) for a in arrays.values()]
        px = np.array([g.shape[0] * g.shape[2] * g.shape[3] for g in self.groups], np.float64)
        self.weights = torch.tensor(px / px.sum(), dtype=torch.float64)
        self.device = device
        self.gen = torch.Generator(device="cpu").manual_seed(seed)

    def frames(self):
        return sum(g.shape[0] for g in self.groups)

    def _int(self, hi, n):
        return torch.randint(0, hi, (n,), generator=self.gen)

    def sample(self, batch, patch, exposure, dihedral):
        gi = int(torch.multinomial(self.weights, 1, generator=self.gen))
        arr = self.groups[gi]
        n, _, H, W = arr.shape
        if H < patch or W < patch:
            raise SystemExit(f"frames of {W}x{H} are smaller than --patch {patch}")
        idx = self._int(n, batch)
        ys, xs = self._int(H - patch + 1, batch), self._int(W - patch + 1, batch)
        code = self._int(8 if dihedral else 1, batch)
        scale = torch.exp2((torch.rand(batch, generator=self.gen) * 2 - 1) * exposure)
        ar = torch.arange(patch)
        iy = (ys[:, None] + ar)[:, :, None].to(self.device)
        ix = (xs[:, None] + ar)[:, None, :].to(self.device)
        x = arr[idx.to(self.device)[:, None, None], :, iy, ix]          # B x P x P x 16
        x = x.permute(0, 3, 1, 2).float()
        x = dihedral_apply(x, code.to(self.device))
        x[:, :9] *= scale.to(self.device)[:, None, None, None]
        return x.contiguous()


def _mirror_x(x):
    """Mirror along x (dim 3) with exact gradients: dx'(x) = -dx(W-2-x), dx'(W-1) = 0."""
    x = x.flip(3)
    dx = x[:, 3:6]
    x[:, 3:6] = torch.cat([-dx[..., 1:], torch.zeros_like(dx[..., :1])], 3)
    return x


def _mirror_y(x):
    x = x.flip(2)
    dy = x[:, 6:9]
    x[:, 6:9] = torch.cat([-dy[..., 1:, :], torch.zeros_like(dy[..., :1, :])], 2)
    return x


def _transpose(x):
    x = x.transpose(2, 3)
    return torch.cat([x[:, 0:3], x[:, 6:9], x[:, 3:6], x[:, 9:]], 1)


def dihedral_apply(x, code):
    """Per crop: bit 0 transpose, bit 1 mirror x, bit 2 mirror y (square crops)."""
    out = x.clone()
    for bit, f in ((1, _transpose), (2, _mirror_x), (4, _mirror_y)):
        m = (code & bit) != 0
        if bool(m.any()):
            out[m] = f(out[m])
    return out


# ------------------------------------------------------------------------------------------
# validation through the inference pipeline

def validate(net, frames, device):
    from . import pipeline as pl
    net.eval()
    run = pl.torch_runner(net, device)
    rows = []
    for meta, fr in frames:
        out = pl.reconstruct(fr, run)
        rows.append({"file": meta["file"], "spp": meta["spp"], "relmse": relmse(out, fr["reference"])})
    net.train()
    by_spp = {}
    for r in rows:
        by_spp.setdefault(r["spp"], []).append(math.log(r["relmse"]))
    geo = {str(s): math.exp(sum(v) / len(v)) for s, v in sorted(by_spp.items())}
    score = math.exp(sum(math.log(r["relmse"]) for r in rows) / len(rows))
    return score, geo, rows


# ------------------------------------------------------------------------------------------
# checkpoints

def save_parts(state, prefix, limit=15 * 2**20):
    """Write `state` (a checkpoint dict whose 'net' is a state dict) as prefix-0.pt, prefix-1.pt ...,
    each under `limit` bytes of tensors: the device machine returns files of at most 16 MiB."""
    parts, cur, size = [], {}, 0
    for k, v in state["net"].items():
        n = v.numel() * v.element_size()
        if cur and size + n > limit:
            parts.append(cur)
            cur, size = {}, 0
        cur[k] = v.detach().cpu()
        size += n
    parts.append(cur)
    rest = {k: v for k, v in state.items() if k not in ("net", "opt", "gopt")}
    paths = []
    for i, p in enumerate(parts):
        path = f"{prefix}-{i}.pt"
        torch.save({"part": i, "of": len(parts), "net": p, **(rest if i == len(parts) - 1 else {})}, path)
        paths.append(path)
    return paths


def merge_parts(prefix):
    """prefix-0.pt ... -> one checkpoint dict with 'net' whole (for gdrecon_py.export)."""
    first = torch.load(f"{prefix}-0.pt", map_location="cpu", weights_only=False)
    net, out = {}, {}
    for i in range(first["of"]):
        p = torch.load(f"{prefix}-{i}.pt", map_location="cpu", weights_only=False)
        net.update(p["net"])
        out.update({k: v for k, v in p.items() if k not in ("net", "part", "of")})
    out["net"] = net
    return out


# ------------------------------------------------------------------------------------------

def build(args, device):
    feats = args.variant == "full"
    net = gn.GradNet() if feats else gn.GradNetNoFeat()
    with torch.no_grad():
        net.out.bias.fill_(args.out_bias)
    gbr = gn.GBranch() if feats else None
    net.to(device, memory_format=torch.channels_last)
    if gbr is not None:
        gbr.to(device, memory_format=torch.channels_last)
    opt = torch.optim.Adam(net.parameters(), lr=args.lr, betas=(0.9, 0.999))
    if args.schedule == "cosine":
        sch = torch.optim.lr_scheduler.LambdaLR(opt, cosine(args.warmup_steps, args.epochs * args.steps))
    else:
        sch = torch.optim.lr_scheduler.StepLR(opt, step_size=2, gamma=0.95)
    gopt = gsch = None
    if gbr is not None:
        gopt = torch.optim.Adam(gbr.parameters(), lr=args.lr, betas=(0.9, 0.999))
        gsch = torch.optim.lr_scheduler.StepLR(gopt, step_size=2, gamma=0.95)
    return net, gbr, opt, sch, gopt, gsch


def cosine(warmup, total, floor=0.01):
    """Per main step: linear warm-up over `warmup` steps, then a cosine from 1 to `floor` at
    `total` (learning-rate factors, for LambdaLR)."""
    total = max(total, 1)

    def f(t):
        ramp = min(1.0, (t + 1) / warmup) if warmup > 0 else 1.0
        u = min(t, total) / total
        return ramp * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * u)))
    return f


def init_state(path):
    """Starting weights for a continuation: an exported graph (`.onnx`, through
    `export.net_from_onnx`) or a `.pt` state dict (a checkpoint's 'net', or the dict itself;
    float16 allowed, which halves what the device call carries), as float32."""
    if path.endswith(".onnx"):
        from .export import net_from_onnx
        sd = net_from_onnx(path).state_dict()
    else:
        sd = torch.load(path, map_location="cpu", weights_only=False)
        sd = sd.get("net", sd)
    return {k: v.float() if v.is_floating_point() else v for k, v in sd.items()}


class Stepper:
    """One main or G step on a batch; autocast on the device where asked."""

    def __init__(self, args, device, net, gbr, opt, gopt):
        self.a, self.dev, self.net, self.gbr, self.opt, self.gopt = args, device, net, gbr, opt, gopt
        self.amp = torch.autocast(device.type, dtype=torch.bfloat16, enabled=args.bf16)
        self.skipped = 0

    def _cl(self, t):
        return t.contiguous(memory_format=torch.channels_last)

    def main(self, x, lam):
        data, grad, lin, dxc, dyc, featc = split_batch(x)
        if self.gbr is None:
            data = data[:, :1]
        data, grad = self._cl(data), self._cl(grad)
        with self.amp:
            y = self.net(data, grad)
            G = None
            if self.gbr is not None:
                with torch.no_grad():
                    G = self.gbr(data, grad)
        y = y.float()
        lg = gn.loss_grad(y, dxc, dyc)
        ld = gn.loss_data(y, lin)
        total = lg + self.a.alpha * ld
        l1 = torch.zeros((), device=self.dev)
        if G is not None:
            l1 = gn.loss_first_order(y, featc, G.float(), lin)
            if lam > 0:
                total = total + lam * l1
        vals = torch.stack([lg, ld, l1, total]).detach().cpu().tolist()
        if not math.isfinite(vals[3]):
            self.skipped += 1
            return None
        self.opt.zero_grad(set_to_none=True)
        total.backward()
        self.opt.step()
        return dict(zip(("grad", "data", "first", "total"), vals))

    def g(self, x):
        data, grad, lin, _, _, featc = split_batch(x)
        data, grad = self._cl(data), self._cl(grad)
        with self.amp:
            G = self.gbr(data, grad)
        lp = gn.loss_first_order(data[:, :1].float(), featc, G.float(), lin)
        v = float(lp.detach())
        if not math.isfinite(v):
            self.skipped += 1
            return None
        self.gopt.zero_grad(set_to_none=True)
        lp.backward()
        self.gopt.step()
        return v


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def probe(args, device, crops_arrays, seconds):
    """Main + G steps per second on a throw-away model and stream (the run's RNG is untouched)."""
    net, gbr, opt, _, gopt, _ = build(args, device)
    st = Stepper(args, device, net, gbr, opt, gopt)
    crops = Crops(crops_arrays, device, seed=args.seed + 7919)
    t_end, n, t0 = None, 0, time.time()
    while True:
        x = crops.sample(args.batch, args.patch, args.exposure, args.dihedral)
        st.main(x, 0.1)
        if gbr is not None and n % 3 == 0:
            st.g(x)
        n += 1
        sync(device)
        if n == 3:                       # after cudnn's autotuning and the first allocations
            t0, n0 = time.time(), n
        if n > 3 and time.time() - t0 > seconds:
            t_end = time.time()
            break
    main_steps = n - n0
    per_main = (t_end - t0) / main_steps   # a G step after every third main step included
    del net, gbr, opt, gopt, st
    if device.type == "cuda":
        torch.cuda.empty_cache()
    return per_main, main_steps


def main(argv=None):
    t_start = time.time()
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--train", required=True, nargs="+", help="training packs (gdrecon_py.pack train)")
    ap.add_argument("--val", default="", help="validation pack; checkpoints are chosen on it")
    ap.add_argument("--out", required=True, help="run folder (outside the repository)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--variant", choices=["full", "nofeat"], default="full")
    ap.add_argument("--epochs", type=int, default=16)
    ap.add_argument("--steps", type=int, default=0, help="main steps per epoch; 0: sized by the probe")
    ap.add_argument("--budget", type=float, default=420.0, help="seconds of steps, with --steps 0")
    ap.add_argument("--probe-seconds", type=float, default=15.0)
    ap.add_argument("--deadline", type=float, default=0.0, help="stop this many seconds after the start")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--patch", type=int, default=128)
    ap.add_argument("--lr", type=float, default=4e-4)
    ap.add_argument("--alpha", type=float, default=1.0)
    ap.add_argument("--out-bias", type=float, default=0.4)
    ap.add_argument("--exposure", type=float, default=2.0, help="log2 range of the exposure scale")
    ap.add_argument("--no-dihedral", dest="dihedral", action="store_false")
    ap.add_argument("--bf16", type=int, default=-1, help="1/0; default: on for CUDA")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--log-every", type=int, default=10)
    ap.add_argument("--init", default="", help="a continuation: start from these weights (.onnx or .pt)")
    ap.add_argument("--epoch-offset", type=int, default=0,
                    help="lambda_F as if this many epochs came before (the run --init continues)")
    ap.add_argument("--lambda-cap", type=float, default=math.inf, help="hold lambda_F at most at this")
    ap.add_argument("--g-warmup", type=int, default=0, help="G-branch steps before the first epoch")
    ap.add_argument("--schedule", choices=["step", "cosine"], default="step",
                    help="step: lr x0.95 every 2 epochs (the release's); cosine: per main step, to 1 %%")
    ap.add_argument("--warmup-steps", type=int, default=0, help="linear lr warm-up (cosine schedule)")
    ap.add_argument("--snapshot-every", type=int, default=0,
                    help="with --export, also export the weights after every this many epochs (snapE-*.pt)")
    ap.add_argument("--export", default="", help="folder for best-*.pt / last-*.pt parts and the log")
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    args.bf16 = bool(args.bf16 if args.bf16 >= 0 else device.type == "cuda")
    torch.set_num_threads(args.threads)
    torch.backends.cudnn.benchmark = True
    os.makedirs(args.out, exist_ok=True)

    tarr = pack.read_train(args.train)
    vframes = []
    if args.val:
        vmeta, varr = pack.read(args.val)
        vframes = pack.val_frames(varr, vmeta)
    print(f"data: {sum(a.shape[0] for a in tarr.values())} training frames "
          f"({', '.join(f'{k}: {a.shape[0]}' for k, a in tarr.items())}), {len(vframes)} validation frames, "
          f"{time.time() - t_start:.1f} s", flush=True)

    last = os.path.join(args.out, "last.pt")
    resume = os.path.exists(last)
    run_json = os.path.join(args.out, "args.json")
    if resume and os.path.exists(run_json):
        with open(run_json) as f:
            args.steps = json.load(f)["steps"]
    probe_info = None
    if args.steps <= 0:
        per_main, pm = probe(args, device, tarr, args.probe_seconds)
        args.steps = max(1, int(args.budget / (per_main * args.epochs)))
        probe_info = {"seconds_per_main_step": per_main, "main_steps": pm}
        print(f"probe: {per_main * 1e3:.1f} ms per main step (G steps included at {G_RATIO:.3f}); "
              f"{args.steps} steps per epoch", flush=True)
    g_steps = round(args.steps * G_RATIO) if args.variant == "full" else 0
    if not resume:
        with open(run_json, "w") as f:
            json.dump(vars(args) | {"argv": sys.argv, "probe": probe_info, "g_steps": g_steps,
                                    "device_name": torch.cuda.get_device_name(0) if device.type == "cuda" else "cpu",
                                    "torch": torch.__version__}, f, indent=1)

    torch.manual_seed(args.seed)
    net, gbr, opt, sch, gopt, gsch = build(args, device)
    crops = Crops(tarr, device, seed=args.seed)
    start_epoch, elapsed, best = 0, 0.0, None
    if resume:
        ck = torch.load(last, map_location=device, weights_only=False)
        net.load_state_dict(ck["net"]); opt.load_state_dict(ck["opt"]); sch.load_state_dict(ck["sch"])
        if gbr is not None:
            gbr.load_state_dict(ck["gbr"]); gopt.load_state_dict(ck["gopt"]); gsch.load_state_dict(ck["gsch"])
        crops.gen.set_state(ck["sampler_rng"])
        torch.set_rng_state(ck["torch_rng"])
        start_epoch, elapsed, best = ck["epoch"] + 1, ck["elapsed"], ck.get("best")
        print(f"resumed from {last} at epoch {start_epoch}", flush=True)
    st = Stepper(args, device, net, gbr, opt, gopt)
    log = open(os.path.join(args.out, "log.jsonl"), "a")
    if not resume and args.init:
        net.load_state_dict(init_state(args.init))
        print(f"started from {args.init}", flush=True)

    def past_deadline():
        return args.deadline > 0 and time.time() - t_start > args.deadline

    def g_run(n):
        """Up to `n` G-branch steps (fewer past the deadline): (sum of L', steps counted,
        stopped)."""
        gsum, n_g = 0.0, 0
        for _ in range(n):
            if past_deadline():
                return gsum, n_g, True
            v = st.g(crops.sample(args.batch, args.patch, args.exposure, args.dihedral))
            if v is not None:
                gsum += v
                n_g += 1
        return gsum, n_g, False

    if not resume and gbr is not None and args.g_warmup > 0:
        # The exported graph holds the network alone: a continuation's G-branch starts afresh
        # and must predict something before L_1st may lean on it.
        tg = time.time()
        gsum, n_g, _ = g_run(args.g_warmup)
        sync(device)
        rec = {"kind": "g_warmup", "g_steps": n_g, "lprime": gsum / max(n_g, 1),
               "seconds": time.time() - tg}
        log.write(json.dumps(rec) + "\n")
        print(json.dumps(rec), flush=True)

    stopped = False
    epoch = start_epoch - 1
    for epoch in range(start_epoch, args.epochs):
        t0 = time.time()
        lam = min(lambda_f(epoch + args.epoch_offset), args.lambda_cap) if gbr is not None else 0.0
        sums, n_main = {"grad": 0.0, "data": 0.0, "first": 0.0, "total": 0.0}, 0
        for step in range(args.steps):
            if past_deadline():
                stopped = True
                break
            lr = opt.param_groups[0]["lr"]
            rec = st.main(crops.sample(args.batch, args.patch, args.exposure, args.dihedral), lam)
            if rec is None:
                continue
            n_main += 1
            if args.schedule == "cosine":
                sch.step()
            for k in sums:
                sums[k] += rec[k]
            if step % args.log_every == 0:
                log.write(json.dumps({"epoch": epoch, "step": step, "kind": "main", "lambda": lam,
                                      "lr": lr, **rec}) + "\n")
        gsum, n_g = 0.0, 0
        if gbr is not None and not stopped:
            gsum, n_g, stopped = g_run(g_steps)
            gsch.step()
        if args.schedule == "step":
            sch.step()
        sync(device)
        dt = time.time() - t0
        elapsed += dt
        summ = {"epoch": epoch, "kind": "epoch", "seconds": dt, "elapsed": elapsed, "lambda": lam,
                "main_steps": n_main, "g_steps": n_g, "skipped": st.skipped, "complete": not stopped,
                **{k: v / max(n_main, 1) for k, v in sums.items()},
                "lprime": gsum / max(n_g, 1) if gbr is not None else None}
        if vframes:
            tv = time.time()
            score, geo, rows = validate(net, vframes, device)
            summ.update(val=score, val_by_spp=geo, val_seconds=time.time() - tv)
            log.write(json.dumps({"epoch": epoch, "kind": "val", "rows": rows}) + "\n")
            if best is None or score < best["val"]:
                best = {"epoch": epoch, "val": score, "val_by_spp": geo}
                torch.save({"net": net.state_dict(), "gbr": gbr.state_dict() if gbr is not None else None,
                            "epoch": epoch, "elapsed": elapsed, "variant": args.variant, "args": vars(args),
                            "val": score, "val_by_spp": geo}, os.path.join(args.out, "best.pt"))
        summ["best_epoch"] = best["epoch"] if best else None
        log.write(json.dumps(summ) + "\n")
        log.flush()
        print(json.dumps(summ), flush=True)
        ck = {"net": net.state_dict(), "opt": opt.state_dict(), "sch": sch.state_dict(),
              "sampler_rng": crops.gen.get_state(), "torch_rng": torch.get_rng_state(),
              "epoch": epoch, "elapsed": elapsed, "variant": args.variant, "args": vars(args),
              "best": best, "complete": not stopped}
        if gbr is not None:
            ck.update(gbr=gbr.state_dict(), gopt=gopt.state_dict(), gsch=gsch.state_dict())
        torch.save(ck, last + ".tmp")
        os.replace(last + ".tmp", last)
        if args.export and args.snapshot_every > 0 and (epoch + 1) % args.snapshot_every == 0 \
                and epoch + 1 < args.epochs and not stopped:
            os.makedirs(args.export, exist_ok=True)
            save_parts({"net": net.state_dict(), "epoch": epoch, "elapsed": elapsed, "variant": args.variant},
                       os.path.join(args.export, f"snap{epoch}"))
        if stopped:
            break
    log.close()
    print(f"trained {elapsed:.0f} s; {'stopped at the deadline in' if stopped else 'ended after'} "
          f"epoch {epoch}; best epoch {best['epoch'] if best else None}; skipped steps {st.skipped}", flush=True)
    if args.export:
        os.makedirs(args.export, exist_ok=True)
        ck = torch.load(last, map_location="cpu", weights_only=False)
        save_parts({k: ck[k] for k in ("net", "gbr", "epoch", "elapsed", "variant", "args", "best", "complete")
                    if k in ck}, os.path.join(args.export, "last"))
        bp = os.path.join(args.out, "best.pt")
        if os.path.exists(bp) and best and best["epoch"] != ck["epoch"]:
            save_parts(torch.load(bp, map_location="cpu", weights_only=False), os.path.join(args.export, "best"))
        for name in ("log.jsonl", "args.json"):
            shutil.copyfile(os.path.join(args.out, name), os.path.join(args.export, name))
        print(f"exported to {args.export} ({time.time() - t_start:.0f} s after the start)", flush=True)


if __name__ == "__main__":
    main()
