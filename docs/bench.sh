#!/usr/bin/env bash
# Regenerates the benchmark report docs/bench/ with one command (issue #8): run time against
# error for every method variant, 720p timings, and resolution scaling.
#
#   bash docs/bench.sh
#
# Needs the validation set and the 720p frames (docs/data.md, docs/benchmarks.md say how to
# render them) under $GDRECON_DATA (default ~/.cache/gdrecon/data), and ONNX Runtime for
# gradnet (`bash onnx/setup.sh` once; onnx/env.sh is sourced here). Builds the release CLI in
# $CARGO_TARGET_DIR (default target/). Takes about 20 minutes on 2 cores; run it on an
# otherwise idle machine (summary.md records the load average). Re-running overwrites every
# output; nothing else is touched.
#
# Environment: GDRECON_DATA (input frames), GDRECON_BENCH_OUT (default docs/bench),
# THREADS (worker threads, default all cores).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

data="${GDRECON_DATA:-$HOME/.cache/gdrecon/data}"
out="${GDRECON_BENCH_OUT:-docs/bench}"
target="${CARGO_TARGET_DIR:-$PWD/target}"
threads=()
if [ -n "${THREADS:-}" ]; then threads=(--threads "$THREADS"); fi

shopt -s nullglob
val=("$data"/val/*_*spp.exr)
hd=("$data"/bench720/cornell_16spp.exr "$data"/bench720/sunsky_16spp.exr)
if [ "${#val[@]}" -ne 18 ]; then
  echo "bench.sh: expected 18 validation bundles in $data/val, found ${#val[@]} (see docs/data.md)" >&2
  exit 1
fi
for f in "${hd[@]}"; do
  if [ ! -f "$f" ]; then
    echo "bench.sh: missing $f (render it as docs/benchmarks.md says)" >&2
    exit 1
  fi
done

# shellcheck source=/dev/null
source onnx/env.sh
if [ -z "${ORT_DYLIB_PATH:-}" ]; then
  echo "bench.sh: no ONNX Runtime for gradnet: run 'bash onnx/setup.sh' first" >&2
  exit 1
fi

cargo build --release --locked --bin gdrecon
bin="$target/release/gdrecon"
start=$SECONDS

echo "== 1/4 validation set: every variant, runs 3 (about 8 minutes)"
"$bin" bench "${val[@]}" --methods l2,l1,filter,gradnet --sweep --runs 3 --warmup 1 \
  "${threads[@]}" --out-dir "$out" \
  --title "Validation set: 320 x 180, six scenes, 4 / 16 / 64 spp, 4096 spp references"

echo "== 2/4 1280 x 720: every method, runs 5 (about 8 minutes, the filter most of it)"
"$bin" bench "${hd[@]}" --methods l2,l1,filter,gradnet --runs 5 --warmup 1 \
  "${threads[@]}" --out-dir "$out/720p" \
  --title "1280 x 720, 16 spp, 256 spp references"

echo "== 3/4 scaling: l2, l1, gradnet at 0.5, 1, 2 x of cornell 720p, runs 5"
"$bin" bench "${hd[0]}" --methods l2,l1,gradnet --scales 0.5,1,2 --runs 5 --warmup 1 \
  "${threads[@]}" --out-dir "$out/scaling" \
  --title "Resolution scaling: l2, l1, gradnet (cornell, 720p = 1x)"

echo "== 4/4 scaling: filter at 0.5, 1 x of cornell 720p, runs 1 (it needs ~35 s per 720p frame)"
"$bin" bench "${hd[0]}" --methods filter --scales 0.5,1 --runs 1 --warmup 0 \
  "${threads[@]}" --out-dir "$out/scaling-filter" \
  --title "Resolution scaling: filter (cornell, 720p = 1x, one run, no warm-up)"

# One page: the validation summary, then the others with their headings one level down.
for part in 720p scaling scaling-filter; do
  {
    echo
    echo "<!-- $part/summary.md; its CSV, JSON and plots are in $part/ -->"
    sed 's/^#/##/' "$out/$part/summary.md"
  } >>"$out/summary.md"
done

echo "== done in $((SECONDS - start)) s"
echo "summary:  $out/summary.md"
echo "plots:    $out/pareto.png $out/pareto.svg"
echo "data:     $out/results.csv $out/results.json and $out/{720p,scaling,scaling-filter}/"
