"""Loss curves of a training run (log.jsonl written by gdrecon_py/train.py) as a PNG, drawn with
Pillow (matplotlib is not in the project's environment).

    $GDRECON_PYTHON -m gdrecon_py.plot_losses RUN_DIR [RUN_DIR2 ...] -o docs/gradnet_losses.png

One panel per loss (L_grad, L_data, L_1st, total, L' of the G-branch); per-step values in light
colour, the moving average over 20 steps in full colour; one colour per run.

    $GDRECON_PYTHON -m gdrecon_py.plot_losses RUN_DIR --curve -o docs/gradnet_curve.png \
        --ref 4=0.0182,16=0.00452,64=0.00156

`--curve` (runs of gdrecon_py/train_gradnet.py, which validate after every epoch): the validation
relMSE (geometric mean over the frames of each spp) against the epoch, log y, one colour per spp,
with `--ref` levels (L1's geometric means, say) as thin lines of the same colour.

    $GDRECON_PYTHON -m gdrecon_py.plot_losses RUN_A RUN_B ... --compare -o docs/gradnet_ablation.png \
        --labels shipped,no-augmentation,...

`--compare` (train_gradnet.py runs, an ablation): one panel per spp and one for all frames, the
validation relMSE against the epoch, one colour per run.
"""
import argparse
import json
import math
import os

from PIL import Image, ImageDraw

COLORS = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189)]


def load(run):
    main, g = [], []
    with open(os.path.join(run, "log.jsonl")) as f:
        for line in f:
            r = json.loads(line)
            if r.get("kind") == "main":
                main.append(r)
            elif r.get("kind") == "g":
                g.append(r)
    return main, g


def smooth(v, n=20):
    out, s = [], 0.0
    for i, x in enumerate(v):
        s += x
        if i >= n:
            s -= v[i - n]
        out.append(s / min(i + 1, n))
    return out


def panel(draw, box, title, series, log_y=True, smooth_n=20, xlabel="steps"):
    x0, y0, x1, y1 = box
    draw.rectangle(box, outline=(0, 0, 0))
    draw.text((x0 + 6, y0 + 4), title, fill=(0, 0, 0))
    vals = [v for _, ys in series for v in ys if v > 0 or not log_y]
    if not vals:
        return
    lo, hi = min(vals), max(vals)
    if log_y:
        lo, hi = math.log10(max(lo, 1e-8)), math.log10(hi)
    if hi <= lo:
        hi = lo + 1e-6
    n = max(len(ys) for _, ys in series)

    def tx(i):
        return x0 + 40 + (x1 - x0 - 50) * i / max(n - 1, 1)

    def ty(v):
        v = math.log10(max(v, 1e-8)) if log_y else v
        return y1 - 20 - (y1 - y0 - 40) * (v - lo) / (hi - lo)
    for k in range(5):
        val = lo + (hi - lo) * k / 4
        lab = f"{10 ** val:.3g}" if log_y else f"{val:.3g}"
        yy = y1 - 20 - (y1 - y0 - 40) * k / 4
        draw.line([(x0 + 38, yy), (x1 - 8, yy)], fill=(225, 225, 225))
        draw.text((x0 + 2, yy - 6), lab, fill=(80, 80, 80))
    draw.text((x1 - 90, y1 - 16), f"{xlabel} (0..{n - 1})", fill=(80, 80, 80))
    for color, ys in series:
        light = tuple(int(c + (255 - c) * 0.7) for c in color)
        pts = [(tx(i), ty(v)) for i, v in enumerate(ys)]
        if len(pts) > 1:
            draw.line(pts, fill=light, width=1)
            draw.line([(tx(i), ty(v)) for i, v in enumerate(smooth(ys, smooth_n))], fill=color, width=2)


def legend(draw, labels):
    """One colour swatch and label per run along the top edge."""
    x = 10
    for i, lab in enumerate(labels):
        draw.rectangle([x, 14, x + 14, 26], fill=COLORS[i % 4])
        draw.text((x + 20, 14), lab, fill=(0, 0, 0))
        x += 30 + 7 * len(lab)


def val_epochs(run):
    rows = [json.loads(line) for line in open(os.path.join(run, "log.jsonl"))]
    return [r for r in rows if r.get("kind") == "epoch" and "val" in r]


