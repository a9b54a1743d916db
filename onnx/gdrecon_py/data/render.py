"""Render gdrecon frame bundles (docs/CONVENTIONS.md) with Mitsuba 3 (llvm_ad_rgb).

Gradient-domain path tracing by *random replay* with the stock `path` integrator: the film has
one extra column and row, a box reconstruction filter and sample_border=False; the W x H crop
window is rendered at offsets (0,0), (1,0), (0,1) with the same seed and spp, so the shifted
renders replay the base paths' random numbers one pixel over:

    dx = render(1,0) - render(0,0)     (dx(x,y) = I(x+1,y) - I(x,y)),  last column := 0
    dy = render(0,1) - render(0,0)     (dy(x,y) = I(x,y+1) - I(x,y)),  last row    := 0

The spp of a bundle is split into k passes (distinct seeds per pass, one seed for the three crops
of a pass): color = mean of pass means, variance = sample variance of the pass means / k.
Features (albedo, shading normal, depth) come from the `aov` integrator; `reference` is an
independent high-spp render (its own seeds) of the same crop; `primal` (with --primal) is a plain
path-traced render of the same crop at 2x the bundle's spp (its own seeds), the equal-time
baseline of a non-gradient renderer (header `gdrecon_primal_spp`).

Examples:
  $GDRECON_PYTHON -m gdrecon_py.data.render --scene cornell --size 320x180 --spp 16 \
      --ref-spp 1024 --seed 1 --out examples/data --name sample
  $GDRECON_PYTHON -m gdrecon_py.data.render --scene all --size 256x256 --spp 4,16 \
      --perturb 0:16 --seed 1000 --out ~/.cache/gdrecon/data/train
  $GDRECON_PYTHON -m gdrecon_py.data.render --scene test --size 320x180 --spp 4,16,64 \
      --ref-spp 4096 --primal --seed 30000 --out ~/.cache/gdrecon/data/test
  $GDRECON_PYTHON -m gdrecon_py.data.render --add-primal ~/.cache/gdrecon/data/val

--scene takes a family, a split name (train, val, test; scenes.SPLITS), 'all', or a comma list.
--add-primal adds the `primal` layer to existing bundles (files or folders) and leaves every
other channel and header attribute bit-identical.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import subprocess
import time

import numpy as np

from ..metrics import relmse

VARIANT = "llvm_ad_rgb"
AOVS = "albedo:albedo,nn:sh_normal,dd:depth"
MAX_CHUNK_SPP = 256  # reference renders are split into chunks of at most this many spp
PERTURB_FAMILY = 0x7E55  # spawn-key tag of the training perturbation family


def find_libllvm():
    """Path of libLLVM 19 (Debian package libllvm19), or None."""
    try:
        out = subprocess.run(["dpkg", "-L", "libllvm19"], capture_output=True, text=True).stdout
        for line in out.splitlines():
            if "/libLLVM.so.19" in line and os.path.isfile(line):
                return line
    except OSError:
        pass
    for pat in ("/usr/lib/*/libLLVM.so.19*", "/usr/lib/*/libLLVM-19.so", "/usr/lib/llvm-19/lib/libLLVM*.so*"):
        hits = sorted(glob.glob(pat))
        if hits:
            return hits[0]
    return None


def init_mitsuba():
    """Import Mitsuba with the LLVM variant (sets DRJIT_LIBLLVM_PATH if it is unset)."""
    if not os.environ.get("DRJIT_LIBLLVM_PATH"):
        lib = find_libllvm()
        if lib:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
    import mitsuba as mi

    mi.set_variant(VARIANT)
    return mi


mi = init_mitsuba()
import drjit as dr  # noqa: E402

from . import scenes  # noqa: E402  (needs the variant set above)


# --------------------------------------------------------------------------------------------
# seeds


def derive_seed(*key):
    """Deterministic 31-bit seed from an integer key (numpy SeedSequence hashing)."""
    return int(np.random.SeedSequence([int(k) & 0xFFFFFFFF for k in key]).generate_state(1)[0] & 0x7FFFFFFF)


# streams: distinct first key component => independent random numbers
NOISY, FEATURES, REFERENCE, PRIMAL = 1, 2, 3, 4
PRIMAL_FACTOR = 2  # primal spp = PRIMAL_FACTOR x the bundle's spp (equal-time comparisons)


def scene_rng(perturb_index, perturb_seed):
    """Random generator of a training perturbation (None for the base scene)."""
    if perturb_index is None:
        return None
    return np.random.default_rng(np.random.SeedSequence([PERTURB_FAMILY, int(perturb_seed), int(perturb_index)]))


# --------------------------------------------------------------------------------------------
# scene loading and crop rendering


class Frame:
    """A loaded scene with a (W+1) x (H+1) film whose W x H crop window can be moved."""

    def __init__(self, scene_name, width, height, perturb_index=None, perturb_seed=0, max_depth=None,
                 full_film=False):
        """full_film: crop window = the whole (W+1) x (H+1) film (tests use it to get converged
        finite differences that do not rely on moving the crop)."""
        build = scenes.SCENES[scene_name]
        rng = scene_rng(perturb_index, perturb_seed)
        d = build(width, height, rng)
        if max_depth is not None:
            d["integrator"]["max_depth"] = int(max_depth)
        d["sensor"]["film"] = {
            "type": "hdrfilm",
            "width": width + 1,
            "height": height + 1,
            "crop_width": width + 1 if full_film else width,
            "crop_height": height + 1 if full_film else height,
            "crop_offset_x": 0,
            "crop_offset_y": 0,
            "rfilter": {"type": "box"},
            "sample_border": False,
            "pixel_format": "rgb",
            "component_format": "float32",
        }
        d["sensor"]["sampler"] = {"type": "independent", "sample_count": 1}
        self.name = scene_name
        self.width, self.height = (width + 1, height + 1) if full_film else (width, height)
        self.perturb_index = perturb_index
        # serial loading: parallel loading appends emitter shapes in thread-completion order, so a
        # scene with several emitter shapes could sample its lights in a different order from
        # run to run (same seed, different pixels)
        self.scene = mi.load_dict(d, parallel=False)
        self.sensor = self.scene.sensors()[0]
        self.params = mi.traverse(self.sensor)
        self.offset = (0, 0)
        self.aov = None

    def set_offset(self, ox, oy):
        if (ox, oy) != self.offset:
            self.params["film.crop_offset"] = mi.ScalarPoint2u(ox, oy)
            self.params.update()
            self.offset = (ox, oy)

    def render(self, offset, seed, spp):
        """W x H x 3 float32 image of the crop at `offset` (mean of `spp` samples per pixel)."""
        self.set_offset(*offset)
        img = self.scene.integrator().render(self.scene, self.sensor, seed=int(seed), spp=int(spp))
        out = np.array(img, dtype=np.float32)
        assert out.shape == (self.height, self.width, 3), out.shape
        return out

    def render_chunked(self, offset, seed_key, spp):
        """Mean of chunks of at most MAX_CHUNK_SPP spp (seeds derive_seed(*seed_key, chunk))."""
        acc = np.zeros((self.height, self.width, 3), np.float64)
        done, chunk = 0, 0
        while done < spp:
            n = min(MAX_CHUNK_SPP, spp - done)
            acc += n * self.render(offset, derive_seed(*seed_key, chunk), n)
            done += n
            chunk += 1
        return (acc / spp).astype(np.float32)

    def features(self, seed, spp):
        """albedo (H,W,3), normal (H,W,3), depth (H,W) from the aov integrator at crop (0,0)."""
        if self.aov is None:
            self.aov = mi.load_dict({"type": "aov", "aovs": AOVS})
        self.set_offset(0, 0)
        self.aov.render(self.scene, self.sensor, seed=int(seed), spp=int(spp))
        bmp = self.sensor.film().bitmap()
        names = [bmp.struct_()[i].name for i in range(bmp.channel_count())]
        arr = np.array(bmp, dtype=np.float32).reshape(self.height, self.width, -1)

        def pick(*chs):
            return np.stack([arr[..., names.index(c)] for c in chs], axis=-1)

        albedo = pick("albedo.R", "albedo.G", "albedo.B")
        normal = pick("nn.X", "nn.Y", "nn.Z")
        depth = arr[..., names.index("dd.T")]
        return albedo, normal, depth


def aov_channel_names(frame):
    frame.features(0, 1)
    bmp = frame.sensor.film().bitmap()
    return [bmp.struct_()[i].name for i in range(bmp.channel_count())]


def render_gradient_pass(frame, seed, spp):
    """One random-replay pass: (base, dx, dy), all H x W x 3 float32 (dx/dy borders zeroed)."""
    base = frame.render((0, 0), seed, spp)
    sx = frame.render((1, 0), seed, spp)
    sy = frame.render((0, 1), seed, spp)
    dx = sx - base
    dy = sy - base
    dx[:, -1, :] = 0.0
    dy[-1, :, :] = 0.0
    return base, dx, dy


def render_bundle(frame, spp, seed, passes=4, features=True, feature_spp=None):
    """Noisy layers of one frame bundle: dict of layer name -> array (H,W,3) (depth (H,W)).

    spp is split into `passes` passes (spp must be a multiple of passes; passes is reduced to
    spp when spp < passes). Seeds: derive_seed(NOISY, seed, spp, pass)."""
    k = max(1, min(int(passes), int(spp)))
    if spp % k:
        raise ValueError(f"spp {spp} is not a multiple of the number of passes {k}")
    per = spp // k
    bases, dxs, dys = [], [], []
    for p in range(k):
        s = derive_seed(NOISY, seed, spp, p)
        b, gx, gy = render_gradient_pass(frame, s, per)
        bases.append(b)
        dxs.append(gx)
        dys.append(gy)
    bases = np.stack(bases).astype(np.float64)
    out = {
        "color": bases.mean(0).astype(np.float32),
        "dx": np.mean(dxs, axis=0, dtype=np.float64).astype(np.float32),
        "dy": np.mean(dys, axis=0, dtype=np.float64).astype(np.float32),
    }
    if k > 1:
        out["variance"] = (bases.var(0, ddof=1) / k).astype(np.float32)
    if features:
        fspp = int(feature_spp or max(spp, 8))
        albedo, normal, depth = frame.features(derive_seed(FEATURES, seed, spp), fspp)
        out["albedo"], out["normal"], out["depth"] = albedo, normal, depth
    return out


def render_reference(frame, spp, seed):
    """High-spp plain render of the (0,0) crop; seeds derive_seed(REFERENCE, seed, chunk) are
    independent of every noisy and feature seed."""
    return frame.render_chunked((0, 0), (REFERENCE, seed), spp)


def render_primal(frame, spp, seed):
    """Plain path-traced render of the (0,0) crop at `spp` (the primal spp, normally
    PRIMAL_FACTOR x the bundle's spp); seeds derive_seed(PRIMAL, seed, spp, chunk) are independent
    of the noisy, feature and reference seeds."""
    return frame.render_chunked((0, 0), (PRIMAL, seed, spp), spp)


# --------------------------------------------------------------------------------------------
# EXR I/O

F32_LAYERS = {"color", "dx", "dy", "variance", "reference", "primal"}
COMPONENTS = {"normal": "XYZ", "depth": "Z"}


def write_bundle(path, layers, attrs=None, feature_half=True):
    """Write one multi-layer, single-part, ZIP-compressed scanline EXR with channels
    `layer.R/G/B` (`normal.X/Y/Z`, `depth.Z`). f32 for color/dx/dy/variance/reference; features
    f16 when feature_half. `attrs` go into the header (e.g. spp)."""
    channels = {}
    for name, arr in layers.items():
        arr = np.asarray(arr)
        dtype = np.float32 if (name in F32_LAYERS or not feature_half) else np.float16
        if arr.ndim == 2:
            arr = arr[..., None]
        comps = COMPONENTS.get(name, "RGB")
        if arr.shape[-1] != len(comps):
            raise ValueError(f"layer {name}: {arr.shape[-1]} components, expected {comps}")
        for i, c in enumerate(comps):
            channels[f"{name}.{c}"] = np.ascontiguousarray(arr[..., i].astype(dtype))
    write_exr(path, channels, scanline_header(attrs))


def scanline_header(attrs=None):
    """The header of every EXR written here: ZIP-compressed scan lines, plus `attrs`."""
    import OpenEXR

    return {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **(attrs or {})}


def write_exr(path, channels, header):
    """Write `channels` (name -> 2-D array) with `header`, atomically (a .tmp file renamed over
    `path`, so an interrupted run never leaves a truncated file that --skip-existing trusts)."""
    import OpenEXR

    tmp = path + ".tmp"
    OpenEXR.File(header, channels).write(tmp)
    os.replace(tmp, path)


def read_bundle(path):
    """(layers, header): layers maps layer name -> float32 array (H,W,C), in component order
    R,G,B / X,Y,Z / Z; header is the EXR header dict. Undotted channels (a plain RGB image)
    form the layer ''."""
    import OpenEXR

    f = OpenEXR.File(path, separate_channels=True)
    chans = {k: v.pixels for k, v in f.channels().items()}
    order = {"R": 0, "G": 1, "B": 2, "X": 0, "Y": 1, "Z": 2}
    groups = {}
    for name in chans:
        layer, _, comp = name.rpartition(".")
        groups.setdefault(layer, []).append(comp)
    layers = {}
    for layer, comps in groups.items():
        comps = sorted(comps, key=lambda c: order.get(c.upper(), 9))
        name = (lambda c: f"{layer}.{c}") if layer else (lambda c: c)
        layers[layer] = np.stack([chans[name(c)].astype(np.float32) for c in comps], axis=-1)
    return layers, f.header()


def add_layers(path, layers, attrs=None):
    """Add (or replace) f32 RGB layers and header attributes in an existing bundle, leaving every
    other channel (its pixels and pixel type) and every other header attribute as they are."""
    import OpenEXR

    f = OpenEXR.File(path, separate_channels=True)
    header = dict(f.header())
    channels = {k: v.pixels for k, v in f.channels().items()}
    H, W = next(iter(channels.values())).shape
    for name, arr in layers.items():
        arr = np.asarray(arr, np.float32)
        if arr.shape != (H, W, 3):
            raise ValueError(f"{path}: layer {name} has shape {arr.shape}, expected {(H, W, 3)}")
        for i, c in enumerate("RGB"):
            channels[f"{name}.{c}"] = np.ascontiguousarray(arr[..., i])
    for key in ("channels", "dataWindow", "displayWindow"):  # derived from the pixels on write
        header.pop(key, None)
    header.update(attrs or {})
    write_exr(path, channels, header)


def add_primal(paths, force=False, manifest="manifest.jsonl"):
    """Add the `primal` layer (PRIMAL_FACTOR x spp, seeds of render_primal) to existing bundles,
    rebuilding each scene from the bundle's provenance attributes. Bundles that already have one
    are skipped unless force. Appends a row per bundle to the folder's manifest."""
    files = []
    for p in paths:
        files += sorted(glob.glob(os.path.join(p, "*.exr"))) if os.path.isdir(p) else [p]
    frames = {}
    for path in files:
        layers, hdr = read_bundle(path)
        if "primal" in layers and not force:
            print(f"# skip {path}: has a primal layer", flush=True)
            continue
        name = hdr["gdrecon_scene"]
        pi = int(hdr.get("gdrecon_perturb", -1))
        pi = None if pi < 0 else pi
        pseed = int(hdr.get("gdrecon_perturb_seed", 0))
        md = hdr.get("gdrecon_max_depth")
        md = None if md is None else int(md)
        H, W = layers["color"].shape[:2]
        key = (name, pi, pseed, md, W, H)
        if key not in frames:
            frames.clear()  # one scene in memory at a time (bundles of a scene are adjacent)
            frames[key] = Frame(name, W, H, pi, pseed, md)
        spp = int(round(float(hdr["spp"])))
        pspp = PRIMAL_FACTOR * spp
        fseed = int(hdr["gdrecon_seed"])
        t1 = time.time()
        primal = render_primal(frames[key], pspp, fseed)
        dt = time.time() - t1
        add_layers(path, {"primal": primal}, {"gdrecon_primal_spp": float(pspp)})
        rec = {"file": os.path.basename(path), "op": "add_primal", "scene": name, "perturb": pi, "seed": fseed,
               "spp": spp, "primal_spp": pspp, "primal_seconds": round(dt, 2)}
        if "reference" in layers:
            rec["relmse_color"] = relmse(layers["color"], layers["reference"])
            rec["relmse_primal"] = relmse(primal, layers["reference"])
        print(json.dumps(rec), flush=True)
        if manifest:
            with open(os.path.join(os.path.dirname(os.path.abspath(path)), manifest), "a") as fh:
                fh.write(json.dumps(rec) + "\n")


# --------------------------------------------------------------------------------------------
# CLI


def parse_size(s):
    w, _, h = s.lower().partition("x")
    return int(w), int(h)


def parse_perturb(s):
    """'I' -> [I]; 'A:B' -> range(A, B); 'none' -> [None]."""
    if s is None or s.lower() == "none":
        return [None]
    if ":" in s:
        a, b = s.split(":")
        return list(range(int(a), int(b)))
    return [int(s)]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--scene", default="cornell",
                    help="scene name, split name (%s), comma list, or 'all' (%s)"
                    % (", ".join(scenes.SPLITS), ", ".join(scenes.SCENES)))
    ap.add_argument("--size", default="320x180", help="W x H of the frame (default 320x180)")
    ap.add_argument("--spp", default="16", help="comma list of spp; one bundle per value (default 16)")
    ap.add_argument("--ref-spp", type=int, default=0, help="spp of the reference layer (0: none)")
    ap.add_argument("--seed", type=int, default=1, help="render seed (noisy, feature and reference "
                    "seeds all derive from it, in disjoint streams)")
    ap.add_argument("--passes", type=int, default=4, help="k independent passes for the variance layer")
    ap.add_argument("--feature-spp", type=int, default=0, help="spp of the aov features (default max(spp, 8))")
    ap.add_argument("--perturb", default=None,
                    help="training perturbation index 'I' or range 'A:B' (default: base scene)")
    ap.add_argument("--perturb-seed", type=int, default=0, help="seed of the perturbation family")
    ap.add_argument("--primal", action="store_true",
                    help=f"add a `primal` layer: plain path tracing at {PRIMAL_FACTOR}x the bundle's spp")
    ap.add_argument("--add-primal", nargs="+", metavar="PATH", default=None,
                    help="add the primal layer to existing bundles (files or folders) and exit; "
                    "other layers and attributes stay bit-identical")
    ap.add_argument("--force", action="store_true", help="with --add-primal: replace an existing primal")
    ap.add_argument("--max-depth", type=int, default=None, help="override the integrator's max_depth")
    ap.add_argument("--no-features", action="store_true", help="skip albedo/normal/depth")
    ap.add_argument("--full-float", action="store_true", help="write features as f32 too")
    ap.add_argument("--out", default=None, help="output folder (required unless --add-primal)")
    ap.add_argument("--name", default=None, help="file name stem (default <scene>[_p<I>]_<spp>spp)")
    ap.add_argument("--skip-existing", action="store_true",
                    help="do not re-render a scene/perturbation whose bundles all exist")
    ap.add_argument("--manifest", default="manifest.jsonl", help="jsonl log in --out ('' for none)")
    args = ap.parse_args(argv)

    if args.add_primal:
        add_primal(args.add_primal, args.force, args.manifest)
        return
    if not args.out:
        ap.error("--out is required")
    try:
        names = scenes.families(args.scene)
    except KeyError as e:
        ap.error(str(e.args[0]))
    W, H = parse_size(args.size)
    spps = [int(s) for s in args.spp.split(",")]
    perturbs = parse_perturb(args.perturb)
    if perturbs != [None]:
        held_out = [n for n in names if scenes.split_of(n) != "train"]
        if held_out:
            print(f"# warning: perturbing {', '.join(held_out)}: validation/test families are never "
                  "training data (docs/data.md)", flush=True)
    os.makedirs(args.out, exist_ok=True)

    t_all = time.time()
    for pi in perturbs:
        for name in names:
            # per-frame seed: base seed combined with the scene and perturbation so frames differ
            sid = list(scenes.SCENES).index(name)
            fseed = args.seed if (pi is None and len(names) == 1) else derive_seed(args.seed, sid, -1 if pi is None else pi)
            stems = []
            for spp in spps:
                stem = args.name or (f"{name}" + ("" if pi is None else f"_p{pi:04d}") + f"_{spp}spp")
                if args.name and (len(spps) > 1 or len(names) > 1 or len(perturbs) > 1):
                    stem = f"{args.name}_{name}" + ("" if pi is None else f"_p{pi:04d}") + f"_{spp}spp"
                stems.append(stem)
            if args.skip_existing and all(os.path.exists(os.path.join(args.out, s + ".exr")) for s in stems):
                print(f"# skip {name} perturb={pi}: bundles exist", flush=True)
                continue
            frame = Frame(name, W, H, pi, args.perturb_seed, args.max_depth)
            ref = None
            t_ref = 0.0
            if args.ref_spp > 0:
                t1 = time.time()
                ref = render_reference(frame, args.ref_spp, fseed)
                t_ref = time.time() - t1
            for spp, stem in zip(spps, stems):
                t1 = time.time()
                layers = render_bundle(frame, spp, fseed, args.passes, not args.no_features,
                                       args.feature_spp or None)
                if ref is not None:
                    layers["reference"] = ref
                t_primal = 0.0
                if args.primal:
                    t2 = time.time()
                    layers["primal"] = render_primal(frame, PRIMAL_FACTOR * spp, fseed)
                    t_primal = time.time() - t2
                attrs = {
                    "spp": float(spp),
                    "gdrecon_scene": name,
                    "gdrecon_seed": int(fseed),
                    "gdrecon_perturb": -1 if pi is None else int(pi),
                    "gdrecon_perturb_seed": int(args.perturb_seed),
                    "gdrecon_passes": int(min(args.passes, spp)),
                    "gdrecon_renderer": f"mitsuba {mi.__version__} {VARIANT} path random-replay",
                }
                if ref is not None:
                    attrs["gdrecon_reference_spp"] = float(args.ref_spp)
                if args.primal:
                    attrs["gdrecon_primal_spp"] = float(PRIMAL_FACTOR * spp)
                if args.max_depth is not None:
                    attrs["gdrecon_max_depth"] = int(args.max_depth)
                path = os.path.join(args.out, stem + ".exr")
                write_bundle(path, layers, attrs, feature_half=not args.full_float)
                dt = time.time() - t1 - t_primal
                rec = {"file": os.path.basename(path), "scene": name, "perturb": pi, "seed": fseed,
                       "spp": spp, "size": [W, H], "passes": min(args.passes, spp),
                       "seconds": round(dt, 2)}
                if ref is not None:
                    rec["ref_spp"] = args.ref_spp
                    rec["ref_seconds"] = round(t_ref, 2)
                    rec["relmse_color"] = relmse(layers["color"], ref)
                if args.primal:
                    rec["primal_spp"] = PRIMAL_FACTOR * spp
                    rec["primal_seconds"] = round(t_primal, 2)
                    if ref is not None:
                        rec["relmse_primal"] = relmse(layers["primal"], ref)
                print(json.dumps(rec), flush=True)
                if args.manifest:
                    with open(os.path.join(args.out, args.manifest), "a") as fh:
                        fh.write(json.dumps(rec) + "\n")
            del frame
    print(f"# total {time.time() - t_all:.1f} s", flush=True)


if __name__ == "__main__":
    main()
