"""Contact sheet of the base scenes: the tone-mapped `reference` layer of one bundle per scene in
a grid, each labelled with its name.

  $GDRECON_PYTHON -m gdrecon_py.data.contact_sheet --val ~/.cache/gdrecon/data/val --out docs/scenes.png

Takes `<scene>_64spp.exr` (or any `<scene>_*spp.exr` with a reference layer) from --val.
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
    ap.add_argument("--val", default=os.path.expanduser("~/.cache/gdrecon/data/val"))
    ap.add_argument("--out", required=True)
    ap.add_argument("--cols", type=int, default=3)
    args = ap.parse_args(argv)

    tiles = []
    for name in scenes.SCENES:
        cands = sorted(glob.glob(os.path.join(args.val, f"{name}_64spp.exr"))) + \
            sorted(glob.glob(os.path.join(args.val, f"{name}_*spp.exr")))
        img = None
        for path in cands:
            layers, hdr = read_bundle(path)
            if "reference" in layers:
                img = tonemap(layers["reference"])
                spp = hdr.get("gdrecon_reference_spp", "?")
                break
        if img is None:
            print(f"no bundle with a reference for {name} in {args.val}", file=sys.stderr)
            continue
        tile = Image.fromarray(img)
        d = ImageDraw.Draw(tile)
        try:
            font = ImageFont.load_default(size=16)
        except TypeError:  # old Pillow
            font = ImageFont.load_default()
        label = f"{name} (reference {int(float(spp))} spp)"
        x0, y0, x1, y1 = d.textbbox((4, 2), label, font=font)
        d.rectangle([0, 0, x1 + 4, y1 + 4], fill=(0, 0, 0))
        d.text((4, 2), label, fill=(255, 255, 255), font=font)
        tiles.append(tile)
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
