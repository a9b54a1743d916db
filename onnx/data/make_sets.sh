#!/usr/bin/env bash
# Render gdrecon's validation and training sets (outside the repository; never committed).
#
#   bash onnx/data/make_sets.sh [val|train|all]      (default: all)
#
# Needs `bash onnx/setup.sh` (the venv, with the gdrecon_py package that renders).
# Environment: GDRECON_DATA (default $HOME/.cache/gdrecon/data), GDRECON_VENV (see setup.sh),
# TRAIN_PERTURB (default 0:16), TRAIN_REF_SPP (default 0 = noisy only), VAL_REF_SPP (4096).
# Already rendered bundles are skipped (--skip-existing), so an interrupted run resumes.
#
# Split rule (docs/data.md): validation = the six *base* scenes (no perturbation), render seed
# 20000; training = perturbed variants only (perturbation family seed 0, indices 0..15), render
# seed 1000. A perturbation never reproduces a base scene (every parameter is redrawn and the
# camera is always rotated by >= 2 degrees), and all render seeds are hashed from distinct keys.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
venv="${GDRECON_VENV:-$HOME/.cache/gdrecon/venv}"
py="$venv/bin/python"
root="${GDRECON_DATA:-$HOME/.cache/gdrecon/data}"
what="${1:-all}"
source "$here/../env.sh"

if [ "$what" = val ] || [ "$what" = all ]; then
  echo "# validation set -> $root/val"
  time "$py" -m gdrecon_py.data.render --scene all --size 320x180 --spp 4,16,64 \
      --ref-spp "${VAL_REF_SPP:-4096}" --seed 20000 --out "$root/val" --skip-existing
fi
if [ "$what" = train ] || [ "$what" = all ]; then
  echo "# training set -> $root/train"
  time "$py" -m gdrecon_py.data.render --scene all --size 256x256 --spp 4,16 \
      --perturb "${TRAIN_PERTURB:-0:16}" --perturb-seed 0 --ref-spp "${TRAIN_REF_SPP:-0}" \
      --seed 1000 --out "$root/train" --skip-existing
fi
