"""Fine-tuning against references (gdrecon_py.qat_ref): the crops keep the reference aligned
with the noisy frame through every augmentation, and the loss is the one its docstring states."""
import math

import pytest
import torch

from gdrecon_py import gradnet as gn
from gdrecon_py import qat, qat_ref


def frames(n=3, h=40, w=40, seed=0):
    """n x 19 x h x w: the reference a known function of the colour (2 x colour + 0.1), the
    gradients the colour's forward differences (last column / row 0, as rendered)."""
    g = torch.Generator().manual_seed(seed)
    col = torch.rand(n, 3, h, w, generator=g)
    dx = torch.zeros_like(col)
    dx[..., :-1] = col[..., 1:] - col[..., :-1]
    dy = torch.zeros_like(col)
    dy[..., :-1, :] = col[..., 1:, :] - col[..., :-1, :]
    feat = torch.rand(n, 7, h, w, generator=g)
    return torch.cat([col, dx, dy, feat, 2 * col + 0.1], 1)


def test_crops_keep_the_reference_aligned_and_exposed_alike():
    arr = frames()
    gen = torch.Generator().manual_seed(3)
    for _ in range(4):
        x = qat_ref.sample(arr, gen, 8, 24, exposure=2.0)
        col, dx, dy, ref = x[:, 0:3], x[:, 3:6], x[:, 6:9], x[:, 16:19]
        # exposure s: ref' = s (2 c + 0.1) and c' = s c, so ref' - 2 c' = 0.1 s, one s per crop
        s = (ref - 2 * col) / 0.1
        assert torch.allclose(s, s[:, :1, :1, :1].expand_as(s), rtol=1e-4, atol=1e-4)
        assert float(s.min()) >= 0.25 - 1e-4 and float(s.max()) <= 4.0 + 1e-4
        # gradients stay the colour's forward differences after rotations and mirrors
        assert torch.allclose(dx[..., :-1], col[..., 1:] - col[..., :-1], atol=1e-5)
        assert torch.allclose(dy[..., :-1, :], col[..., 1:, :] - col[..., :-1, :], atol=1e-5)


def _nets():
    torch.manual_seed(0)
    net = gn.GradNet().eval()
    ranges = {k: (0.01, 10) for k in qat.ACT_NAMES}
    return qat.QATGradNet(net, ranges), net


def test_loss_is_the_teacher_weighted_relmse():
    from gdrecon_py.mulaw import mulaw_inv
    from gdrecon_py.train import split_batch
    student, teacher = _nets()
    x = qat_ref.sample(frames(), torch.Generator().manual_seed(1), 2, 32, exposure=0.0)
    data, grad = split_batch(x[:, :16])[:2]
    with torch.no_grad():
        lt = mulaw_inv(teacher(data, grad))
        ly = mulaw_inv(student(data, grad))
    ref = x[:, 16:19].reshape(lt.shape)
    w = 1 / (lt ** 2 + 0.01)
    want = float(((ly - ref) ** 2 * w).mean() + 0.5 * ((ly - lt) ** 2 * w).mean())
    with torch.no_grad():
        got = float(qat_ref.loss_of(student, teacher, x, dist=0.5, clip=0.0))
    assert math.isclose(got, want, rel_tol=1e-5)
    # the cap bounds every pixel's term
    with torch.no_grad():
        capped = float(qat_ref.loss_of(student, teacher, x, dist=0.0, clip=1e-3))
    assert capped <= 1e-3 + 1e-9
    # the student switched to fp32 against references equal to the teacher: nothing to learn
    student.quant = False
    y = x.clone()
    y[:, 16:19] = lt.reshape(2, 3, 32, 32)
    with torch.no_grad():
        assert float(qat_ref.loss_of(student, teacher, y, dist=1.0, clip=0.0)) < 1e-12


def test_schedule_warms_up_then_decays_to_zero():
    assert qat_ref.lr_at(0, 300, 1e-5, 20) == pytest.approx(1e-5 / 20)
    assert qat_ref.lr_at(19, 300, 1e-5, 20) <= 1e-5
    assert qat_ref.lr_at(150, 300, 1e-5, 20) == pytest.approx(0.5e-5)
    assert qat_ref.lr_at(299, 300, 1e-5, 20) < 1e-9


def test_an_empty_folder_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="no bundles"):
        qat_ref.load_frames(str(tmp_path), set())


def _bundles(folder, n=2, size=24):
    """n bundles of a training family with a reference layer (the reference 2 x colour + 0.1)."""
    from gdrecon_py.data.render import write_bundle
    arr = frames(n, size, size, seed=5).numpy().transpose(0, 2, 3, 1)
    for i in range(n):
        a = arr[i]
        write_bundle(str(folder / f"cornell_p{i:04d}_4spp.exr"),
                     {"color": a[..., 0:3], "dx": a[..., 3:6], "dy": a[..., 6:9], "albedo": a[..., 9:12],
                      "normal": a[..., 12:15] * 2 - 1, "depth": a[..., 15:16], "reference": a[..., 16:19]},
                     {"spp": 4.0}, feature_half=False)


