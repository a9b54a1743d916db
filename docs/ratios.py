"""Per-frame relMSE ratios of bench variants against a baseline, summarised per spp.

Reads a `gdrecon bench` results.csv (baselines included with --baselines) and prints, for each
variant, the geometric mean over frames of variant / baseline per spp and the worst frame:

    python3 docs/ratios.py docs/bench/test/results.csv oidn l1:prior l2:data=prior frgr
    python3 docs/ratios.py docs/bench/test/results.csv oidn:equal-time l1:prior

Variants are named as bench names them (`l1:prior`, `frgr`); baselines by their setting
(`base`, `oidn`, `oidn:equal-time`). Standard library only.
"""
import collections
import csv
import math
import sys


def load(path):
    table = collections.defaultdict(dict)
    for r in csv.DictReader(open(path)):
        if r["method"] == "baseline":
            name = r["setting"]
        elif r["setting"] in ("default", ""):
            name = r["method"]
        else:
            name = f"{r['method']}:{r['setting']}"
        if r["scale"] in ("1", "1.0"):
            table[name][(r["scene"], int(r["spp"]))] = float(r["rel_mse"])
    return table


def main(argv):
    if len(argv) < 3:
        sys.exit(__doc__)
    table = load(argv[0])
    base = table[argv[1]]
    for name in argv[2:]:
        cells = []
        for spp in sorted({k[1] for k in base}):
            keys = [k for k in base if k[1] == spp and k in table[name]]
            if not keys:
                continue
            ratios = [table[name][k] / base[k] for k in keys]
            geo = math.exp(sum(map(math.log, ratios)) / len(ratios))
            worst, key = max(zip(ratios, keys))
            cells.append(f"{spp} spp {geo:.3f} (worst {worst:.3f}, {key[0]})")
        print(f"{name} / {argv[1]}: " + "; ".join(cells))


if __name__ == "__main__":
    main(sys.argv[1:])