def curve(run, out, refs):
    ep = val_epochs(run)
    spps = sorted({float(k) for r in ep for k in r["val_by_spp"]})
    W, H = 900, 560
    img = Image.new("RGB", (W, H), (255, 255, 255))
    d = ImageDraw.Draw(img)
    box = (10, 40, W - 10, H - 10)
    series = [(COLORS[i % 4], [r["val_by_spp"][k] for r in ep for k in r["val_by_spp"] if float(k) == s])
              for i, s in enumerate(spps)]
    flat = [(tuple(int(v + (255 - v) * 0.6) for v in c), [refs[s]] * len(ys))
            for (c, ys), s in zip(series, spps) if s in refs]
    panel(d, box, "validation relMSE, geometric mean per spp, after each epoch (light: --ref levels)",
          series + flat, smooth_n=1, xlabel="epochs")
    x = 10
    for i, s in enumerate(spps):
        d.rectangle([x, 14, x + 14, 26], fill=COLORS[i % 4])
        d.text((x + 20, 14), f"{s:g} spp", fill=(0, 0, 0))
        x += 90
    img.save(out)
    print(f"wrote {out}")


def compare(runs, labels, out):
    eps = [val_epochs(r) for r in runs]
    spps = sorted({k for ep in eps for r in ep for k in r["val_by_spp"]}, key=float)
    W, H = 1200, 420
    img = Image.new("RGB", (W, H), (255, 255, 255))
    d = ImageDraw.Draw(img)
    n = len(spps) + 1
    pw = (W - 10 * (n + 1)) // n
    boxes = [(10 + i * (pw + 10), 40, 10 + i * (pw + 10) + pw, H - 10) for i in range(n)]
    for b, k in zip(boxes, spps):
        panel(d, b, f"validation relMSE, {float(k):g} spp (geometric mean)",
              [(COLORS[i % 4], [r["val_by_spp"][k] for r in ep]) for i, ep in enumerate(eps)],
              smooth_n=1, xlabel="epochs")
    panel(d, boxes[-1], "validation relMSE, all frames",
          [(COLORS[i % 4], [r["val"] for r in ep]) for i, ep in enumerate(eps)], smooth_n=1, xlabel="epochs")
    legend(d, labels)
    img.save(out)
    print(f"wrote {out}")


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+")
    ap.add_argument("-o", "--out", required=True)
    ap.add_argument("--labels", help="comma-separated legend labels")
    ap.add_argument("--curve", action="store_true", help="validation curve of one train_gradnet run")
    ap.add_argument("--ref", default="", help="spp=relMSE,... levels drawn with --curve")
    ap.add_argument("--compare", action="store_true", help="validation curves of several train_gradnet runs")
    args = ap.parse_args(argv)
    labels = args.labels.split(",") if args.labels else [os.path.basename(r.rstrip("/")) for r in args.runs]
    if args.compare:
        compare(args.runs, labels, args.out)
        return
    if args.curve:
        refs = {float(k): float(v) for k, v in (kv.split("=") for kv in args.ref.split(",") if kv)}
        curve(args.runs[0], args.out, refs)
        return
    data = [load(r) for r in args.runs]
    W, H = 1200, 760
    img = Image.new("RGB", (W, H), (255, 255, 255))
    d = ImageDraw.Draw(img)
    pw, ph = 390, 340
    boxes = [(10 + (i % 3) * (pw + 10), 40 + (i // 3) * (ph + 10), 10 + (i % 3) * (pw + 10) + pw,
              40 + (i // 3) * (ph + 10) + ph) for i in range(6)]
    keys = [("grad", "L_grad"), ("data", "L_data"), ("first", "L_1st (logged; weighted by lambda_F)"),
            ("total", "total = L_grad + L_data + lambda_F L_1st")]
    for b, (k, t) in zip(boxes, keys):
        panel(d, b, t, [(COLORS[i % 4], [r[k] for r in m]) for i, (m, _) in enumerate(data)])
    panel(d, boxes[4], "L' (G-branch)", [(COLORS[i % 4], [r["lprime"] for r in g])
                                          for i, (_, g) in enumerate(data) if g])
    lam = [(COLORS[i % 4], [r["lambda"] for r in m]) for i, (m, _) in enumerate(data)]
    panel(d, boxes[5], "lambda_F schedule (linear y)", lam, log_y=False)
    legend(d, labels)
    img.save(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
