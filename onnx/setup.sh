#!/usr/bin/env bash
# Create (or reuse) gdrecon's Python virtual environment, outside the repository.
#
#   bash onnx/setup.sh              # everything pinned in onnx/requirements.txt (torch included)
#   bash onnx/setup.sh --no-torch   # rendering only: onnx/requirements-render.txt
#   source onnx/env.sh              # afterwards: exports DRJIT_LIBLLVM_PATH, GDRECON_PYTHON, ...
#
# Options:
#   --no-torch      install only the rendering requirements (mitsuba, drjit, numpy, OpenEXR, ...)
#   --venv DIR      where the venv lives (default: ${GDRECON_VENV:-$HOME/.cache/gdrecon/venv})
#   --python PY     interpreter that creates the venv (default: ${PYTHON:-python3})
#   --force         reinstall even if the stamp says the venv is up to date
#
# Idempotent: the venv carries a stamp (hash of the requirements files + mode + interpreter);
# when it matches, nothing is installed. pip's download cache (~/.cache/pip) is used as usual.
# The project's package onnx/gdrecon_py is installed in editable mode (no dependencies, no
# download when the venv has setuptools) unless the venv already imports it from this checkout,
# so its scripts run as `$GDRECON_PYTHON -m gdrecon_py.<module>` from any directory.
# System package: libllvm19 (needed by Mitsuba's llvm_* variants) is apt-installed only if
# missing; sudo is used only when not root.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
mode=full
force=0
venv="${GDRECON_VENV:-$HOME/.cache/gdrecon/venv}"
py="${PYTHON:-python3}"
while [ $# -gt 0 ]; do
  case "$1" in
    --no-torch|--minimal) mode=render ;;
    --venv) venv="$2"; shift ;;
    --python) py="$2"; shift ;;
    --force) force=1 ;;
    -h|--help) sed -n '2,20p' "$0"; exit 0 ;;
    *) echo "setup.sh: unknown option '$1' (see --help)" >&2; exit 2 ;;
  esac
  shift
done

log() { printf '[gdrecon setup] %s\n' "$*"; }

as_root() {
  if [ "$(id -u)" = 0 ]; then "$@"; else sudo "$@"; fi
}

apt_updated=0
apt_install() {
  if ! command -v apt-get >/dev/null 2>&1; then
    log "apt-get not found: install $* by hand"; return 1
  fi
  if [ $apt_updated = 0 ]; then
    as_root env DEBIAN_FRONTEND=noninteractive apt-get update -qq
    apt_updated=1
  fi
  as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@"
}

# --- 1. LLVM 19 for Dr.Jit's LLVM backend -----------------------------------------------------
if command -v dpkg >/dev/null 2>&1 && dpkg -s libllvm19 2>/dev/null | grep -q '^Status: install ok installed'; then
  log "libllvm19 already installed"
else
  log "installing libllvm19 (apt)"
  apt_install libllvm19 || log "WARNING: could not install libllvm19; set DRJIT_LIBLLVM_PATH yourself"
fi
llvm_lib=""
if command -v dpkg >/dev/null 2>&1; then
  llvm_lib="$(dpkg -L libllvm19 2>/dev/null | grep -E '/libLLVM\.so\.19(\.[0-9]+)*$' | head -n1 || true)"
  [ -n "$llvm_lib" ] || llvm_lib="$(dpkg -L libllvm19 2>/dev/null | grep -E '/libLLVM-19\.so$' | head -n1 || true)"
fi

# --- 2. the virtual environment -----------------------------------------------------------------
if ! command -v "$py" >/dev/null 2>&1; then
  log "$py not found: installing python3 (apt)"
  apt_install python3 python3-venv
fi
pyver="$("$py" -c 'import sys; print("%d.%d.%d" % sys.version_info[:3])')"

