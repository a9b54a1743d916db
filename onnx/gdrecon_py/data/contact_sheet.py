"""Contact sheet of the base scenes: the tone-mapped `reference` layer of one bundle per scene in
a grid, each labelled with its name, split, reference spp and the reference's mean / max.

  $GDRECON_PYTHON -m gdrecon_py.data.contact_sheet --scenes val --dir ~/.cache/gdrecon/data/val \
      --out docs/scenes.png
  $GDRECON_PYTHON -m gdrecon_py.data.contact_sheet --scenes test --dir ~/.cache/gdrecon/data/test \
      --out docs/scenes-test.png

Takes `<scene>_64spp.exr` (or any `<scene>_*spp.exr` with a reference layer) from the first
--dir that has one (--layer picks another layer, e.g. `color` for frames without a reference).
--scenes: 'all', a split name (train, val, test) or a comma list (scenes.families).
Tone mapping: Reinhard x / (1 + x) per channel, then the sRGB transfer curve.
"""
import argparse
import glob
import os
import sys

import numpy as np
from PIL import Image, ImageDraw, ImageFont


def tonemap(x):
    x = np.clip(np.nan_to_num(x, nan=0.0, posinf=0.0), 0, None)
    x = x / (1.0 + x)
    x = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (np.clip(x, 0, 1) * 255 + 0.5).astype(np.uint8)


def main(argv=None):
    from .render import read_bundle  # sets the Mitsuba variant scenes needs
    from . import scenes

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dir", "--val", dest="dirs", action="append", default=None,
                    help="folder(s) with bundles (default ~/.cache/gdrecon/data/val and .../test)")
    ap.add_argument("--scenes", default="all", help="'all', a split name or a comma list")
    ap.add_argument("--layer", default="reference", help="layer to show (default reference)")
    ap.add_argument("--out", default=None, help="PNG to write")
    ap.add_argument("--stats", action="store_true", help="print a Markdown table of the layer's "
                    "mean, max, 99.9th percentile and fraction of values > 10 per scene")
    ap.add_argument("--cols", type=int, default=3)
    args = ap.parse_args(argv)
    dirs = args.dirs or [os.path.expanduser(f"~/.cache/gdrecon/data/{d}") for d in ("val", "test")]

    tiles = []
    rows = []
    for name in scenes.families(args.scenes):
        cands = []
        for d in dirs:
            cands += sorted(glob.glob(os.path.join(d, f"{name}_64spp.exr"))) + \
                sorted(glob.glob(os.path.join(d, f"{name}_*spp.exr")))
        img = None
        for path in cands:
            layers, hdr = read_bundle(path)
            if args.layer in layers:
                x = layers[args.layer]
                img = tonemap(x)
                spp = hdr.get("gdrecon_reference_spp", "?") if args.layer == "reference" else hdr.get("spp", "?")
                stats = f"mean {x.mean():.3g}, max {x.max():.3g}"
                rows.append(f"| {name} | {scenes.split_of(name)} | {x.mean():.4g} | {x.max():.4g} | "
                            f"{np.quantile(x, 0.999):.4g} | {np.mean(x > 10):.2%} |")
                break
        if img is None:
            print(f"no bundle with a {args.layer} layer for {name} in {dirs}", file=sys.stderr)
            continue
        tile = Image.fromarray(img)
        d = ImageDraw.Draw(tile)
        try:
            font = ImageFont.load_default(size=16)
        except TypeError:  # old Pillow
            font = ImageFont.load_default()
        try:
            small = ImageFont.load_default(size=12)
        except TypeError:
            small = font
        label = f"{name} [{scenes.split_of(name)}] ({args.layer} {int(float(spp))} spp)"
        x0, y0, x1, y1 = d.textbbox((4, 2), label, font=font)
        d.rectangle([0, 0, x1 + 4, y1 + 4], fill=(0, 0, 0))
        d.text((4, 2), label, fill=(255, 255, 255), font=font)
        h = tile.size[1]
        x0, y0, x1, y1 = d.textbbox((4, h - 16), stats, font=small)
        d.rectangle([0, y0 - 2, x1 + 4, h], fill=(0, 0, 0))
        d.text((4, h - 16), stats, fill=(255, 255, 255), font=small)
        tiles.append(tile)
    if args.stats:
        print(f"| scene | split | mean {args.layer} | max | 99.9th pct | values > 10 |")
        print("| --- | --- | --- | --- | --- | --- |")
        print("\n".join(rows))
    if not args.out:
        return
    if not tiles:
        sys.exit("no tiles")
    w, h = tiles[0].size
    cols = min(args.cols, len(tiles))
    rows = (len(tiles) + cols - 1) // cols
    pad = 4
    sheet = Image.new("RGB", (cols * w + (cols + 1) * pad, rows * h + (rows + 1) * pad), (255, 255, 255))
    for i, t in enumerate(tiles):
        r, c = divmod(i, cols)
        sheet.paste(t, (pad + c * (w + pad), pad + r * (h + pad)))
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    sheet.save(args.out, optimize=True)
    print(f"wrote {args.out} ({sheet.size[0]}x{sheet.size[1]}, {len(tiles)} scenes)")


if __name__ == "__main__":
    main()
