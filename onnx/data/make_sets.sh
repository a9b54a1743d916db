#!/usr/bin/env bash
# Render gdrecon's validation, test and training sets (outside the repository; never committed).
#
#   bash onnx/data/make_sets.sh [val|test|train|gradnet|all]      (default: val then test)
#
# Needs `bash onnx/setup.sh` (the venv, with the gdrecon_py package that renders).
# Environment: GDRECON_DATA (default $HOME/.cache/gdrecon/data), GDRECON_VENV (see setup.sh),
# VAL_REF_SPP / TEST_REF_SPP (4096), TRAIN_PERTURB (default 0:12), TRAIN_REF_SPP (default 1024:
# the combiner trains against references; 0 = noisy only), TRAIN_DIR (default
# $GDRECON_DATA/train2).
# Already rendered bundles are skipped (--skip-existing), so an interrupted run resumes; primal
# layers missing from existing bundles are added (--add-primal) without touching their other
# layers.
#
# Split rule (docs/data.md, scenes.SPLITS): scene *families* are split three ways.
#   val   = base scenes of cornell metals glass textures indirect sunsky studio dusk,
#           render seed 20000 (tuning: methods, parameters, checkpoints are chosen on it)
#   test  = base scenes of gaproom lamps cellar caustics fabric courtyard thin foliage,
#           render seed 30000 (never used to choose anything)
#   train = perturbed variants of atrium night shelf garden vitrine aquarium only (perturbation family
#           seed 1, indices 0..11), render seed 40000, in $TRAIN_DIR.
#   gradnet = GradNet's training set: perturbations 12..97 of the same families, one spp per
#           view, 144x144, no references, in $GRADNET_DIR (default $GDRECON_DATA/train3).
# The retired training set ($GDRECON_DATA/train: perturbations of the six original validation
# families, perturbation seed 0, render seed 1000) trained the existing GradNet checkpoint and is
# not used for new training.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
venv="${GDRECON_VENV:-$HOME/.cache/gdrecon/venv}"
py="$venv/bin/python"
root="${GDRECON_DATA:-$HOME/.cache/gdrecon/data}"
what="${1:-eval}"
source "$here/../env.sh"
# this checkout's package first (the venv's editable install may point at another checkout)
export PYTHONPATH="$(cd "$here/.." && pwd)${PYTHONPATH:+:$PYTHONPATH}"
render() { "$py" -m gdrecon_py.data.render "$@"; }

if [ "$what" = val ] || [ "$what" = eval ] || [ "$what" = all ]; then
  echo "# validation set -> $root/val"
  time render --scene val --size 320x180 --spp 4,16,64 --ref-spp "${VAL_REF_SPP:-4096}" --primal \
      --seed 20000 --out "$root/val" --skip-existing
  time render --add-primal "$root/val"
fi
if [ "$what" = test ] || [ "$what" = eval ] || [ "$what" = all ]; then
  echo "# test set -> $root/test"
  time render --scene test --size 320x180 --spp 4,16,64 --ref-spp "${TEST_REF_SPP:-4096}" --primal \
      --seed 30000 --out "$root/test" --skip-existing
  time render --add-primal "$root/test"
fi
if [ "$what" = train ] || [ "$what" = all ]; then
  dir="${TRAIN_DIR:-$root/train2}"
  echo "# training set -> $dir"
  time render --scene train --size 256x256 --spp 4,16,64 \
      --perturb "${TRAIN_PERTURB:-0:12}" --perturb-seed 1 --ref-spp "${TRAIN_REF_SPP:-1024}" \
      --seed 40000 --out "$dir" --skip-existing
fi
if [ "$what" = gradnet ] || [ "$what" = all ]; then
  dir="${GRADNET_DIR:-$root/train3}"
  echo "# GradNet's training set -> $dir"
  for sp in 4:12:28 16:28:44 64:44:60 32:60:72 8:72:84 16:84:98; do
    IFS=: read -r spp a b <<<"$sp"
    time render --scene train --size 144x144 --spp "$spp" --perturb "$a:$b" --perturb-seed 1 \
        --ref-spp 0 --seed 40000 --out "$dir" --skip-existing
  done
fi
