"""relMSE of GradNet on the validation set, next to the noisy base and the CLI's L2 / L1.

    source onnx/env.sh
    target/release/gdrecon bench ~/.cache/gdrecon/data/val/*.exr --methods l2,l1 --runs 1 \
        --warmup 0 --csv /tmp/val_l2l1.csv
    $GDRECON_PYTHON -m gdrecon_py.evaluate_gradnet --cli-csv /tmp/val_l2l1.csv \
        --md docs/gradnet_eval.md

GradNet runs through the exported ONNX graph (onnxruntime) and the reference pipeline of
gdrecon_py/pipeline.py (feature normalisation, mu-law, pad to x8, run, crop, inverse mu-law,
Gaussian bias correction). Also reports GradNet without the bias correction, and the no-feature
model when onnx/gradnet_nofeat.onnx exists. relMSE = mean((I - R)^2 / (R^2 + 0.01))
(gdrecon_py.metrics, docs/CONVENTIONS.md).
"""
import argparse
import csv
import glob
import json
import math
import os
import time

from . import ONNX_DIR
from . import pipeline as pl
from .metrics import relmse

SCENES = ["cornell", "metals", "glass", "textures", "indirect", "sunsky"]
SPPS = [4, 16, 64]


def read_cli_csv(path):
    """gdrecon bench --csv -> {(file basename, method): relmse}."""
    out = {}
    with open(path) as f:
        for row in csv.DictReader(f):
            keys = {k.lower(): v for k, v in row.items()}
            fname = os.path.basename(keys.get("frame") or keys.get("file") or keys.get("input") or "")
            meth = keys.get("method", "")
            val = keys.get("relmse") or keys.get("rel_mse")
            if fname and meth and val not in (None, ""):
                out[(fname, meth)] = float(val)
    return out


def gmean(v):
    v = [x for x in v if x is not None]
    return math.exp(sum(math.log(x) for x in v) / len(v)) if v else None


def fmt(x):
    return "" if x is None else f"{x:.5g}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--val", default=os.path.expanduser("~/.cache/gdrecon/data/val"))
    ap.add_argument("--cli-csv", help="gdrecon bench --csv output with l2 and l1 rows")
    ap.add_argument("--model", default=os.path.join(ONNX_DIR, "gradnet.onnx"))
    ap.add_argument("--nofeat", default=os.path.join(ONNX_DIR, "gradnet_nofeat.onnx"))
    ap.add_argument("--md", help="write the markdown table here")
    ap.add_argument("--json", help="write raw numbers here")
    args = ap.parse_args(argv)

    cli = read_cli_csv(args.cli_csv) if args.cli_csv else {}
    run_full = pl.ort_runner(args.model)
    run_nf = pl.ort_runner(args.nofeat) if os.path.exists(args.nofeat) else None
    rows = []
    t0 = time.time()
    for scene in SCENES:
        for spp in SPPS:
            f = os.path.join(args.val, f"{scene}_{spp}spp.exr")
            if not os.path.exists(f):
                continue
            fr = pl.read_frame(f)
            ref = fr["reference"]
            raw = pl.reconstruct(fr, run_full, use_features=True, correct_bias=False)
            corr = pl.bias_correct(raw, pl.sanitize(fr)["color"])
            r = {"scene": scene, "spp": spp, "file": os.path.basename(f),
                 "base": relmse(pl.sanitize(fr)["color"], ref),
                 "l2": cli.get((os.path.basename(f), "l2")), "l1": cli.get((os.path.basename(f), "l1")),
                 "gradnet": relmse(corr, ref), "gradnet_nobias": relmse(raw, ref)}
            if run_nf:
                r["gradnet_nofeat"] = relmse(pl.reconstruct(fr, run_nf, use_features=False), ref)
            rows.append(r)
            print(json.dumps(r), flush=True)
    print(f"evaluated {len(rows)} frames in {time.time() - t0:.1f} s", flush=True)

    cols = ["base", "l2", "l1", "gradnet", "gradnet_nobias"] + (["gradnet_nofeat"] if run_nf else [])
    head = {"base": "base", "l2": "L2", "l1": "L1", "gradnet": "GradNet",
            "gradnet_nobias": "GradNet, no bias corr.", "gradnet_nofeat": "GradNet no-feat"}
    lines = ["| scene | spp | " + " | ".join(head[c] for c in cols) + " | GradNet / L1 |",
             "|---|---|" + "---|" * (len(cols) + 1)]
    for r in rows:
        ratio = r["gradnet"] / r["l1"] if r.get("l1") else None
        lines.append(f"| {r['scene']} | {r['spp']} | " + " | ".join(fmt(r.get(c)) for c in cols)
                     + f" | {fmt(ratio)} |")
    lines += ["", "Geometric means over the six scenes:", "",
              "| spp | " + " | ".join(head[c] for c in cols) + " | GradNet / L1 |",
              "|---|" + "---|" * (len(cols) + 1)]
    for spp in SPPS:
        sel = [r for r in rows if r["spp"] == spp]
        g = {c: gmean([r.get(c) for r in sel]) if all(r.get(c) for r in sel) else None for c in cols}
        ratio = g["gradnet"] / g["l1"] if g.get("l1") else None
        lines.append(f"| {spp} | " + " | ".join(fmt(g[c]) for c in cols) + f" | {fmt(ratio)} |")
    table = "\n".join(lines)
    print(table)
    if args.md:
        with open(args.md, "w") as f:
            f.write(table + "\n")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
