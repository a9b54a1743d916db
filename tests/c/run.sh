#!/usr/bin/env bash
# The C API's tests, from C and C++ against the installed header and libraries:
# 1. build the release library with the `testing` feature (the deliberate panic the C test
#    needs) and install it into a temporary prefix (packaging/install.sh);
# 2. check that the shared library exports only gdr_ symbols and has its soname;
# 3. write the Rust API's reference outputs (tests/capi.rs, write_reference_for_c);
# 4. compile tests/c/test_capi.c as C99 and as C++ (-Wall -Wextra -Werror -pedantic), found
#    through pkg-config, dynamically and statically linked, and run them (bit-for-bit equality,
#    layouts, every error case, cancellation latency), and tests/c/test_safety.c (a renderer's
#    misuse: callbacks that release or re-enter, concurrent logging, panics that must print
#    nothing, fork after commit, overlap checks of huge views), and tests/c/test_cpp.cpp as
#    C++17 (include/gdrecon.hpp);
# 5. run both again under valgrind (no leaks, no invalid accesses);
# 6. build and run the C, C++ and Python examples on the bundled sample frame.
# Honours CARGO_TARGET_DIR. The last line is "N passed, N failed".
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
cd "$root"
target="${CARGO_TARGET_DIR:-$root/target}"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
prefix="$work/prefix"
sample="$root/examples/data/sample.exr"
passed=0
failed=0

step() { echo "== $*"; }
ok() { passed=$((passed + 1)); echo "ok: $*"; }
bad() { failed=$((failed + 1)); echo "FAILED: $*"; }
# Prints a test log: in full when the run failed, else only its measurements and result line.
# CI output stays short enough to be read whole.
show_log() {
    local log="$1" failed_run="$2"
    if [ "$failed_run" = 0 ]; then
        grep -E "^(skipped:|cancellation latency|log callback:|overlap check|pointer-only re-commit|[0-9]+ passed, [0-9]+ failed$)" "$log" || true
        return
    fi
    cat "$log"
}
# Runs a test binary and adds the counts from its closing "N passed, N failed" line.
counted() {
    local name="$1"
    shift
    local log="$work/$name.log" status=0
    "$@" >"$log" 2>&1 || status=$?
    local clean=1
    [ "$status" -eq 0 ] && grep -qE '^[0-9]+ passed, 0 failed$' "$log" && clean=0
    show_log "$log" "$clean"
    local line
    line="$(grep -E '^[0-9]+ passed, [0-9]+ failed$' "$log" | tail -1 || true)"
    if [ -z "$line" ]; then
        bad "$name: no result line (exit $status)"
        return
    fi
    passed=$((passed + ${line%% passed*}))
    local f="${line#*passed, }"
    failed=$((failed + ${f%% failed}))
    [ "$status" -eq 0 ] || [ "${f%% failed}" -ne 0 ] || bad "$name: exit status $status"
    # The library never prints: a panic it caught (the tests provoke some) leaves no trace.
    if grep -qE "panicked at|RUST_BACKTRACE" "$log"; then bad "$name: the library printed a panic"; fi
}

step "tools"
missing=()
for tool in gcc g++ make pkg-config valgrind nm readelf python3; do
    command -v "$tool" >/dev/null || missing+=("$tool")
done
if [ "${#missing[@]}" -gt 0 ]; then
    echo "installing with apt: ${missing[*]}"
    pkgs=()
    for tool in "${missing[@]}"; do
        case "$tool" in
        nm | readelf) pkgs+=(binutils) ;;
        *) pkgs+=("$tool") ;;
        esac
    done
    apt-get update -qq >/dev/null && apt-get install -y -qq "${pkgs[@]}" >/dev/null
fi

step "build the release library (with the test hooks: internal_test_panic, the copy method)"
cargo build --release --locked --lib --features testing
bash packaging/install.sh "$prefix"
export PKG_CONFIG_PATH="$prefix/lib/pkgconfig"

