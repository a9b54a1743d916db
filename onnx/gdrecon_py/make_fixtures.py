"""Write the GradNet parity fixtures the Rust tests compare against (tests/fixtures/gradnet/).

Everything comes from the torch reference model (the training checkpoints, not the ONNX
export) and the numpy reference pipeline (gdrecon_py/pipeline.py):

  crop_a.exr, crop_b.exr        two crops of examples/data/sample.exr (45 x 37: padded on both
                                axes; 56 x 40: no padding), every layer f32, the last dx column
                                and dy row zero (the gradient convention)
  <crop>_data.npy, _grad.npy    pipeline.prepare_inputs with features: 3 x 8 x Hp x Wp, 3 x 2 x Hp x Wp
  <crop>_torch.npy              the torch full model on those inputs: 3 x 1 x Hp x Wp
  <crop>_out.npy                pipeline.reconstruct with the torch full model: H x W x 3
  <crop>_out_nobias.npy         the same without the bias correction
  <crop>_nofeat_out.npy         pipeline.reconstruct with the torch no-feature model
  bias_out.npy, bias_color.npy, bias_corrected.npy
                                pipeline.bias_correct on random 23 x 61 x 3 data
  emitter.exr, emitter_out.npy  (--emitter, no checkpoints needed) the guard frame
                                tests/data/guard/lamps_16spp.exr (bulbs of radiance up to 424 in
                                view) through pipeline.reconstruct with onnx/gradnet.onnx run by
                                onnxruntime: steps 6b (emitters) and 7's bias limit
                                (beyond) are exercised
  <crop>_int8_net.npy           (--int8, no checkpoints needed) onnx/gradnet_int8_nhwc.onnx (the
                                deployed int8 graph, the one the library embeds) run by
                                onnxruntime on <crop>_data / _grad, one channel at a time:
                                3 x 1 x Hp x Wp
  <crop>_int8_out.npy           pipeline.reconstruct with that graph (onnxruntime): H x W x 3

Run (needs the checkpoints of docs/gradnet.md, or `--full` / `--nofeat` naming a checkpoint or
an exported graph whose weights the torch model takes; takes a few seconds):
    source onnx/env.sh
    $GDRECON_PYTHON -m gdrecon_py.make_fixtures [--full RUN/last.pt] [--nofeat onnx/gradnet_nofeat.onnx]
"""
import argparse
import os

import numpy as np
import torch

from . import REPO
from . import export as ex
from . import pipeline as pl
from .data.render import write_bundle

RUNS = os.path.expanduser("~/.cache/gdrecon/train_runs")
CROPS = {"crop_a": (60, 100, 37, 45), "crop_b": (100, 200, 40, 56)}   # y0, x0, h, w
LAYERS = ("color", "dx", "dy", "albedo", "normal", "depth", "variance", "reference")


