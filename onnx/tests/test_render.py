"""Tests of gdrecon_py/data/render.py: random replay is right, bundles follow docs/CONVENTIONS.md,
renders are deterministic. Runs in well under a minute on 2 cores.

    ~/.cache/gdrecon/venv/bin/python -m pytest -q onnx/tests
"""
import os

import numpy as np
import pytest

from gdrecon_py.data import render as r  # (sets the llvm_ad_rgb variant)
from gdrecon_py.metrics import relmse

W = H = 32
SPP = 4          # spp of each noisy estimate
N_SEEDS = 64     # independent noisy estimates averaged
REF_CHUNKS, REF_CHUNK_SPP = 32, 512  # converged image: 16384 spp, per-pixel variance from chunks

# Statistical test of the replayed gradient against the converged finite difference G:
#   z2 = (mean_N(est) - G)^2 / (var(mean_N(est)) + var(G))   per pixel and channel,
# with both variances estimated from the samples. For an unbiased estimator E[z2] ~ 1
# (measured: 1.05 for dx, 1.11 for dy on this scene) and about 0.3-0.5 % of z2 exceed 9.
# The tolerances below are many standard errors away from those values, and a gradient that is
# off by one pixel or taken along the wrong axis fails them by a factor of ~50-100
# (measured: mean z2 = 87 and 142).
MEAN_Z2_MAX = 1.5
FRAC_Z2_GT_9_MAX = 0.02


def z2_stats(est, G, vG):
    m = est.mean(0)
    v = est.var(0, ddof=1) / len(est)
    z2 = (m - G) ** 2 / (v + vG + 1e-8)
    return float(z2.mean()), float(np.mean(z2 > 9.0))


def unbiased(est, G, vG):
    mean_z2, frac = z2_stats(est, G, vG)
    return mean_z2 < MEAN_Z2_MAX and frac < FRAC_Z2_GT_9_MAX, (mean_z2, frac)


@pytest.fixture(scope="module")
def converged():
    """Converged (W+1) x (H+1) image of the whole film (no crop shift involved) and its
    forward differences G_x, G_y with their variances."""
    full = r.Frame("cornell", W, H, full_film=True)
    chunks = np.stack([full.render((0, 0), r.derive_seed(77, c), REF_CHUNK_SPP)
                       for c in range(REF_CHUNKS)]).astype(np.float64)
    R = chunks.mean(0)
    vR = chunks.var(0, ddof=1) / REF_CHUNKS
    gx = (R[:H, 1:W + 1] - R[:H, :W])[:, :W - 1]
    vgx = (vR[:H, 1:W + 1] + vR[:H, :W])[:, :W - 1]
    gy = (R[1:H + 1, :W] - R[:H, :W])[:H - 1]
    vgy = (vR[1:H + 1, :W] + vR[:H, :W])[:H - 1]
    return dict(R=R[:H, :W], gx=gx, vgx=vgx, gy=gy, vgy=vgy)


@pytest.fixture(scope="module")
def estimates():
    """N_SEEDS replayed dx, dy (and a non-replayed dx) at SPP each, interior pixels only."""
    f = r.Frame("cornell", W, H)
    dx, dy, dx_indep = [], [], []
    for s in range(N_SEEDS):
        seed = r.derive_seed(5, s)
        b = f.render((0, 0), seed, SPP)
        x = f.render((1, 0), seed, SPP)
        y = f.render((0, 1), seed, SPP)
        x_other = f.render((1, 0), r.derive_seed(6, s), SPP)  # no replay: different seed
        dx.append(x - b)
        dy.append(y - b)
        dx_indep.append(x_other - b)
    dx = np.array(dx, np.float64)[:, :, :W - 1]
    dy = np.array(dy, np.float64)[:, :H - 1]
    dx_indep = np.array(dx_indep, np.float64)[:, :, :W - 1]
    return dict(dx=dx, dy=dy, dx_indep=dx_indep)


def test_replayed_dx_converges_to_forward_difference(converged, estimates):
    ok, stats = unbiased(estimates["dx"], converged["gx"], converged["vgx"])
    assert ok, f"dx: mean z^2, frac(z^2 > 9) = {stats}"


def test_replayed_dy_converges_to_forward_difference(converged, estimates):
    ok, stats = unbiased(estimates["dy"], converged["gy"], converged["vgy"])
    assert ok, f"dy: mean z^2, frac(z^2 > 9) = {stats}"