hash_reqs() { cat "$here/requirements-render.txt" "$here/requirements.txt" | sha256sum | cut -c1-16; }
want_hash="$(hash_reqs)-py$pyver"
stamp="$venv/.gdrecon-stamp"
up_to_date=0
if [ $force = 0 ] && [ -f "$stamp" ] && [ -x "$venv/bin/python" ] && "$venv/bin/python" -c '' 2>/dev/null; then
  read -r have_mode have_hash < "$stamp" || true
  if [ "${have_hash:-}" = "$want_hash" ] && { [ "$have_mode" = full ] || [ "$mode" = render ]; }; then
    up_to_date=1
  fi
fi

if [ $up_to_date = 1 ]; then
  log "venv $venv is up to date ($have_mode, $want_hash): nothing to install"
else
  if [ ! -x "$venv/bin/python" ]; then
    log "creating venv $venv with $py ($pyver)"
    mkdir -p "$(dirname "$venv")"
    if ! "$py" -m venv "$venv"; then
      # Debian's system python needs python3-venv (ensurepip) to create a venv
      log "venv creation failed: installing python3-venv (apt) and retrying"
      rm -rf "$venv"
      apt_install python3-venv
      "$py" -m venv "$venv"
    fi
  fi
  req="$here/requirements.txt"
  [ $mode = render ] && req="$here/requirements-render.txt"
  log "installing $(basename "$req") into $venv (mode $mode)"
  "$venv/bin/python" -m pip install --disable-pip-version-check -q --upgrade pip
  "$venv/bin/python" -m pip install --disable-pip-version-check -q -r "$req"
  echo "$mode $want_hash" > "$stamp"
fi

# --- 3. the project's package, editable (onnx/pyproject.toml: onnx/gdrecon_py) -----------------
# -I: neither the current directory nor PYTHONPATH may make it look installed
pkg_home() {
  "$venv/bin/python" -I -c 'import os, gdrecon_py; print(os.path.dirname(os.path.dirname(os.path.realpath(gdrecon_py.__file__))))' 2>/dev/null || true
}
here_real="$(cd "$here" && pwd -P)"
if [ $force = 0 ] && [ "$(pkg_home)" = "$here_real" ]; then
  log "gdrecon_py already installed (editable, $here_real)"
else
  log "installing gdrecon_py (editable, $here_real) into $venv"
  if "$venv/bin/python" -I -c 'import setuptools' 2>/dev/null; then
    "$venv/bin/python" -m pip install --disable-pip-version-check -q --no-deps --no-build-isolation -e "$here_real"
  else
    "$venv/bin/python" -m pip install --disable-pip-version-check -q --no-deps -e "$here_real"
  fi
  [ "$(pkg_home)" = "$here_real" ] || { log "ERROR: gdrecon_py is not importable from $here_real after the install"; exit 1; }
fi

# --- 4. smoke test and the environment to export -----------------------------------------------
export DRJIT_LIBLLVM_PATH="${DRJIT_LIBLLVM_PATH:-$llvm_lib}"
"$venv/bin/python" - <<'EOF'
import mitsuba as mi
mi.set_variant("llvm_ad_rgb")
import OpenEXR, numpy
print("[gdrecon setup] mitsuba %s (llvm_ad_rgb) OK, numpy %s" % (mi.__version__, numpy.__version__))
EOF
ort_lib="$(ls "$venv"/lib/python3*/site-packages/onnxruntime/capi/libonnxruntime.so.* 2>/dev/null | head -n1 || true)"

log "venv: $venv"
echo "# gdrecon environment (or: source onnx/env.sh)"
echo "export GDRECON_VENV=\"$venv\""
echo "export GDRECON_PYTHON=\"$venv/bin/python\""
echo "export DRJIT_LIBLLVM_PATH=\"$DRJIT_LIBLLVM_PATH\""
[ -n "$ort_lib" ] && echo "export ORT_DYLIB_PATH=\"$ort_lib\""
exit 0
