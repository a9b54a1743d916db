"""Compact, self-contained packs of gdrecon bundles: what a training run on another machine needs,
small enough to travel (the device machine takes 64 MiB a call, docs/gradnet.md).

    $GDRECON_PYTHON -m gdrecon_py.pack train OUT.xz DIR [DIR ...] [--part I/N]   # training frames
    $GDRECON_PYTHON -m gdrecon_py.pack val   OUT.xz DIR               # validation, with references

A training pack holds, per frame, the 16 planes GradNet trains on (colour 3, dx 3, dy 3 linear and
sanitised; the 7 feature planes normalised exactly as inference normalises them,
`pipeline.normalize_features`), frames of one size stacked together. A validation pack holds whole
frames (colour, gradients, features, variance and reference) for `pipeline.reconstruct`.

Storage (depth of validation frames excepted: float32): float16 with the mantissa rounded to
nearest at `MANTISSA_BITS` bits (relative error at most 2^-8), the noisy planes of training frames
at `NOISY_BITS` (2^-7: a relative variance of about 2e-5, a few thousandths of a 64 spp
frame's noise variance, unbiased); bytes split into planes, lzma. Reading a pack needs numpy
and the standard library only.
"""
import argparse
import glob
import io
import json
import lzma
import os
import sys

import numpy as np

MANTISSA_BITS = 7
NOISY_BITS = 6
TRAIN_PLANES = 16
VAL_LAYERS = ("color", "dx", "dy", "albedo", "normal", "depth", "variance", "reference")


def round_half(a, bits=MANTISSA_BITS):
    """float array -> float16 with the mantissa rounded to nearest at `bits` bits (of 10)."""
    h = np.asarray(a, np.float32).astype(np.float16)
    drop = 10 - bits
    if drop <= 0:
        return h
    u = h.view(np.uint16).astype(np.uint32)
    u = ((u + (1 << (drop - 1))) >> drop) << drop        # carries into the exponent correctly
    u = np.minimum(u & 0x7FFF, 0x7BFF) | (u & 0x8000)    # never round up to Inf
    return u.astype(np.uint16).view(np.float16)


def _encode(arrays):
    """{name: float16 or float32 array} -> lzma bytes (byte-planar: byte i of every value, then
    byte i + 1, which lzma compresses far better than interleaved bytes)."""
    buf = io.BytesIO()
    planar = {}
    for k, a in arrays.items():
        a = np.ascontiguousarray(a)
        planar[k] = a.reshape(-1).view(np.uint8).reshape(-1, a.itemsize).T.copy()
        planar[k + ".shape"] = np.array(a.shape, np.int64)
        planar[k + ".dtype"] = np.array(a.dtype.str)
    np.savez(buf, **planar)
    return lzma.compress(buf.getvalue(), preset=6)


def _decode(blob):
    z = np.load(io.BytesIO(lzma.decompress(blob)))
    out = {}
    for k in z.files:
        if k.endswith(".shape") or k.endswith(".dtype"):
            continue
        dtype = np.dtype(str(z[k + ".dtype"]))
        out[k] = z[k].T.copy().view(dtype).reshape(tuple(z[k + ".shape"]))
    return out


def write(path, arrays, meta):
    blob = _encode(arrays)
    head = json.dumps(meta).encode()
    tmp = path + ".tmp"
    with open(tmp, "wb") as f:
        f.write(len(head).to_bytes(8, "little"))
        f.write(head)
        f.write(blob)
    os.replace(tmp, path)


def read(path):
    """-> (meta dict, {name: float16 array})."""
    with open(path, "rb") as f:
        n = int.from_bytes(f.read(8), "little")
        meta = json.loads(f.read(n))
        arrays = _decode(f.read())
    return meta, arrays