def test_wrong_offsets_fail_the_same_test(converged, estimates):
    # off by one pixel: dx at x+1 compared with G at x (what render(2,0) - render(1,0) gives)
    ok, stats = unbiased(estimates["dx"][:, :, 1:], converged["gx"][:, :-1], converged["vgx"][:, :-1])
    assert not ok, f"a one-pixel shifted dx passed: {stats}"
    assert stats[0] > 10 * MEAN_Z2_MAX
    # wrong axis: dy used as dx
    ok, stats = unbiased(estimates["dy"][:, :, :W - 1], converged["gx"][:H - 1], converged["vgx"][:H - 1])
    assert not ok, f"dy passed as dx: {stats}"
    # wrong sign
    ok, stats = unbiased(-estimates["dx"], converged["gx"], converged["vgx"])
    assert not ok, f"-dx passed: {stats}"


def test_replay_correlates_the_shifted_paths(converged, estimates):
    """Replay (same seed for both crops) must cut the error of a single estimate well below
    that of two independent renders (measured ratio 0.36 here)."""
    g = converged["gx"]
    mse_replay = np.mean((estimates["dx"] - g) ** 2)
    mse_indep = np.mean((estimates["dx_indep"] - g) ** 2)
    assert mse_replay < 0.6 * mse_indep, (mse_replay, mse_indep)


def test_bundle_follows_conventions(tmp_path):
    import OpenEXR

    out = tmp_path / "frames"
    r.main(["--scene", "cornell", "--size", f"{W}x{H - 8}", "--spp", "4,8", "--ref-spp", "64",
            "--seed", "3", "--out", str(out), "--name", "t"])
    files = sorted(os.listdir(out))
    assert files == ["manifest.jsonl", "t_cornell_4spp.exr", "t_cornell_8spp.exr"], files
    for spp in (4, 8):
        path = str(out / f"t_cornell_{spp}spp.exr")
        f = OpenEXR.File(path, separate_channels=True)
        assert len(f.parts) == 1
        hdr = f.header()
        assert hdr["compression"] == OpenEXR.ZIP_COMPRESSION
        assert float(hdr["spp"]) == spp
        ch = {k: v.pixels for k, v in f.channels().items()}
        expected = {f"{layer}.{c}" for layer in ("color", "dx", "dy", "variance", "albedo", "reference")
                    for c in "RGB"} | {"normal.X", "normal.Y", "normal.Z", "depth.Z"}
        assert set(ch) == expected
        for name, px in ch.items():
            assert px.shape == (H - 8, W), (name, px.shape)
            assert np.all(np.isfinite(px)), name
            layer = name.split(".")[0]
            if layer in ("color", "dx", "dy", "variance", "reference"):
                assert px.dtype == np.float32, name
        layers, _ = r.read_bundle(path)
        assert np.all(layers["dx"][:, -1] == 0) and np.all(layers["dy"][-1] == 0)
        assert np.any(layers["dx"][:, :-1] != 0) and np.any(layers["dy"][:-1] != 0)
        assert np.all(layers["color"] >= 0) and np.all(layers["variance"] >= 0)
        assert np.all(np.abs(layers["normal"]) <= 1.001)
        assert np.all(layers["depth"] > 0)  # closed box: every camera ray hits
        # the reference is shared by both bundles and independent of the noisy render
        assert not np.array_equal(layers["reference"], layers["color"])
        assert relmse(layers["color"], layers["reference"]) < relmse(np.zeros_like(layers["color"]),
                                                                   layers["reference"])


def test_render_is_deterministic_for_a_seed():
    a = r.render_bundle(r.Frame("textures", 24, 16), 4, seed=11)
    b = r.render_bundle(r.Frame("textures", 24, 16), 4, seed=11)
    c = r.render_bundle(r.Frame("textures", 24, 16), 4, seed=12)
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    assert not np.array_equal(a["color"], c["color"])


def test_perturbations_are_deterministic_and_distinct_from_base():
    from gdrecon_py.data import scenes

    for name in scenes.SCENES:
        base = r.Frame(name, 16, 9).render((0, 0), 1, 4)
        p0 = r.Frame(name, 16, 9, perturb_index=0).render((0, 0), 1, 4)
        p0b = r.Frame(name, 16, 9, perturb_index=0).render((0, 0), 1, 4)
        p1 = r.Frame(name, 16, 9, perturb_index=1).render((0, 0), 1, 4)
        assert np.array_equal(p0, p0b), name
        assert not np.array_equal(base, p0) and not np.array_equal(p0, p1), name


