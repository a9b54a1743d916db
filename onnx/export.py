"""Export trained GradNet weights to ONNX (network only: mu-law, padding and the bias correction
are the caller's job, see onnx/pipeline.py and onnx/README.md).

    source onnx/env.sh
    $GDRECON_PYTHON onnx/export.py --ckpt $HOME/.cache/gdrecon/train_runs/full/last.pt \
        --out onnx/gradnet.onnx
    $GDRECON_PYTHON onnx/export.py --ckpt $HOME/.cache/gdrecon/train_runs/nofeat/last.pt \
        --out onnx/gradnet_nofeat.onnx

Writes <out>, <out>.sha256 (`sha256sum` format) and updates onnx/models.json (one entry per
model: file, sha256, bytes, variant, inputs/outputs, opset, IR version, checkpoint provenance).
The graph: inputs `data` (N x 8 x H x W, or N x 1 for the no-feature model) and `grad`
(N x 2 x H x W), output `output` (N x 1 x H x W); N, H, W dynamic (H, W multiples of 8).
torch.onnx.export(dynamo=False, opset 17) writes IR version 8, which ONNX Runtime 1.31 accepts
(it rejects IR 14); the IR version is checked and pinned to <= 10 here.
"""
import argparse
import hashlib
import json
import os
import sys

import numpy as np
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import gradnet as gn  # noqa: E402

OPSET = 17
MAX_IR = 10
MANIFEST = os.path.join(HERE, "models.json")


def sha256_file(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def export_model(net, path, metadata=None):
    """Export `net` (GradNet, eval mode) to `path`; returns the ONNX ModelProto as written."""
    import onnx
    net = net.eval()
    dch = net.data_ch
    data = torch.zeros(3, dch, 32, 48)
    grad = torch.zeros(3, 2, 32, 48)
    dyn = {"data": {0: "N", 2: "H", 3: "W"}, "grad": {0: "N", 2: "H", 3: "W"},
           "output": {0: "N", 2: "H", 3: "W"}}
    torch.onnx.export(net, (data, grad), path, input_names=["data", "grad"], output_names=["output"],
                      dynamic_axes=dyn, opset_version=OPSET, dynamo=False, do_constant_folding=True,
                      export_params=True)
    m = onnx.load(path)
    if m.ir_version > MAX_IR:
        m.ir_version = MAX_IR
    meta = {"mu": "16", "data_channels": str(dch), "size_multiple": "8",
            "producer_note": "gdrecon GradNet (Guo et al. 2019); see onnx/README.md"}
    meta.update(metadata or {})
    del m.metadata_props[:]
    for k, v in meta.items():
        p = m.metadata_props.add()
        p.key, p.value = k, str(v)
    onnx.checker.check_model(m)
    onnx.save(m, path)  # weights inline (a single file, < 2 GB)
    return m


def load_checkpoint(path):
    ck = torch.load(path, map_location="cpu", weights_only=False)
    variant = ck.get("variant", "full")
    net = gn.GradNet() if variant == "full" else gn.GradNetNoFeat()
    net.load_state_dict(ck["net"])
    return net.eval(), ck


def net_from_onnx(path):
    """Rebuild the torch model from the weights stored in an exported ONNX file (initializer
    names are the state_dict keys)."""
    import onnx
    from onnx import numpy_helper
    m = onnx.load(path)
    inits = {i.name: numpy_helper.to_array(i) for i in m.graph.initializer}
    dch = int({p.key: p.value for p in m.metadata_props}.get("data_channels", "8"))
    net = gn.GradNet(data_ch=dch)
    sd = net.state_dict()
    missing = [k for k in sd if k not in inits]
    if missing:
        raise KeyError(f"{path}: initializers missing for {missing[:5]}")
    net.load_state_dict({k: torch.from_numpy(np.array(inits[k])) for k in sd})
    return net.eval()


def update_manifest(entry, manifest=MANIFEST):
    d = {"models": {}}
    if os.path.exists(manifest):
        with open(manifest) as f:
            d = json.load(f)
    d.setdefault("models", {})[entry["file"]] = entry
    d["preprocessing"] = ("see onnx/README.md and onnx/pipeline.py: sanitise, feature normalisation, "
                          "mu-law mu=16, pad to multiple of 8 (reflect / anti-symmetric gradients), "
                          "crop, inverse mu-law, Gaussian bias correction radius 45 sigma 15")
    with open(manifest, "w") as f:
        json.dump(d, f, indent=1, sort_keys=True)
        f.write("\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ckpt", required=True)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    net, ck = load_checkpoint(args.ckpt)
    variant = ck.get("variant", "full")
    tr = ck.get("args", {})
    meta = {"variant": variant, "epochs_trained": ck["epoch"] + 1,
            "train_seconds": round(ck.get("elapsed", 0.0)), "train_args": json.dumps(tr, sort_keys=True)}
    m = export_model(net, args.out, meta)

    # self-check with onnxruntime
    import onnxruntime as ort
    sess = ort.InferenceSession(args.out, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    worst = 0.0
    for (h, w) in [(16, 24), (40, 32)]:
        d = rng.random((3, net.data_ch, h, w), dtype=np.float32)
        g = (rng.random((3, 2, h, w), dtype=np.float32) - 0.5)
        ref = net(torch.from_numpy(d), torch.from_numpy(g)).detach().numpy()
        got = sess.run(["output"], {"data": d, "grad": g})[0]
        worst = max(worst, float(np.abs(ref - got).max()))
    print(f"{args.out}: IR {m.ir_version}, opset {m.opset_import[0].version}, "
          f"max |torch - ort| = {worst:.2e}", flush=True)
    if worst > 1e-4:
        raise SystemExit("parity check failed")

    digest = sha256_file(args.out)
    base = os.path.basename(args.out)
    with open(args.out + ".sha256", "w") as f:
        f.write(f"{digest}  {base}\n")
    dch = net.data_ch
    entry = {"file": base, "sha256": digest, "bytes": os.path.getsize(args.out), "variant": variant,
             "ir_version": m.ir_version, "opset": m.opset_import[0].version,
             "inputs": {"data": ["N", dch, "H", "W"], "grad": ["N", 2, "H", "W"]},
             "outputs": {"output": ["N", 1, "H", "W"]},
             "epochs_trained": ck["epoch"] + 1, "train_seconds": round(ck.get("elapsed", 0.0)),
             "train_args": tr, "parity_max_abs": worst}
    update_manifest(entry)
    print(f"sha256 {digest}  {base}", flush=True)


if __name__ == "__main__":
    main()
