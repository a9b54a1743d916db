"""The field's yardstick: Intel Open Image Denoise on the same frames, for `gdrecon bench`.

For every bundle in a folder (docs/CONVENTIONS.md layout) this runs OIDN 2.5.1 (PyPI
`pyoidn`, pinned in onnx/requirements.txt; CPU device, RT filter, hdr, quality high,
albedo + normal from the bundle, not marked clean so OIDN prefilters them) on two images:

- `color`: the gradient-domain render's base image at the bundle's spp ("OIDN, same spp");
- `primal` (when the bundle has it): a plain path-traced render of the same frame at 2x the
  spp ("OIDN, equal time": a gradient-domain sample costs about two primal samples).

Outputs, next to the bundles, read by `gdrecon bench` (which computes their relMSE itself):

    <folder>/oidn/<stem>.exr             RGB, OIDN on color
    <folder>/oidn-equal-time/<stem>.exr  RGB, OIDN on primal
    <folder>/oidn/timings.json           {stem: seconds of the same-spp filter}

It prints a relMSE table (gdrecon_py.metrics.relmse) as it goes.

  $GDRECON_PYTHON -m gdrecon_py.oidn ~/.cache/gdrecon/data/val [--force]

`--fixtures` writes instead the parity fixtures of the library's own OIDN prior
(tests/prior.rs): tests/fixtures/prior/<stem>_oidn.npy, (H, W, 3) float32, for every guard frame
tests/data/guard/<stem>.exr (HDR bulbs, a dim cellar, ...), through `denoise` below.

  $GDRECON_PYTHON -m gdrecon_py.oidn --fixtures
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import time

import numpy as np

from .metrics import relmse

SAME_SPP = "oidn"
EQUAL_TIME = "oidn-equal-time"


def denoise(color, albedo=None, normal=None):
    """OIDN RT filter (hdr, quality high) on an (H, W, 3) float32 image; returns float32.

    Negative or non-finite inputs (none in our renders) are clamped to 0 first: OIDN expects
    non-negative HDR radiance."""
    import pyoidn

    color = np.nan_to_num(np.asarray(color, np.float32), nan=0.0, posinf=0.0).clip(0, None)
    aux = {}
    if albedo is not None:
        aux["albedo"] = np.ascontiguousarray(np.clip(albedo, 0, 1), np.float32)
    if normal is not None:
        aux["normal"] = np.ascontiguousarray(np.clip(normal, -1, 1), np.float32)
    return pyoidn.denoise(np.ascontiguousarray(color), hdr=True, quality="high", **aux)


def write_rgb(path, img):
    """A single-layer f32 RGB EXR (channels R, G, B), written atomically."""
    from .data.render import scanline_header, write_exr

    img = np.asarray(img, np.float32)
    write_exr(path, {c: np.ascontiguousarray(img[..., i]) for i, c in enumerate("RGB")},
              scanline_header())


def read_rgb(path):
    """The (H, W, 3) float32 image of a file written by write_rgb."""
    from .data.render import read_bundle

    return read_bundle(path)[0][""]


def main(argv=None):
    from .data.render import read_bundle

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("folder", nargs="*", help="folders of bundles")
    ap.add_argument("--force", action="store_true", help="recompute outputs that exist")
    ap.add_argument("--fixtures", action="store_true",
                    help="write tests/fixtures/prior/<stem>_oidn.npy for the guard frames")
    args = ap.parse_args(argv)
    if args.fixtures:
        return write_fixtures()
    if not args.folder:
        ap.error("give at least one folder of bundles (or --fixtures)")

    warm = False
    for folder in args.folder:
        same_dir, eq_dir = os.path.join(folder, SAME_SPP), os.path.join(folder, EQUAL_TIME)
        os.makedirs(same_dir, exist_ok=True)
        os.makedirs(eq_dir, exist_ok=True)
        timings_path = os.path.join(same_dir, "timings.json")
        timings = json.load(open(timings_path)) if os.path.exists(timings_path) else {}
        print(f"# {folder}\nframe\tbase\toidn\toidn_equal_time\tseconds", flush=True)
        for path in sorted(glob.glob(os.path.join(folder, "*.exr"))):
            stem = os.path.splitext(os.path.basename(path))[0]
            out_same = os.path.join(same_dir, stem + ".exr")
            out_eq = os.path.join(eq_dir, stem + ".exr")
            layers, _ = read_bundle(path)
            albedo, normal = layers.get("albedo"), layers.get("normal")
            if args.force or not os.path.exists(out_same):
                if not warm:  # the first call creates OIDN's device: not part of a filter's time
                    denoise(layers["color"][:8, :8], *(a[:8, :8] if a is not None else None
                                                       for a in (albedo, normal)))
                    warm = True
                t0 = time.perf_counter()
                same = denoise(layers["color"], albedo, normal)
                timings[stem] = round(time.perf_counter() - t0, 4)
                write_rgb(out_same, same)
            else:
                same = read_rgb(out_same)
            eq = None
            if "primal" in layers and (args.force or not os.path.exists(out_eq)):
                eq = denoise(layers["primal"], albedo, normal)
                write_rgb(out_eq, eq)
            elif os.path.exists(out_eq):
                eq = read_rgb(out_eq)
            ref = layers.get("reference")
            if ref is not None:
                cells = [relmse(layers["color"], ref), relmse(same, ref),
                         relmse(eq, ref) if eq is not None else float("nan")]
                print(stem + "\t" + "\t".join(f"{c:.5g}" for c in cells) + f"\t{timings.get(stem, 0):.3f}",
                      flush=True)
        with open(timings_path, "w") as fh:
            json.dump(timings, fh, indent=1, sort_keys=True)


def write_fixtures():
    """OIDN on every guard frame's base image, for the Rust parity test of the prior."""
    from .data.render import read_bundle

    repo = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    out_dir = os.path.join(repo, "tests", "fixtures", "prior")
    os.makedirs(out_dir, exist_ok=True)
    for path in sorted(glob.glob(os.path.join(repo, "tests", "data", "guard", "*.exr"))):
        stem = os.path.splitext(os.path.basename(path))[0]
        layers, _ = read_bundle(path)
        out = denoise(layers["color"], layers.get("albedo"), layers.get("normal"))
        np.save(os.path.join(out_dir, stem + "_oidn.npy"), np.asarray(out, np.float32))
        print(f"{stem}: {out.shape[1]} x {out.shape[0]}, relMSE {relmse(out, layers['reference']):.4g}")


if __name__ == "__main__":
    main()
