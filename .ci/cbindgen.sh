#!/usr/bin/env bash
# Regenerates include/gdrecon.h with the pinned cbindgen (installed on first use):
#   bash .ci/cbindgen.sh           write the header
#   bash .ci/cbindgen.sh --check   fail if the committed header differs from a fresh one
# cbindgen's output changes between releases, so the version is pinned here and nowhere else.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
version=0.29.2
if ! command -v cbindgen >/dev/null || [ "$(cbindgen --version | awk '{print $2}')" != "$version" ]; then
    echo "installing cbindgen $version"
    cargo install cbindgen --locked --version "$version" --quiet
fi
generate() { cbindgen --quiet --config cbindgen.toml --output "$1" src/capi/mod.rs; }
if [ "${1:-}" = "--check" ]; then
    fresh="$(mktemp)"
    trap 'rm -f "$fresh"' EXIT
    generate "$fresh"
    if ! diff -u include/gdrecon.h "$fresh"; then
        echo "include/gdrecon.h is out of date: run bash .ci/cbindgen.sh and commit it" >&2
        exit 1
    fi
    echo "include/gdrecon.h is up to date (cbindgen $version)"
else
    generate include/gdrecon.h
    echo "wrote include/gdrecon.h (cbindgen $version)"
fi