def read_train(paths):
    """Training packs -> {frame size: float16 array}, the packs' frames of each size stacked.
    Refuses a pack that is not a training pack."""
    out = {}
    for path in paths:
        meta, arrays = read(path)
        if meta.get("kind") != "train":
            raise SystemExit(f"{path}: not a training pack")
        for k, a in arrays.items():
            out[k] = np.concatenate([out[k], a]) if k in out else a
    return out


def _bundles(dirs, part="0/1"):
    """Bundles in `dirs` (sorted per folder); `part` "I/N" keeps every N-th from the I-th (packs
    that must travel separately)."""
    files = []
    for d in dirs:
        files += sorted(glob.glob(os.path.join(d, "*.exr"))) if os.path.isdir(d) else [d]
    if not files:
        raise SystemExit(f"no .exr bundle in {' '.join(dirs)}")
    i, n = (int(v) for v in part.split("/"))
    return files[i::n]


def train_planes(frame):
    """Bundle dict -> 16 x H x W float32 (colour, dx, dy, normalised features)."""
    from . import pipeline as pl
    fr = pl.sanitize(frame)
    feat = pl.normalize_features(fr["albedo"], fr["normal"], fr["depth"])
    return np.concatenate([fr["color"], fr["dx"], fr["dy"], feat], -1).transpose(2, 0, 1)


def pack_train(out, dirs, part="0/1"):
    from . import pipeline as pl
    groups, names = {}, {}
    for f in _bundles(dirs, part):
        fr = pl.read_frame(f)
        a = train_planes(fr)
        key = f"{a.shape[2]}x{a.shape[1]}"
        # the noisy planes at NOISY_BITS (the pack must travel), features at MANTISSA_BITS
        groups.setdefault(key, []).append(np.concatenate([round_half(a[:9], NOISY_BITS), round_half(a[9:])]))
        names.setdefault(key, []).append({"file": os.path.basename(f), "spp": fr.get("spp")})
    arrays = {k: np.stack(v) for k, v in groups.items()}
    write(out, arrays, {"kind": "train", "planes": TRAIN_PLANES, "frames": names,
                        "mantissa_bits": MANTISSA_BITS, "noisy_bits": NOISY_BITS, "part": part})
    return arrays


def pack_val(out, dirs):
    from . import pipeline as pl
    arrays, frames = {}, []
    for i, f in enumerate(_bundles(dirs)):
        fr = pl.read_frame(f)
        if fr.get("reference") is None:
            raise SystemExit(f"{f}: a validation pack needs the reference layer")
        for k in VAL_LAYERS:
            if fr.get(k) is not None:
                # depth exactly: its per-frame min-max normalisation would stretch rounding
                arrays[f"{i}/{k}"] = (np.asarray(fr[k], np.float32) if k == "depth"
                                      else round_half(fr[k]))
        frames.append({"file": os.path.basename(f), "spp": fr.get("spp")})
    write(out, arrays, {"kind": "val", "frames": frames, "mantissa_bits": MANTISSA_BITS})
    return arrays


def val_frames(arrays, meta):
    """Validation pack -> list of (meta row, frame dict of float32 H x W x C arrays)."""
    out = []
    for i, row in enumerate(meta["frames"]):
        fr = {k: arrays[f"{i}/{k}"].astype(np.float32) for k in VAL_LAYERS if f"{i}/{k}" in arrays}
        out.append((row, fr))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("kind", choices=["train", "val"])
    ap.add_argument("out")
    ap.add_argument("dirs", nargs="+")
    ap.add_argument("--part", default="0/1", help="I/N: every N-th bundle from the I-th (train)")
    a = ap.parse_args(argv)
    arrays = pack_train(a.out, a.dirs, a.part) if a.kind == "train" else pack_val(a.out, a.dirs)
    raw = sum(v.nbytes for v in arrays.values())
    print(f"{a.out}: {len(arrays)} arrays, {raw / 2**20:.1f} MiB raw, "
          f"{os.path.getsize(a.out) / 2**20:.1f} MiB packed", file=sys.stderr)


if __name__ == "__main__":
    main()
