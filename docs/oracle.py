"""How much a per-region choice between two methods' outputs could gain: an upper bound.

For every bundle in a folder with a `reference` layer, reads the two methods' outputs
`<OUT>/<frame>.<a>.exr` and `<OUT>/<frame>.<b>.exr` (written by `gdrecon reconstruct`), and
prints, per spp, the geometric mean over frames (and the best frame) of the relMSE of a choice
made with the reference's help, as a multiple of method `a`'s: per frame, per 32 x 32 and 8 x 8
block, per pixel. A learned choice can only approach these; they size the gain, nothing more.

    for f in DIR/*_*spp.exr; do b=$(basename $f .exr)
      for m in combiner gradnet; do gdrecon reconstruct $f -o OUT/$b.$m.exr -m $m --quiet; done
    done
    $GDRECON_PYTHON docs/oracle.py DIR OUT combiner gradnet

relMSE from `onnx/gdrecon_py/metrics.py` (its terms per pixel, then the mean). Needs the project's venv
(`onnx/setup.sh`; `PYTHONPATH=onnx` when gdrecon_py is not installed).
"""
import collections
import glob
import math
import os
import sys

import numpy as np

from gdrecon_py.data.render import read_bundle
from gdrecon_py.metrics import relmse_map


def rgb(path):
    layers, _ = read_bundle(path)
    return layers["color"] if "color" in layers else layers[""]


def per_pixel(img, ref):
    return relmse_map(img, ref).mean(-1)


def blocks(ma, mb, bs):
    """relMSE of the per-block choice of the smaller mean (partial blocks at the edges: `a`)."""
    h, w = ma.shape[0] // bs * bs, ma.shape[1] // bs * bs
    pick = lambda m: m[:h, :w].reshape(h // bs, bs, w // bs, bs).mean((1, 3))
    use_b = np.kron(pick(mb) < pick(ma), np.ones((bs, bs), bool))
    best = ma.copy()
    best[:h, :w] = np.where(use_b, mb[:h, :w], ma[:h, :w])
    return best.mean()


def main(folder, out, a, b):
    res = collections.defaultdict(lambda: collections.defaultdict(list))
    for f in sorted(glob.glob(os.path.join(folder, "*_*spp.exr"))):
        name = os.path.basename(f)[:-4]
        scene, spp = name.rsplit("_", 1)
        layers, _ = read_bundle(f)
        ref = layers["reference"]
        ma = per_pixel(rgb(os.path.join(out, f"{name}.{a}.exr")), ref)
        mb = per_pixel(rgb(os.path.join(out, f"{name}.{b}.exr")), ref)
        rows = {b: mb.mean(), "per frame": min(ma.mean(), mb.mean()), "per 32 x 32 block": blocks(ma, mb, 32),
                "per 8 x 8 block": blocks(ma, mb, 8), "per pixel": np.minimum(ma, mb).mean()}
        for k, v in rows.items():
            res[k][int(spp[:-3])].append((scene, v / ma.mean()))
    for k, by_spp in res.items():
        cells = []
        for spp in sorted(by_spp):
            vals = by_spp[spp]
            gm = math.exp(sum(math.log(v) for _, v in vals) / len(vals))
            best = min(vals, key=lambda t: t[1])
            cells.append(f"{spp} spp {gm:.3f} (best {best[1]:.3f} {best[0]})")
        print(f"{k} x {a}: " + "; ".join(cells))


if __name__ == "__main__":
    if len(sys.argv) != 5:
        sys.exit(__doc__)
    main(*sys.argv[1:])