def test_splits_are_disjoint_and_keep_the_validation_seeds():
    from gdrecon_py.data import scenes

    tr, va, te = (set(scenes.SPLITS[k]) for k in ("train", "val", "test"))
    assert not (tr & va) and not (tr & te) and not (va & te)
    assert tr | va | te == set(scenes.SCENES)
    # vitrine, then aquarium joined training; chandelier and conservatory (fine detail) validation
    assert len(te) == 8 and len(va) == 10 and len(tr) == 6
    # appended, so that every family rendered before keeps its index (its frame seeds)
    assert list(scenes.SCENES)[-2:] == ["chandelier", "conservatory"]
    # frame seeds hash a family's index in SCENES: the six original validation families keep 0..5
    assert list(scenes.SCENES)[:6] == ["cornell", "metals", "glass", "textures", "indirect", "sunsky"]
    assert scenes.families("val") == scenes.SPLITS["val"]
    assert scenes.families("test,cornell") == scenes.SPLITS["test"] + ["cornell"]
    assert all(scenes.split_of(n) == k for k, v in scenes.SPLITS.items() for n in v)
    assert not set(scenes.RETIRED_TRAIN) & tr
    with pytest.raises(KeyError):
        scenes.families("nope")


def test_primal_is_deterministic_and_has_its_own_seeds():
    seed, spp = 11, 8
    streams = {r.derive_seed(r.NOISY, seed, s, p) for s in (spp // 2, spp) for p in range(4)}
    streams |= {r.derive_seed(r.FEATURES, seed, s) for s in (spp // 2, spp)}
    streams |= {r.derive_seed(r.REFERENCE, seed, c) for c in range(4)}
    assert r.derive_seed(r.PRIMAL, seed, spp, 0) not in streams
    f = r.Frame("cornell", 24, 16)
    a = r.render_primal(f, spp, seed)
    b = r.render_primal(r.Frame("cornell", 24, 16), spp, seed)
    assert a.shape == (16, 24, 3) and a.dtype == np.float32 and np.all(np.isfinite(a))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, r.render_primal(f, spp, seed + 1))
    # not a replay of the reference chunks (same seed and spp)
    assert not np.array_equal(a, r.render_reference(f, spp, seed))


def test_add_primal_leaves_other_layers_identical(tmp_path):
    import shutil

    import OpenEXR

    def raw(path):
        f = OpenEXR.File(path, separate_channels=True)
        return {k: v.pixels.copy() for k, v in f.channels().items()}, dict(f.header())

    cmd = ["--scene", "textures", "--size", "20x12", "--spp", "4,8", "--ref-spp", "32", "--seed", "5"]
    r.main(cmd + ["--out", str(tmp_path / "plain")])
    r.main(cmd + ["--out", str(tmp_path / "fresh"), "--primal"])
    shutil.copytree(tmp_path / "plain", tmp_path / "added")
    r.main(["--add-primal", str(tmp_path / "added")])
    for spp in (4, 8):
        name = f"textures_{spp}spp.exr"
        before, hb = raw(str(tmp_path / "plain" / name))
        after, ha = raw(str(tmp_path / "added" / name))
        fresh, hf = raw(str(tmp_path / "fresh" / name))
        assert set(after) == set(before) | {"primal.R", "primal.G", "primal.B"}
        for k, v in before.items():
            assert after[k].dtype == v.dtype and np.array_equal(after[k], v), k
        assert float(ha["gdrecon_primal_spp"]) == 2 * spp
        for k, v in hb.items():
            if k not in ("channels",):
                assert k in ha and str(ha[k]) == str(v), k
        # adding later gives the same primal as rendering with --primal
        for c in "RGB":
            assert after[f"primal.{c}"].dtype == np.float32
            assert np.array_equal(after[f"primal.{c}"], fresh[f"primal.{c}"])
        layers, _ = r.read_bundle(str(tmp_path / "added" / name))
        assert relmse(layers["primal"], layers["reference"]) < relmse(layers["color"], layers["reference"]) * 1.5
    # a second run skips bundles that have a primal
    mtime = os.path.getmtime(tmp_path / "added" / "textures_4spp.exr")
    r.main(["--add-primal", str(tmp_path / "added" / "textures_4spp.exr")])
    assert os.path.getmtime(tmp_path / "added" / "textures_4spp.exr") == mtime


def test_emitter_order_is_deterministic():
    """Mitsuba orders the emitters of rectangle/mesh shapes nondeterministically (a scene with two
    emissive rectangles rendered different pixels for one seed from run to run), so each family
    has at most one; loading is serial (render.Frame) so the other emitters keep dict order."""
    from gdrecon_py.data import scenes

    for name, build in scenes.SCENES.items():
        for rng in (None, np.random.default_rng(0)):
            d = build(16, 9, rng)
            n = sum(1 for v in d.values() if isinstance(v, dict) and "emitter" in v
                    and v.get("type") in ("rectangle", "cube", "obj", "ply"))
            assert n <= 1, (name, n)
    sigs = set()
    for _ in range(4):
        f = r.Frame("dusk", 16, 9)
        sigs.add(tuple("env" if e.get_shape() is None else round(e.get_shape().bbox().center().x, 3)
                       for e in f.scene.emitters()))
    assert len(sigs) == 1, sigs
