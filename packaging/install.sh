#!/usr/bin/env bash
# Installs the C library, header and pkg-config file into a prefix:
#   bash packaging/install.sh PREFIX
# after `cargo build --release` (honours CARGO_TARGET_DIR). Layout:
#   PREFIX/include/gdrecon.h, gdrecon.hpp (the C++17 wrapper)
#   PREFIX/lib/libgdrecon.so.X.Y.Z, libgdrecon.so.X -> (the soname), libgdrecon.so ->
#   PREFIX/lib/libgdrecon.a
#   PREFIX/lib/pkgconfig/gdrecon.pc          (pkg-config --cflags --libs gdrecon: the shared library)
#   PREFIX/lib/pkgconfig/gdrecon-static.pc   (pkg-config --cflags --libs gdrecon-static: the archive)
# `pkg-config --static gdrecon` cannot pick the archive (its -lgdrecon finds the .so first, as
# for any library installed both ways): static linking names the archive by its path.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
prefix="${1:?usage: install.sh PREFIX}"
mkdir -p "$prefix"
prefix="$(cd "$prefix" && pwd)"
target="${CARGO_TARGET_DIR:-$root/target}/release"
version="$(sed -n 's/^version = "\(.*\)"/\1/p' "$root/Cargo.toml" | head -1)"
major="${version%%.*}"
for f in libgdrecon.so libgdrecon.a; do
    [ -f "$target/$f" ] || { echo "install.sh: $target/$f is missing: run cargo build --release" >&2; exit 1; }
done
mkdir -p "$prefix/include" "$prefix/lib/pkgconfig"
install -m 644 "$root/include/gdrecon.h" "$root/include/gdrecon.hpp" "$prefix/include/"
install -m 755 "$target/libgdrecon.so" "$prefix/lib/libgdrecon.so.$version"
ln -sf "libgdrecon.so.$version" "$prefix/lib/libgdrecon.so.$major"
ln -sf "libgdrecon.so.$major" "$prefix/lib/libgdrecon.so"
install -m 644 "$target/libgdrecon.a" "$prefix/lib/libgdrecon.a"
# The archive keeps the standard library's debug info (the release profile strips only what
# it links): drop it, as the shared library has none.
if command -v strip >/dev/null; then strip --strip-debug "$prefix/lib/libgdrecon.a"; fi
# What a static link needs besides the archive (rustc's --print native-static-libs on Linux).
static_libs="-lgcc_s -lutil -lrt -lpthread -lm -ldl -lc"
for pc in gdrecon gdrecon-static; do
    sed -e "s|@PREFIX@|$prefix|" -e "s|@VERSION@|$version|" -e "s|@STATIC_LIBS@|$static_libs|" \
        "$root/packaging/$pc.pc.in" > "$prefix/lib/pkgconfig/$pc.pc"
done
echo "installed gdrecon $version into $prefix"
