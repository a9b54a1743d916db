"""The pieces of the GPU trainer that can be wrong silently: the pack's rounding and round trip,
the exact gradients of the augmented crops, the checkpoint parts, and one short training run."""
import json
import os

import numpy as np
import pytest
import torch

from gdrecon_py import gradnet as gn
from gdrecon_py import pack
from gdrecon_py import train_gradnet as tg


def forward_differences(img):
    """img: ... x H x W -> (dx, dy) with the stored-zero last column / row (docs/CONVENTIONS.md)."""
    dx = torch.zeros_like(img)
    dy = torch.zeros_like(img)
    dx[..., :, :-1] = img[..., :, 1:] - img[..., :, :-1]
    dy[..., :-1, :] = img[..., 1:, :] - img[..., :-1, :]
    return dx, dy


def planes_of(img, feat):
    dx, dy = forward_differences(img)
    return torch.cat([img, dx, dy, feat], 1)


@pytest.mark.parametrize("code", range(8))
def test_dihedral_gradients_are_those_of_the_transformed_image(code):
    g = torch.Generator().manual_seed(code)
    img = torch.rand(2, 3, 12, 12, generator=g)
    feat = torch.rand(2, 7, 12, 12, generator=g)
    x = planes_of(img, feat)
    got = tg.dihedral_apply(x, torch.full((2,), code))
    # transform the image (and features) alone, then take its differences: the reference
    t = img.clone()
    f = feat.clone()
    if code & 1:
        t, f = t.transpose(2, 3), f.transpose(2, 3)
    if code & 2:
        t, f = t.flip(3), f.flip(3)
    if code & 4:
        t, f = t.flip(2), f.flip(2)
    want = planes_of(t, f)
    assert torch.allclose(got, want, atol=1e-6), code


def test_round_half_is_unbiased_and_bounded():
    rng = np.random.default_rng(0)
    a = rng.lognormal(0, 2, 200_000).astype(np.float32) * rng.choice([-1, 1], 200_000)
    a = np.clip(a, -6e4, 6e4)
    for bits in (5, 7):
        r = pack.round_half(a, bits).astype(np.float32)
        normal = np.abs(a) > 6.2e-5                      # float16's subnormals are absolute
        rel = np.abs(r[normal] - a[normal]) / np.abs(a[normal])
        assert rel.max() <= 2.0 ** -(bits + 1) + 2.0 ** -11, bits   # float16 first, then the mantissa
        assert abs(np.mean((r[normal] - a[normal]) / np.abs(a[normal]))) < 1e-4, bits
        assert np.isfinite(r).all()


def test_pack_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    arrays = {"144x144": pack.round_half(rng.random((2, 16, 8, 8))),
              "0/depth": rng.random((8, 8, 1)).astype(np.float32)}
    path = str(tmp_path / "p.xz")
    pack.write(path, arrays, {"kind": "train"})
    meta, back = pack.read(path)
    assert meta == {"kind": "train"}
    for k, a in arrays.items():
        assert back[k].dtype == a.dtype and np.array_equal(back[k], a), k


def test_checkpoint_parts_round_trip(tmp_path):
    net = torch.nn.Sequential(torch.nn.Linear(64, 64), torch.nn.Linear(64, 8))
    state = {"net": net.state_dict(), "epoch": 3, "variant": "full"}
    paths = tg.save_parts(state, str(tmp_path / "w"), limit=64 * 64 * 4)
    assert len(paths) >= 2
    back = tg.merge_parts(str(tmp_path / "w"))
    assert back["epoch"] == 3 and back["variant"] == "full"
    for k, v in net.state_dict().items():
        assert torch.equal(back["net"][k], v), k


