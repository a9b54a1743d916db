"""The combiner's candidate reconstructions, computed by the gdrecon CLI and cached beside the
bundles (outside the repository), so training and evaluation read exactly what the library
computes.

For every bundle `<folder>/<stem>.exr` and every candidate below this writes
`<folder>/candidates/<stem>.<name>.exr` (RGB), skipping files that are current:

    prior    the prior: OIDN on the base image (`gdrecon reconstruct -m prior`)
    l1prior  screened Poisson L1 on the prior (`-m l1 --preset prior`), its IRLS stopped once a
             step moves the image by less than STEP_CHANGE (the combiner's `step_change`)
    l1weak   the same with a weak data term (`-p prior_alpha=0.5`), which follows the gradients
             further, multigrid-preconditioned (the preset's Jacobi is slow there)

Each names its preconditioner, as the combiner's candidates do (src/recon/combiner.rs,
`candidates`), so that a change of the preset's shows in the options below.

The options each candidate was computed with are kept in `<folder>/candidates/options.json`,
with the library's output rule (OUTPUT); a candidate whose options changed since, or every
candidate when the rule did, is computed again (a stale file would train or evaluate the
network on inputs the library no longer gives it).

  $GDRECON_PYTHON -m gdrecon_py.candidates ~/.cache/gdrecon/data/val [--gdrecon target/release/gdrecon]
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import subprocess
import time

# The combiner's `step_change` default (src/recon/combiner.rs, STEP_CHANGE). The shipped network
# was trained on candidates without it (every IRLS step run); with it they differ by under
# 0.3 % relMSE on every validation and test frame.
STEP_CHANGE = "0.001"

# What the library does to every output after its method (src/recon/mod.rs, `repair`); the
# candidates of a folder recorded under another rule are all computed again.
OUTPUT = "non-finite values replaced by the base colour, negative values by 0"

# The IRLS regularisation floor the shipped network was trained on (l1's default; the `prior`
# preset's is lower since the thirtieth session): src/recon/combiner.rs, `CANDIDATE_REG_FLOOR`.
REG_FLOOR = "0.01"

CANDIDATES = {
    "prior": ["-m", "prior"],
    "l1prior": ["-m", "l1", "--preset", "prior", "-p", f"step_change={STEP_CHANGE}",
                "-p", "preconditioner=jacobi", "-p", f"reg_floor={REG_FLOOR}"],
    "l1weak": ["-m", "l1", "--preset", "prior", "-p", "prior_alpha=0.5",
               "-p", f"step_change={STEP_CHANGE}", "-p", "preconditioner=multigrid",
               "-p", f"reg_floor={REG_FLOOR}"],
}


def path(folder, stem, name):
    return os.path.join(folder, "candidates", f"{stem}.{name}.exr")


def bundles(folder):
    return sorted(p for p in glob.glob(os.path.join(folder, "*.exr")))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folders", nargs="+")
    ap.add_argument("--gdrecon", default="target/release/gdrecon")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    t0 = time.time()
    n = 0
    for folder in args.folders:
        os.makedirs(os.path.join(folder, "candidates"), exist_ok=True)
        record = os.path.join(folder, "candidates", "options.json")
        try:
            with open(record) as f:
                done = json.load(f)
        except FileNotFoundError:
            done = {}
        if done.get("output") != OUTPUT:
            # Computed before the rule (negative values kept), or with no record at all.
            done = {}
        stale = {name for name, opts in CANDIDATES.items() if done.get(name) != opts}
        with open(record + ".tmp", "w") as f:
            json.dump({k: v for k, v in done.items() if k not in stale}, f, indent=1)
        os.replace(record + ".tmp", record)
        for bundle in bundles(folder):
            stem = os.path.splitext(os.path.basename(bundle))[0]
            for name, opts in CANDIDATES.items():
                out = path(folder, stem, name)
                if os.path.exists(out) and name not in stale:
                    continue
                tmp = out + ".tmp.exr"
                subprocess.run([args.gdrecon, "reconstruct", bundle, "-o", tmp, "-q",
                                "--threads", str(args.threads), *opts], check=True)
                os.replace(tmp, out)
                n += 1
        with open(record + ".tmp", "w") as f:
            json.dump({"output": OUTPUT, **CANDIDATES}, f, indent=1)
        os.replace(record + ".tmp", record)
    print(f"{n} candidates written in {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