def crop(frame, y0, x0, h, w):
    out = {}
    for k in LAYERS:
        if frame.get(k) is not None:
            out[k] = np.ascontiguousarray(frame[k][y0:y0 + h, x0:x0 + w], np.float32)
    out["dx"][:, -1] = 0.0
    out["dy"][-1, :] = 0.0
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=os.path.join(REPO, "tests", "fixtures", "gradnet"))
    ap.add_argument("--full", default=os.path.join(RUNS, "full", "last.pt"), help="checkpoint or .onnx")
    ap.add_argument("--nofeat", default=os.path.join(RUNS, "nofeat", "last.pt"), help="checkpoint or .onnx")
    ap.add_argument("--emitter", action="store_true",
                    help="write only the emitter fixture (onnxruntime and onnx/gradnet.onnx)")
    ap.add_argument("--int8", action="store_true",
                    help="write only the int8 fixtures (onnxruntime and onnx/gradnet_int8_nhwc.onnx)")
    args = ap.parse_args(argv)
    if args.emitter:
        return emitter_fixture(args.out)
    if args.int8:
        return int8_fixtures(args.out)
    torch.set_num_threads(2)
    os.makedirs(args.out, exist_ok=True)
    full, nofeat = torch_model(args.full), torch_model(args.nofeat)
    run_full, run_nofeat = pl.torch_runner(full), pl.torch_runner(nofeat)
    sample = pl.read_frame(os.path.join(REPO, "examples", "data", "sample.exr"))
    save = lambda name, a: np.save(os.path.join(args.out, name), np.asarray(a, np.float32))  # noqa: E731
    for name, (y0, x0, h, w) in CROPS.items():
        fr = crop(sample, y0, x0, h, w)
        write_bundle(os.path.join(args.out, f"{name}.exr"), fr, {"spp": float(sample["spp"] or 16)},
                     feature_half=False)
        data, grad, _ = pl.prepare_inputs(pl.sanitize(fr), use_features=True)
        save(f"{name}_data.npy", data)
        save(f"{name}_grad.npy", grad)
        save(f"{name}_torch.npy", run_full(data, grad))
        save(f"{name}_out.npy", pl.reconstruct(fr, run_full))
        save(f"{name}_out_nobias.npy", pl.reconstruct(fr, run_full, correct_bias=False))
        save(f"{name}_nofeat_out.npy", pl.reconstruct(fr, run_nofeat))
        print(f"{name}: {w} x {h}, padded {data.shape[3]} x {data.shape[2]}")
    rng = np.random.default_rng(3)
    out = rng.random((23, 61, 3), dtype=np.float32) * 2
    color = (out * rng.uniform(0.5, 1.5, out.shape)).astype(np.float32)
    save("bias_out.npy", out)
    save("bias_color.npy", color)
    save("bias_corrected.npy", pl.bias_correct(out, color))
    print("wrote", args.out)


def torch_model(path):
    """The torch model of a training checkpoint, or rebuilt from an exported graph's weights
    (`export.net_from_onnx`: the same torch module, so the fixtures stay torch's)."""
    if path.endswith(".onnx"):
        return ex.net_from_onnx(path)
    return ex.load_checkpoint(path)[0]


def emitter_fixture(out_dir):
    """emitter.exr (a copy of the lamps guard frame) and emitter_out.npy."""
    import shutil

    src = os.path.join(REPO, "tests", "data", "guard", "lamps_16spp.exr")
    fr = pl.read_frame(src)
    out = pl.reconstruct(fr, pl.ort_runner(os.path.join(REPO, "onnx", "gradnet.onnx")))
    emitters = pl.emitters(fr["color"], fr.get("variance"))
    kept, skipped = int(emitters.sum()), int(pl.beyond(fr["color"], kept=emitters).sum())
    shutil.copyfile(src, os.path.join(out_dir, "emitter.exr"))
    np.save(os.path.join(out_dir, "emitter_out.npy"), np.asarray(out, np.float32))
    print(f"emitter: {fr['color'].shape[1]} x {fr['color'].shape[0]}, {kept} pixels keep the base colour, "
          f"{skipped} more beyond the bias limit")


def int8_fixtures(out_dir):
    """<crop>_int8_net.npy and <crop>_int8_out.npy from onnx/gradnet_int8_nhwc.onnx (onnxruntime,
    2 threads, batch 1 per colour channel as the Rust path runs it)."""
    from . import runtime
    sess = runtime.session(os.path.join(REPO, "onnx", "gradnet_int8_nhwc.onnx"))
    run = pl.ort_runner(sess)

    def per_channel(data, grad):
        return np.concatenate([run(data[c:c + 1], grad[c:c + 1]) for c in range(data.shape[0])], 0)
    per_channel.data_channels = run.data_channels
    for name in CROPS:
        fr = pl.read_frame(os.path.join(out_dir, f"{name}.exr"))
        data, grad, _ = pl.prepare_inputs(pl.sanitize(fr), use_features=True)
        np.save(os.path.join(out_dir, f"{name}_int8_net.npy"), np.asarray(per_channel(data, grad), np.float32))
        np.save(os.path.join(out_dir, f"{name}_int8_out.npy"),
                np.asarray(pl.reconstruct(fr, per_channel), np.float32))
        print(f"{name}: int8 fixtures")


if __name__ == "__main__":
    main()