def test_short_run_trains_validates_and_resumes(tmp_path):
    """Two epochs of two steps on a synthetic pack, then a resumed third: losses finite, the
    validation row per frame written, the resumed run continues from the saved epoch."""
    rng = np.random.default_rng(2)
    H = W = 32
    img = rng.random((3, 3, H, W)).astype(np.float32)
    tr = []
    for i in range(3):
        t = torch.from_numpy(img[i:i + 1])
        x = planes_of(t, torch.rand(1, 7, H, W)).numpy()[0]
        tr.append(pack.round_half(x))
    pack.write(str(tmp_path / "t.xz"), {f"{W}x{H}": np.stack(tr)}, {"kind": "train"})
    va = {}
    for k, shape in [("color", 3), ("dx", 3), ("dy", 3), ("albedo", 3), ("normal", 3), ("depth", 1),
                     ("reference", 3)]:
        va[f"0/{k}"] = pack.round_half(rng.random((H, W, shape)))
    pack.write(str(tmp_path / "v.xz"), va, {"kind": "val", "frames": [{"file": "a.exr", "spp": 4}]})
    common = ["--train", str(tmp_path / "t.xz"), "--val", str(tmp_path / "v.xz"), "--out",
              str(tmp_path / "run"), "--device", "cpu", "--steps", "2", "--batch", "2", "--patch", "16",
              "--threads", "1"]
    tg.main(common + ["--epochs", "2"])
    tg.main(common + ["--epochs", "3", "--export", str(tmp_path / "exp")])
    rows = [json.loads(line) for line in open(tmp_path / "run" / "log.jsonl")]
    epochs = [r for r in rows if r["kind"] == "epoch"]
    assert [r["epoch"] for r in epochs] == [0, 1, 2]
    assert all(np.isfinite(r["total"]) and np.isfinite(r["val"]) for r in epochs)
    assert sum(r["kind"] == "val" for r in rows) == 3
    ck = tg.merge_parts(str(tmp_path / "exp" / "last"))
    assert ck["epoch"] == 2 and os.path.exists(tmp_path / "exp" / "log.jsonl")


def test_continuation_starts_from_the_given_weights(tmp_path):
    """`--init` (fp16 .pt) with a cosine schedule, a G warm-up and a snapshot: the first logged
    step runs on the given weights (warm-up lr below the peak), the rate ends at the floor, and
    the snapshot and the last export both come back."""
    rng = np.random.default_rng(3)
    H = W = 32
    tr = []
    for i in range(2):
        t = torch.from_numpy(rng.random((1, 3, H, W)).astype(np.float32))
        tr.append(pack.round_half(planes_of(t, torch.rand(1, 7, H, W)).numpy()[0]))
    pack.write(str(tmp_path / "t.xz"), {f"{W}x{H}": np.stack(tr)}, {"kind": "train"})
    torch.manual_seed(5)
    start = gn.GradNet()
    torch.save({k: v.half() for k, v in start.state_dict().items()}, tmp_path / "init.pt")
    args = ["--train", str(tmp_path / "t.xz"), "--out", str(tmp_path / "run"), "--device", "cpu",
            "--steps", "2", "--batch", "2", "--patch", "16", "--threads", "1", "--epochs", "3",
            "--init", str(tmp_path / "init.pt"), "--epoch-offset", "16", "--g-warmup", "2",
            "--schedule", "cosine", "--warmup-steps", "2", "--lr", "1e-3", "--log-every", "1",
            "--snapshot-every", "2", "--export", str(tmp_path / "exp")]
    got = tg.init_state(str(tmp_path / "init.pt"))
    for k, v in start.state_dict().items():
        assert got[k].dtype == torch.float32 and torch.equal(got[k], v.half().float()), k
    tg.main(args)
    rows = [json.loads(line) for line in open(tmp_path / "run" / "log.jsonl")]
    assert rows[0]["kind"] == "g_warmup" and np.isfinite(rows[0]["lprime"])
    mains = [r for r in rows if r["kind"] == "main"]
    assert len(mains) == 6
    f = tg.cosine(2, 6)
    assert [r["lr"] for r in mains] == pytest.approx([1e-3 * f(t) for t in range(6)])
    assert mains[0]["lr"] == pytest.approx(0.5e-3) and f(6) == pytest.approx(0.01)
    assert all(r["lambda"] == pytest.approx(tg.lambda_f(16 + r["epoch"])) for r in mains)
    snap = tg.merge_parts(str(tmp_path / "exp" / "snap1"))
    last = tg.merge_parts(str(tmp_path / "exp" / "last"))
    assert snap["epoch"] == 1 and last["epoch"] == 2
    assert not os.path.exists(tmp_path / "exp" / "snap2-0.pt")
    moved = [k for k, v in last["net"].items() if not torch.equal(v, start.state_dict()[k].half().float())]
    assert moved
    # At a rate of 0 the run must hand back exactly the weights it was given.
    still = args[:args.index("--out") + 1] + [str(tmp_path / "run0")] + args[args.index("--out") + 2:]
    still[still.index("--lr") + 1] = "0"
    still[still.index("--export") + 1] = str(tmp_path / "exp0")
    tg.main(still)
    back = tg.merge_parts(str(tmp_path / "exp0" / "last"))["net"]
    assert all(torch.equal(v, got[k]) for k, v in back.items())
