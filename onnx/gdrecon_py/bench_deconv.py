"""Time the decoder forms of export.py (--deconv) against each other in ONNX Runtime, and profile
one of them per op type (docs/gradnet.md, "Decoder rewrite").

    source onnx/env.sh
    $GDRECON_PYTHON -m gdrecon_py.bench_deconv --ckpt $HOME/.cache/gdrecon/train_runs/full/last.pt

Exports every form of export.DECONV_FORMS from the checkpoint to a temporary directory (nothing
in the repository is written), then, with the settings of the Rust path (intra-op threads 2,
spinning off, inter-op threads 1, ORT_ENABLE_ALL, CPU arena on) on one random 1 x C x 720 x 1280
input: one warm-up run per session, then --runs rounds that run every form once each
(interleaved, so a load change on a shared machine hits all forms alike); the median per form.
Then each --profile form (default: the export default) in a new session with
SessionOptions.enable_profiling, 1 + --runs runs: the `*_kernel_time` events of the last run
summed per op type. Also prints max |output - output of the first form|.
"""
import argparse
import collections
import json
import os
import tempfile
import time

import numpy as np

from . import export as ex
from .runtime import session


def profile_by_op(path, feeds, runs, prefix):
    """{op type: ms} of the `*_kernel_time` events of the last of `runs` runs, and the run's ms."""
    s = session(path, profile_prefix=prefix)
    for _ in range(runs):
        s.run(None, feeds)
    prof = s.end_profiling()
    with open(prof) as f:
        ev = json.load(f)
    os.remove(prof)
    last = [e for e in ev if e.get("name") == "model_run"][-1]
    t0, t1 = last["ts"], last["ts"] + last["dur"]
    by_op = collections.defaultdict(float)
    for e in ev:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time") and t0 <= e["ts"] <= t1:
            by_op[e["args"]["op_name"]] += e["dur"] / 1e3
    return dict(by_op), last["dur"] / 1e3


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ckpt", required=True)
    ap.add_argument("--forms", default=",".join(reversed(ex.DECONV_FORMS)),
                    help="comma-separated export.DECONV_FORMS (default %(default)s)")
    ap.add_argument("--size", default="1280x720", help="W x H (default %(default)s)")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--profile", default=ex.DEFAULT_DECONV,
                    help="comma-separated forms to profile (default %(default)s; '' = none)")
    args = ap.parse_args(argv)
    import torch
    torch.set_num_threads(2)
    w, h = map(int, args.size.lower().split("x"))
    forms = args.forms.split(",")
    net, _ = ex.load_checkpoint(args.ckpt)
    rng = np.random.default_rng(0)
    feeds = {"data": rng.random((1, net.data_ch, h, w), dtype=np.float32),
             "grad": rng.random((1, 2, h, w), dtype=np.float32) - 0.5}
    with tempfile.TemporaryDirectory() as tmp:
        paths = {}
        for f in forms:
            paths[f] = os.path.join(tmp, f + ".onnx")
            ex.export_model(net, paths[f], deconv=f)
        sess = {f: session(p) for f, p in paths.items()}
        outs = {f: s.run(None, feeds)[0] for f, s in sess.items()}   # warm-up
        times = {f: [] for f in forms}
        for _ in range(args.runs):
            for f, s in sess.items():
                t = time.perf_counter()
                s.run(None, feeds)
                times[f].append(time.perf_counter() - t)
        del sess
        print(f"1 x {net.data_ch} x {h} x {w}, median of {args.runs} runs after 1 warm-up (interleaved):")
        for f in forms:
            diff = float(np.abs(outs[f] - outs[forms[0]]).max())
            print(f"  {f:14s} {np.median(times[f]) * 1e3:7.0f} ms   runs "
                  f"{' '.join(f'{t * 1e3:.0f}' for t in times[f])}   max |out - {forms[0]}| {diff:.1e}")
        for f in filter(None, args.profile.split(",")):
            by_op, run_ms = profile_by_op(paths[f], feeds, 1 + args.runs, os.path.join(tmp, "prof"))
            tot = sum(by_op.values())
            print(f"profile {f} (last of {1 + args.runs} runs): run {run_ms:.0f} ms, kernels {tot:.0f} ms")
            for k, v in sorted(by_op.items(), key=lambda kv: -kv[1]):
                print(f"  {k:16s} {v:7.1f} ms  {100 * v / tot:5.1f} %")


if __name__ == "__main__":
    main()