def stopped_and_resumed(monkeypatch, args):
    """Run `qat_ref` with `args` (4 steps, saved every 2), stop it in its third step, run it again
    (it resumes from the save after step 2) and return the final checkpoint."""
    calls, loss_of = [], qat_ref.loss_of

    def stop_at_the_third_step(*a, **k):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return loss_of(*a, **k)
    monkeypatch.setattr(qat_ref, "loss_of", stop_at_the_third_step)
    with pytest.raises(KeyboardInterrupt):
        qat_ref.main(args)
    monkeypatch.setattr(qat_ref, "loss_of", loss_of)
    out = args[args.index("--out") + 1]
    assert torch.load(f"{out}/last.pt", weights_only=False)["step"] == 2
    qat_ref.main(args)
    return torch.load(f"{out}/last.pt", weights_only=False)


def test_fp32_fine_tuning_resumes_and_exports_with_its_provenance(tmp_path, monkeypatch):
    """`--fp32`: the plain network trains, a run stopped after a save and started again ends with
    the weights of an uninterrupted one, and the export finds the start graph in the manifest and
    records the fine-tuning after its training."""
    import json

    from gdrecon_py import export as ex
    data = tmp_path / "data"
    data.mkdir()
    _bundles(data)
    torch.manual_seed(0)
    net = gn.GradNet().eval()
    with torch.no_grad():
        net.out.bias.fill_(0.4)         # as train_gradnet starts (a live final ReLU)
    start = str(tmp_path / "start.onnx")
    ex.export_model(net, start)
    sha = ex.sha256_file(start)
    common = ["--fp32", "--start", start, "--data", str(data), "--skip", "", "--batch", "1", "--steps", "4",
              "--patch", "16", "--lr", "1e-4", "--warmup", "1", "--save-every", "2", "--threads", "1"]
    qat_ref.main(common + ["--out", str(tmp_path / "whole")])
    whole = torch.load(tmp_path / "whole" / "last.pt", weights_only=False)
    assert whole["precision"] == "fp32" and whole["start_sha256"] == sha and whole["step"] == 4
    before = ex.net_from_onnx(start).state_dict()
    assert any(not torch.equal(before[k], v) for k, v in whole["net"].items())

    split = stopped_and_resumed(monkeypatch, common + ["--out", str(tmp_path / "split")])
    assert split["step"] == 4 and all(torch.equal(whole["net"][k], v) for k, v in split["net"].items())

    manifest = tmp_path / "models.json"
    manifest.write_text(json.dumps({"models": {"start.onnx": {
        "sha256": sha, "variant": "full", "epochs_trained": 16, "train_seconds": 495,
        "train_args": {"lr": 4e-4}}}}))
    prov = ex.provenance(whole, str(manifest))
    assert prov["epochs_trained"] == 16 and prov["train_args"] == {"lr": 4e-4}
    (run,) = prov["fine_tuned"]
    assert run["start_sha256"] == sha and run["steps"] == 4 and run["args"]["fp32"]
    # a fine-tuning of that export appends to the list
    manifest.write_text(json.dumps({"models": {"x.onnx": {"sha256": "ab" * 32, **prov}}}))
    assert len(ex.provenance(dict(whole, start_sha256="ab" * 32), str(manifest))["fine_tuned"]) == 2
    with pytest.raises(SystemExit, match="not in"):
        ex.provenance(dict(whole, start_sha256="cd" * 32), str(manifest))
    with pytest.raises(SystemExit, match="quantise"):
        ex.provenance(dict(whole, precision="int8"), str(manifest))


def test_learned_ranges_resume_and_reach_the_int8_graph(tmp_path, monkeypatch):
    """`--learn-ranges`: the scales move, a run stopped after a save and started again ends with
    the uninterrupted run's weights and scales, and `qat quantize` writes the checkpoint's own
    ranges into the QDQ graph (no --ranges needed)."""
    from gdrecon_py import ONNX_DIR
    data = tmp_path / "data"
    data.mkdir()
    _bundles(data)
    start = f"{ONNX_DIR}/gradnet_int8.onnx"
    common = ["--start", start, "--data", str(data), "--skip", "", "--batch", "1", "--steps", "4",
              "--patch", "16", "--lr", "1e-4", "--warmup", "1", "--save-every", "2", "--threads", "1",
              "--learn-ranges", "1e-2"]
    qat_ref.main(common + ["--out", str(tmp_path / "whole")])
    whole = torch.load(tmp_path / "whole" / "last.pt", weights_only=False)
    before = qat.deployed(qat.ranges_from_int8(start))
    assert whole["precision"] == "int8" and "LSQ" in whole["fine_tuned"]
    assert any(abs(whole["ranges"][k][0] / before[k][0] - 1) > 1e-3 for k in before)

    split = stopped_and_resumed(monkeypatch, common + ["--out", str(tmp_path / "split")])
    assert torch.equal(split["log_scales"], whole["log_scales"]) and split["ranges"] == whole["ranges"]
    assert all(torch.equal(whole["net"][k], v) for k, v in split["net"].items())

    out = str(tmp_path / "lsq_int8.onnx")
    qat.main(["quantize", "--ckpt", str(tmp_path / "whole" / "last.pt"), "--out", out, "--data", str(data),
              "--frames", "2", "--no-manifest"])
    got = qat.ranges_from_int8(out)
    assert tuple(got) == tuple(before)
    for k in got:
        assert abs(got[k][0] - whole["ranges"][k][0]) <= 1e-12 and got[k][1] == whole["ranges"][k][1], k


