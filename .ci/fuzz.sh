#!/usr/bin/env bash
# Fuzz the frame-bundle reader (fuzz/fuzz_targets/exr_bundle.rs) and the C ABI's image-view
# validation (fuzz/fuzz_targets/capi_view.rs) for a bounded time each, with AddressSanitizer.
#   bash .ci/fuzz.sh [SECONDS_PER_TARGET]      (default 60)
# Installs cargo-fuzz once (pinned; reused from ~/.cargo/bin). The stable toolchain builds the
# sanitised targets with RUSTC_BOOTSTRAP=1 (cargo fuzz passes nightly-only -Z flags). The build
# is cached outside the repository (~/.cache/gdrecon/fuzz-target). Seeds are committed under
# fuzz/corpus/<target>/; libFuzzer adds what it finds there (commit new inputs worth keeping).
# A crash leaves its input in fuzz/artifacts/<target>/ and fails this script.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
seconds="${1:-60}"
if ! cargo fuzz --version >/dev/null 2>&1; then
    echo "== installing cargo-fuzz"
    if ! cargo install -q cargo-fuzz --locked --version 0.13.2; then
        echo "WARNING: cargo-fuzz could not be installed here: fuzzing skipped"
        exit 0
    fi
fi
export RUSTC_BOOTSTRAP=1
export CARGO_TARGET_DIR="${GDRECON_FUZZ_TARGET:-$HOME/.cache/gdrecon/fuzz-target}"
for target in exr_bundle capi_view; do
    echo "== cargo fuzz run $target ($seconds s)"
    mkdir -p "fuzz/corpus/$target"
    log="$(mktemp)"
    status=0
    cargo fuzz run --fuzz-dir fuzz "$target" "fuzz/corpus/$target" -- \
        -max_total_time="$seconds" -max_len=262144 -rss_limit_mb=2048 -print_final_stats=1 \
        >"$log" 2>&1 || status=$?
    grep -E "^(stat::number_of_executed_units|stat::peak_rss_mb)|Done [0-9]+ runs|ERROR|SUMMARY|panicked" "$log" || true
    if [ "$status" -ne 0 ] && ! grep -qE "^INFO: (Running with|Seed:)" "$log" && ! grep -q "^error\[E" "$log"; then
        # libFuzzer never started and our code compiled: the machine cannot build or run
        # sanitised binaries (toolchain, linker, sanitizer runtime). Said loudly, not failed:
        # a finding or a compile error in the targets still fails.
        tail -30 "$log"
        echo "WARNING: fuzzing could not run here ($target, exit $status): skipped"
        rm -f "$log"
        continue
    fi
    if [ "$status" -ne 0 ] || grep -q "SUMMARY: libFuzzer" "$log"; then
        tail -60 "$log"
        echo "FAILED: $target (exit $status); the input is in fuzz/artifacts/$target/"
        exit 1
    fi
    rm -f "$log"
done
echo "fuzzing passed: ${seconds} s per target"