step "exported symbols"
symbols="$(nm -D --defined-only "$prefix/lib/libgdrecon.so" | awk '$2 ~ /^[TDBR]$/ {print $3}' | sort)"
others="$(grep -v '^gdr_' <<<"$symbols" || true)"
echo "$(wc -l <<<"$symbols") exported symbols: $(tr '\n' ' ' <<<"$symbols")"
if [ -z "$others" ]; then ok "only gdr_ symbols are exported"; else bad "symbols without the gdr_ prefix: $others"; fi
soname="$(readelf -d "$prefix/lib/libgdrecon.so" | sed -n 's/.*SONAME.*\[\(.*\)\]/\1/p')"
if [ "$soname" = "libgdrecon.so.$(sed -n 's/^version = "\([0-9]*\)\..*/\1/p' Cargo.toml | head -1)" ]; then
    ok "soname $soname"
else
    bad "soname is '$soname'"
fi

step "Rust reference outputs"
GDR_CAPI_REF_DIR="$work/ref" cargo test --release --locked --test capi -- --ignored --exact \
    write_reference_for_c >"$work/ref.log" 2>&1 || { cat "$work/ref.log"; exit 1; }
ok "reference written"

step "compile the C tests (C99, C++, static)"
cflags="$(pkg-config --cflags gdrecon)"
libs="$(pkg-config --libs gdrecon)"
static_libs="$(pkg-config --libs gdrecon-static)"
warn=(-Wall -Wextra -Werror -pedantic)
gcc -std=c99 "${warn[@]}" -O1 -g $cflags tests/c/test_capi.c -o "$work/test_c" $libs -lm \
    -Wl,-rpath,"$prefix/lib" && ok "gcc -std=c99"
g++ -x c++ -std=c++11 "${warn[@]}" -O1 -g $cflags tests/c/test_capi.c -o "$work/test_cpp" $libs \
    -Wl,-rpath,"$prefix/lib" && ok "g++ -std=c++11"
gcc -std=c99 "${warn[@]}" -O1 -g -pthread $cflags tests/c/test_safety.c -o "$work/test_safety" $libs \
    -Wl,-rpath,"$prefix/lib" && ok "gcc -std=c99 test_safety.c"
g++ -std=c++17 "${warn[@]}" -O1 -g $cflags tests/c/test_cpp.cpp -o "$work/test_hpp" $libs \
    -Wl,-rpath,"$prefix/lib" && ok "g++ -std=c++17 test_cpp.cpp (include/gdrecon.hpp)"
gcc -std=c99 "${warn[@]}" -O1 $cflags tests/c/test_capi.c -o "$work/test_static" $static_libs -lm \
    && ok "gcc, static library (pkg-config gdrecon-static)"
# Listings are captured before they are searched: `ldd X | grep -q Y` under pipefail fails
# when grep exits at its match while ldd still writes (SIGPIPE; seen once in 300 runs).
static_deps=$(ldd "$work/test_static")
dynamic=$(readelf -d "$work/test_c")
if grep -q libgdrecon <<<"$static_deps"; then bad "test_static needs libgdrecon.so"; else ok "test_static: no libgdrecon.so (ldd)"; fi
if grep -q "NEEDED.*libgdrecon.so.0" <<<"$dynamic"; then ok "linked against the soname"; else bad "test_c does not need libgdrecon.so.0"; fi

step "run the C tests"
counted test_c "$work/test_c" "$work/ref" "$sample"
counted test_cpp "$work/test_cpp" "$work/ref" "$sample"
counted test_static "$work/test_static" "$work/ref"
counted test_safety "$work/test_safety"
counted test_hpp "$work/test_hpp" "$sample"

step "GradNet with ONNX Runtime next to the library (discovery step 3)"
ort_lib="${ORT_DYLIB_PATH:-}"
if [ -n "$ort_lib" ] && [ -f "$ort_lib" ]; then
    ln -sf "$ort_lib" "$prefix/lib/$(basename "$ort_lib")"
    counted test_c_ort_beside env -u ORT_DYLIB_PATH GDRECON_VENV="$work/no-venv" \
        GDR_TEST_EXPECT_ORT_DIR="$prefix/lib" "$work/test_c" "$work/ref" "$sample"
    rm -f "$prefix/lib/$(basename "$ort_lib")"
else
    bad "ORT_DYLIB_PATH is not set: run bash onnx/setup.sh && source onnx/env.sh first"
fi

step "valgrind"
# The safety test forks: its child cannot free what the pool threads (not copied into it) own,
# so valgrind watches the parent only (the child reports its own checks through a pipe).
vg=(valgrind -q --error-exitcode=1 --leak-check=full --child-silent-after-fork=yes
    --errors-for-leak-kinds=definite,indirect --show-leak-kinds=definite,indirect)
GDR_TEST_NO_TIMING=1 GDR_TEST_NO_GRADNET=1 counted valgrind "${vg[@]}" "$work/test_c" "$work/ref" "$sample"
GDR_TEST_NO_TIMING=1 GDR_TEST_NO_OIDN=1 counted valgrind_safety "${vg[@]}" "$work/test_safety"
counted valgrind_hpp "${vg[@]}" "$work/test_hpp" "$sample"
if grep -qE "definitely lost|indirectly lost|Invalid (read|write)|uninitialised" \
    "$work/valgrind.log" "$work/valgrind_safety.log" "$work/valgrind_hpp.log"; then
    bad "valgrind reported errors"
else
    ok "valgrind: no leaks, no invalid accesses"
fi

step "examples"
# Exactly as examples/c/Makefile documents it, in a copy of the folder, without PKG_CONFIG_PATH.
cp -r examples/c "$work/examples"
(cd "$work/examples" && env -u PKG_CONFIG_PATH make -s GDRECON_PREFIX="$prefix" >/dev/null) &&
    ok "examples/c: make GDRECON_PREFIX=PREFIX"
for ex in reconstruct reconstruct_cpp; do
    if "$work/examples/$ex" "$sample" "$work/out_$ex" >"$work/$ex.log" 2>&1; then
        ok "examples/c/$ex: $(grep -E '^method ' "$work/$ex.log" | paste -sd ';' -)"
    else
        cat "$work/$ex.log"
        bad "examples/c/$ex"
    fi
done
if python3 examples/python/reconstruct.py --lib "$prefix/lib/libgdrecon.so" "$sample" "$work/out_py" \
    >"$work/py.log" 2>&1; then
    ok "examples/python: $(grep -E '^method ' "$work/py.log" | paste -sd ';' -)"
else
    cat "$work/py.log"
    bad "examples/python"
fi

step "README: the C section's commands"
# The block after the marker, run as written from the repository root, with PREFIX moved to a
# temporary directory; what it writes into the checkout is removed afterwards.
readme="$work/readme.sh"
sed -n '/<!-- tests\/c\/run.sh runs the next block -->/,/^```$/p' README.md | sed '1,2d;$d' |
    sed "s|^PREFIX=.*|PREFIX=\"$work/readme-prefix\"|" >"$readme"
readme_outputs=(reconstruct reconstruct_static examples/c/reconstruct examples/c/reconstruct_cpp)
if [ ! -s "$readme" ]; then
    bad "README has no block after the run.sh marker"
elif (env -u PKG_CONFIG_PATH bash -euo pipefail "$readme") >"$work/readme.log" 2>&1 &&
    static_deps=$(ldd reconstruct_static) && deps=$(ldd reconstruct) &&
    ! grep -q libgdrecon <<<"$static_deps" && grep -q "$work/readme-prefix/lib/libgdrecon.so" <<<"$deps"; then
    ok "README commands ($(grep -c . "$readme") lines; reconstruct uses the installed .so, reconstruct_static none)"
else
    cat "$readme" "$work/readme.log"
    bad "README commands"
fi
rm -f "${readme_outputs[@]}" sample_*.pfm

echo "$passed passed, $failed failed"
[ "$failed" -eq 0 ]
