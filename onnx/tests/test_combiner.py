"""The combiner's Python side: the weighted sum is a convex combination of the candidates, the
reference `combine` pads, mixes and crops as the Rust side does and equals the model's forward
(the mean guard off), the guard's window means and verdict,
an export (the head: features in, logits out) matches torch through onnxruntime, and the
checkpoint rule. (Resuming a training run bit for bit was checked by hand:
`--stop-at 20` then a rerun gives the uninterrupted run's losses to the last digit.)"""
import json

import numpy as np
import pytest
import torch

from gdrecon_py import combiner as cb


def random_input(n=2, h=16, w=20, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, cb.IN_CHANNELS, h, w, generator=g) * 3
    x[:, 21:27] -= 1.5  # gradients are signed
    return x


@pytest.mark.parametrize("mixed", [3, 4])
def test_output_is_a_convex_combination_of_the_mixed_candidates(mixed):
    torch.manual_seed(1)
    m = cb.Combiner(mixed=mixed).eval()
    x = random_input()
    with torch.no_grad():
        w = m.weights(x)
        out = m(x)
    assert w.shape[1] == mixed
    assert torch.allclose(w.sum(1), torch.ones_like(w[:, 0]), atol=1e-6)
    cands = x[:, : 3 * mixed].reshape(2, mixed, 3, 16, 20)
    assert (out >= cands.min(1).values - 1e-5).all() and (out <= cands.max(1).values + 1e-5).all()


def test_taps_weight_each_candidate_at_its_neighbours():
    torch.manual_seed(2)
    m = cb.Combiner(taps=3, mixed=3).eval()
    x = random_input(h=12, w=8)
    with torch.no_grad():
        w, out = m.weights(x), m(x)
    p = torch.nn.functional.pad(x[:, :9], (1, 1, 1, 1), mode="replicate")
    want = 0
    for k in range(3):
        for t in range(9):
            dy, dx = divmod(t, 3)
            want = want + w[:, k * 9 + t:k * 9 + t + 1] * p[:, 3 * k:3 * k + 3, dy:dy + 12, dx:dx + 8]
    assert torch.allclose(out, want, atol=1e-6)


def test_combine_repeats_the_last_row_and_column_and_crops():
    seen = {}

    def run(f):
        seen["features"] = f
        return np.zeros((1, 3) + f.shape[2:], np.float32)  # equal weights

    x = np.random.default_rng(0).random((cb.IN_CHANNELS, 9, 6), dtype=np.float32)
    out = cb.combine(x, run)
    f = seen["features"]
    assert f.shape == (1, cb.FEATURES, 12, 8)
    # the features of the repeated rows and columns are those of the last ones (the
    # forward differences there are 0 in both), which is what lets the library compute them
    # from the frame with clamped coordinates instead of padding the frame
    assert np.array_equal(f[0, :, 11, :6], f[0, :, 8, :6])
    assert np.array_equal(f[0, :, :9, 7], f[0, :, :9, 5])
    assert out.shape == (3, 9, 6)
    assert np.allclose(out, x[:9].reshape(3, 3, 9, 6).mean(0), atol=1e-6)


def test_combine_without_the_guard_is_the_models_forward():
    torch.manual_seed(4)
    m = cb.Combiner(mixed=3).eval()
    x = random_input(n=1, h=13, w=10)[0].numpy()
    with torch.no_grad():
        got = cb.combine(x, lambda f: m.head(torch.from_numpy(f)).numpy(), tolerance=0)
        want = m(torch.from_numpy(cb.pad(x))).numpy()[0, :, :13, :10]
    assert np.allclose(got, want, atol=1e-6)


def test_box_mean_is_the_clamped_window_mean():
    rng = np.random.default_rng(5)
    img = rng.random((7, 12))  # smaller than the window one way
    got = cb.box_mean(img, 9)
    for y in range(7):
        for x in range(12):
            ys = np.clip(np.arange(y - 4, y + 5), 0, 6)
            xs = np.clip(np.arange(x - 4, x + 5), 0, 11)
            assert abs(got[y, x] - img[np.ix_(ys, xs)].mean()) < 1e-12


def test_the_guard_drops_a_candidate_that_loses_a_regions_energy():
    h, w = 30, 40
    x = np.ones((cb.IN_CHANNELS, h, w), np.float32)
    x[6:9, 10:22, 12:24] = 0.2  # the weak candidate loses a 12 x 12 block's energy
    drop = cb.dropped(x, 3, 0.4)
    assert not drop[0].any() and not drop[1].any()
    assert drop[2, 16, 18] and not drop[2, 2, 2]
    # equal logits: where the weak candidate is dropped the prior and the strong one share the
    # weight (1 inside the block), elsewhere all three do
    out = cb.combine(x, lambda f: np.zeros((1, 3) + f.shape[2:], np.float32))
    assert np.allclose(out[:, 16, 18], 1.0) and np.allclose(out[:, 2, 2], 1.0)
    # the block's corner pixel: its window holds 36 of the block's pixels, a departure of
    # 0.8 * 36 / 81 = 0.36 < 0.4 * 1.01, so the weak candidate keeps its share there
    assert not drop[2, 10, 12] and np.allclose(out[:, 10, 12], (2 + 0.2) / 3)
    assert not cb.dropped(x, 3, 0).any()


def test_an_export_matches_torch_through_onnxruntime(tmp_path):
    torch.manual_seed(3)
    m = cb.Combiner(mixed=3)
    path = tmp_path / "c.onnx"
    worst = cb.export(m, str(path), {"mixed": 3})
    assert worst < 1e-4
    back = cb.model_from_onnx(str(path))
    x = random_input()
    with torch.no_grad():
        assert torch.allclose(back(x), m.eval()(x), atol=1e-6)
    manifest = json.loads((tmp_path / "models.json").read_text())
    assert manifest["models"]["c.onnx"]["sha256"] == (tmp_path / "c.onnx.sha256").read_text().split()[0]


def test_the_checkpoint_rule_prefers_safe_steps_then_the_lowest_worst():
    log = [{"step": 1, "val_vs_prior": 0.70, "val_worst": ["a", 1.20]},
           {"step": 2, "val_vs_prior": 0.80, "val_worst": ["a", 1.04]},
           {"step": 3, "val_vs_prior": 0.75, "val_worst": ["a", 1.05]}]
    assert cb.choose(log)["step"] == 3
    unsafe = [dict(e, val_worst=["a", e["val_worst"][1] + 0.1]) for e in log]
    assert cb.choose(unsafe)["step"] == 2