def test_a_run_starts_from_the_narrowed_ranges(tmp_path, leaky_int8):
    """`--negative-fraction`: the ranges simulated, and saved for `qat quantize`, are the start
    graph's narrowed (`qat.narrow_negatives`), and a fixed-range run keeps them."""
    data = tmp_path / "data"
    data.mkdir()
    _bundles(data)
    start = leaky_int8
    qat_ref.main(["--start", start, "--data", str(data), "--skip", "", "--batch", "1", "--steps", "1",
                  "--patch", "16", "--warmup", "1", "--threads", "1", "--negative-fraction", "0.5",
                  "--out", str(tmp_path / "run")])
    ck = torch.load(tmp_path / "run" / "last.pt", weights_only=False)
    want = qat.deployed(qat.narrow_negatives(qat.ranges_from_int8(start), 0.5))
    assert ck["ranges"] == {k: (float(torch.tensor(want[k][0])), want[k][1]) for k in qat.ACT_NAMES}
    assert "cut to 0.5" in ck["fine_tuned"] and "log_scales" not in ck
    for flag in (["--negative-fraction", "0.5"], ["--learn-ranges", "1e-3"]):
        with pytest.raises(SystemExit, match="fp32 run has no activation ranges"):
            qat_ref.main(["--fp32", "--start", start, "--out", str(tmp_path / "fp32"), *flag])


def test_a_relu_run_starts_from_the_relu_ranges_and_quantizes_to_the_relu_graph(tmp_path, leaky_int8):
    """`--relu` from a LeakyReLU int8 graph: the student is the ReLU network with the start
    graph's weights, its ranges `qat.relu_ranges` of the start graph's; the checkpoint says so and
    `qat quantize` makes the ReLU graph (its metadata, its 31 tensors at the checkpoint's ranges),
    from which a further run continues without `--relu`. `--negative-fraction` is refused with
    it (no tensor before an activation is quantised) and for a ReLU start graph."""
    import onnx
    data = tmp_path / "data"
    data.mkdir()
    _bundles(data)
    start = leaky_int8
    common = ["--data", str(data), "--skip", "", "--batch", "1", "--steps", "1", "--patch", "16",
              "--warmup", "1", "--threads", "1"]
    qat_ref.main(["--start", start, "--relu", "--out", str(tmp_path / "run"), *common])
    ck = torch.load(tmp_path / "run" / "last.pt", weights_only=False)
    want = qat.deployed(qat.relu_ranges(qat.ranges_from_int8(start)))
    assert ck["activation"] == "relu" and "ReLU graph" in ck["fine_tuned"]
    assert ck["ranges"] == {k: (float(torch.tensor(want[k][0])), want[k][1]) for k in qat.ACT_NAMES_RELU}
    out = str(tmp_path / "relu_int8.onnx")
    qat.main(["quantize", "--ckpt", str(tmp_path / "run" / "last.pt"), "--out", out, "--data", str(data),
              "--frames", "2", "--no-manifest"])
    assert {p.key: p.value for p in onnx.load(out).metadata_props}["activation"] == "relu"
    got = qat.ranges_from_int8(out)
    assert all(abs(got[k][0] - ck["ranges"][k][0]) <= 1e-12 and got[k][1] == ck["ranges"][k][1] for k in got)
    qat_ref.main(["--start", out, "--out", str(tmp_path / "again"), *common])
    assert torch.load(tmp_path / "again" / "last.pt", weights_only=False)["activation"] == "relu"
    with pytest.raises(SystemExit, match="ReLU graph quantises no convolution output"):
        qat_ref.main(["--start", start, "--relu", "--negative-fraction", "0.5", "--out", str(tmp_path / "x"), *common])
    with pytest.raises(SystemExit, match="is a ReLU graph"):
        qat_ref.main(["--start", out, "--negative-fraction", "0.5", "--out", str(tmp_path / "y"), *common])
    with pytest.raises(SystemExit, match="fp32 run has no activation ranges"):
        qat_ref.main(["--fp32", "--relu", "--start", start, "--out", str(tmp_path / "fp32")])
