"""relMSE of the noisy base image (`color`) against `reference` for every bundle in a folder,
as a Markdown table (scenes x spp). relMSE = mean over pixels and channels of
(I - R)^2 / (R^2 + 0.01) (gdrecon_py.metrics, docs/CONVENTIONS.md), 5 significant digits.

  $GDRECON_PYTHON -m gdrecon_py.data.evaluate ~/.cache/gdrecon/data/val
"""
import argparse
import glob
import os
import re

from ..metrics import relmse


def main(argv=None):
    from .render import read_bundle

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder")
    ap.add_argument("--layer", default="color", help="layer to compare with the reference")
    args = ap.parse_args(argv)

    table = {}
    spps = set()
    for path in sorted(glob.glob(os.path.join(args.folder, "*.exr"))):
        layers, hdr = read_bundle(path)
        if "reference" not in layers or args.layer not in layers:
            continue
        m = re.match(r"(.*)_(\d+)spp\.exr$", os.path.basename(path))
        scene, spp = (m.group(1), int(m.group(2))) if m else (os.path.basename(path), int(float(hdr.get("spp", 0))))
        table.setdefault(scene, {})[spp] = relmse(layers[args.layer], layers["reference"])
        spps.add(spp)
    spps = sorted(spps)
    print("| scene | " + " | ".join(f"{s} spp" for s in spps) + " |")
    print("| --- |" + " --- |" * len(spps))
    for scene, row in table.items():
        print(f"| {scene} | " + " | ".join(f"{row[s]:.5g}" if s in row else "" for s in spps) + " |")


if __name__ == "__main__":
    main()
