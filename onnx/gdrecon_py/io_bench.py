"""The CLI end to end against the OpenEXR library and OIDN, in one run (issue: "Faster than the
denoiser it must beat", item 5).

Rounds interleave, so that every ratio compares times taken under the same load:

1. OpenEXR (the PyPI `OpenEXR` package, C++ library 3.x) reads every channel of the bundle;
2. OpenEXR writes the bundle's colour as an RGB float32 ZIP file (what `reconstruct` writes);
3. `gdrecon reconstruct -m l2 BUNDLE -o OUT`, timed whole (process start to exit), with the
   read and write times it prints (its read includes validation and sanitising);
4. `gdrecon bench BUNDLE --settings prior --runs 1 --warmup 1`: OIDN on the frame, the time
   the bar divides by.

  $GDRECON_PYTHON -m gdrecon_py.io_bench BUNDLE [--gdrecon target/release/gdrecon] [--rounds 5]

Prints the medians and the ratios; `docs/benchmarks.md` quotes them.
"""
from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import tempfile
import time


def openexr_read(path):
    import OpenEXR

    t = time.perf_counter()
    with OpenEXR.File(path, separate_channels=True) as f:
        pixels = {name: ch.pixels for name, ch in f.channels().items()}
    return time.perf_counter() - t, pixels


def openexr_write(path, pixels):
    import OpenEXR

    rgb = {c: OpenEXR.Channel(pixels[f"color.{c}"]) for c in "RGB"}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    t = time.perf_counter()
    with OpenEXR.File(header, rgb) as f:
        f.write(path)
    return time.perf_counter() - t


def gdrecon_l2(exe, bundle, out, threads):
    cmd = [exe, "reconstruct", "-m", "l2", bundle, "-o", out]
    if threads:
        cmd += ["--threads", str(threads)]
    t = time.perf_counter()
    text = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    wall = time.perf_counter() - t
    read = float(re.search(r"read in ([0-9.]+) s", text).group(1))
    write = float(re.search(r"wrote .* in ([0-9.]+) s", text).group(1))
    return wall, read, write


def oidn(exe, bundle, threads):
    cmd = [exe, "bench", bundle, "--settings", "prior", "--runs", "1", "--warmup", "1"]
    if threads:
        cmd += ["--threads", str(threads)]
    text = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    row = next(line for line in text.splitlines() if " prior " in line)
    return float(row.split()[3])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bundle")
    ap.add_argument("--gdrecon", default="target/release/gdrecon")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--threads", type=int, default=0, help="gdrecon's --threads (0: all cores)")
    args = ap.parse_args(argv)
    times = {k: [] for k in ("exr read", "exr write", "cli l2", "cli read", "cli write", "oidn")}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            t, pixels = openexr_read(args.bundle)
            times["exr read"].append(t)
            times["exr write"].append(openexr_write(os.path.join(tmp, "py.exr"), pixels))
            wall, read, write = gdrecon_l2(
                args.gdrecon, args.bundle, os.path.join(tmp, "rs.exr"), args.threads
            )
            times["cli l2"].append(wall)
            times["cli read"].append(read)
            times["cli write"].append(write)
            times["oidn"].append(oidn(args.gdrecon, args.bundle, args.threads))
            print(f"round {r + 1}: " + ", ".join(f"{k} {v[-1]:.3f}" for k, v in times.items()))
    med = {k: statistics.median(v) for k, v in times.items()}
    print("\nmedians (s): " + ", ".join(f"{k} {v:.3f}" for k, v in med.items()))
    print(f"gdrecon read / OpenEXR read:   {med['cli read'] / med['exr read']:.2f}x")
    print(f"gdrecon write / OpenEXR write: {med['cli write'] / med['exr write']:.2f}x")
    print(f"whole CLI l2 / OIDN:           {med['cli l2'] / med['oidn']:.3f}x")


if __name__ == "__main__":
    main()
