"""The combiner's candidate reconstructions, computed by the gdrecon CLI and cached beside the
bundles (outside the repository), so training and evaluation read exactly what the library
computes.

For every bundle `<folder>/<stem>.exr` and every candidate below this writes
`<folder>/candidates/<stem>.<name>.exr` (RGB), skipping files that exist:

    prior    the prior: OIDN on the base image (`gdrecon reconstruct -m prior`)
    l1prior  screened Poisson L1 on the prior (`-m l1 --preset prior`)
    l1weak   the same with a weak data term (`-p prior_alpha=0.5`): follows the gradients more

  $GDRECON_PYTHON -m gdrecon_py.candidates ~/.cache/gdrecon/data/val [--gdrecon target/release/gdrecon]
"""
from __future__ import annotations

import argparse
import glob
import os
import subprocess
import time

CANDIDATES = {
    "prior": ["-m", "prior"],
    "l1prior": ["-m", "l1", "--preset", "prior"],
    "l1weak": ["-m", "l1", "--preset", "prior", "-p", "prior_alpha=0.5"],
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
        for bundle in bundles(folder):
            stem = os.path.splitext(os.path.basename(bundle))[0]
            for name, opts in CANDIDATES.items():
                out = path(folder, stem, name)
                if os.path.exists(out):
                    continue
                tmp = out + ".tmp.exr"
                subprocess.run([args.gdrecon, "reconstruct", bundle, "-o", tmp, "-q",
                                "--threads", str(args.threads), *opts], check=True)
                os.replace(tmp, out)
                n += 1
    print(f"{n} candidates written in {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
