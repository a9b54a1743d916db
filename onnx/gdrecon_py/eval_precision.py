"""A reduced-precision GradNet graph against the fp32 one: speed at a frame size, and relMSE on
the validation and test splits (docs/gradnet.md, "Reduced precision").

    source onnx/env.sh
    $GDRECON_PYTHON -m gdrecon_py.eval_precision --time --rounds 5
    $GDRECON_PYTHON -m gdrecon_py.eval_precision --splits val,test --json /tmp/int8_eval.json

--time: one colour channel (1 x Cd x H x W) through each graph, the sessions of `runtime.session`
(the Rust path's settings, `--threads` intra-op threads), one warm-up run each, then `--rounds`
rounds running each graph once, interleaved; medians. The graph alone: a graph that ends before
its output convolution (the int8 graph, `output_layer.py`) is timed without it (about 10 ms of
a 1280 x 720 channel in the library; `gdrecon bench` times the whole method).
--splits: every bundle of each split through the whole reference pipeline (`pipeline.reconstruct`:
features, mu-law, padding, the graph, inverse mu-law, emitters, bias correction) with each graph;
relMSE against the bundle's reference (`metrics.relmse`), per frame, geometric means per spp and
over the split, and the largest per-frame change.
"""
import argparse
import glob
import json
import math
import os
import statistics
import time

import numpy as np

from . import ONNX_DIR, runtime
from . import pipeline as pl
from .metrics import relmse

DATA = os.path.expanduser("~/.cache/gdrecon/data")


def gmean(v):
    return math.exp(sum(math.log(x) for x in v) / len(v))


def time_models(models, width, height, rounds, threads, batch=1):
    sess = {k: runtime.session(p, threads) for k, p in models.items()}
    dch = next(iter(sess.values())).get_inputs()[0].shape[1]
    rng = np.random.default_rng(0)
    hp, wp = (height + 7) // 8 * 8, (width + 7) // 8 * 8
    feed = {"data": rng.random((batch, dch, hp, wp), dtype=np.float32),
            "grad": (rng.standard_normal((batch, 2, hp, wp)) * 0.1).astype(np.float32)}
    ts = {k: [] for k in sess}
    for s in sess.values():
        s.run(None, feed)
    for _ in range(rounds):
        for k, s in sess.items():
            t = time.perf_counter()
            s.run(None, feed)
            ts[k].append(time.perf_counter() - t)
    return ts


def evaluate(models, split_dir):
    runners = {k: pl.ort_runner(p) for k, p in models.items()}
    rows = []
    for f in sorted(glob.glob(os.path.join(split_dir, "*.exr"))):
        fr = pl.read_frame(f)
        if fr.get("reference") is None:
            continue
        name = os.path.basename(f)
        r = {"file": name, "spp": int(fr["spp"])}
        for k, run in runners.items():
            r[k] = relmse(pl.reconstruct(fr, run), fr["reference"])
        rows.append(r)
        print(json.dumps(r), flush=True)
    return rows


def summary(rows, keys):
    ref, others = keys[0], keys[1:]
    lines = []
    groups = [(f"{s} spp", [r for r in rows if r["spp"] == s]) for s in sorted({r["spp"] for r in rows})]
    groups.append(("all", rows))
    for label, sel in groups:
        g = {k: gmean([r[k] for r in sel]) for k in keys}
        parts = [f"{k} {g[k]:.5g}" + ("" if k == ref else f" ({100 * (g[k] / g[ref] - 1):+.2f} %)") for k in keys]
        lines.append(f"  {label:8s} ({len(sel)} frames): " + ", ".join(parts))
    for k in others:
        ch = [(100 * (r[k] / r[ref] - 1), r["file"]) for r in rows]
        lo, hi = min(ch), max(ch)
        lines.append(f"  {k} per frame vs {ref}: worst {hi[0]:+.2f} % ({hi[1]}), best {lo[0]:+.2f} % ({lo[1]})")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default=f"fp32={os.path.join(ONNX_DIR, 'gradnet.onnx')},"
                                        f"int8={os.path.join(ONNX_DIR, 'gradnet_int8_nhwc.onnx')}",
                    help="name=path,... (the first is the reference)")
    ap.add_argument("--time", action="store_true")
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--splits", default="", help="comma-separated: val, test (under --data)")
    ap.add_argument("--data", default=DATA)
    ap.add_argument("--json", help="write the per-frame rows here")
    args = ap.parse_args(argv)
    models = dict(kv.split("=", 1) for kv in args.models.split(","))
    keys = list(models)
    if args.time:
        w, h = (int(v) for v in args.size.lower().split("x"))
        ts = time_models(models, w, h, args.rounds, args.threads, args.batch)
        base = statistics.median(ts[keys[0]])
        for k in keys:
            m = statistics.median(ts[k])
            print(f"{k}: median {m * 1e3:.0f} ms per {args.batch} x channel at {w} x {h} "
                  f"({base / m:.2f}x {keys[0]}); runs " + " ".join(f"{t * 1e3:.0f}" for t in ts[k]), flush=True)
    out = {}
    for split in [s for s in args.splits.split(",") if s]:
        rows = evaluate(models, os.path.join(args.data, split))
        out[split] = rows
        print(f"{split}:\n" + summary(rows, keys), flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
