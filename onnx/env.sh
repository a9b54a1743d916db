# Source me (bash/zsh) after `bash onnx/setup.sh`:   source onnx/env.sh
# Exports the variables the project's Python scripts and the Rust ONNX path need. Idempotent,
# prints nothing, never installs anything.
GDRECON_VENV="${GDRECON_VENV:-$HOME/.cache/gdrecon/venv}"
export GDRECON_VENV
export GDRECON_PYTHON="$GDRECON_VENV/bin/python"
# This checkout's gdrecon_py first: the venv is shared between checkouts and its editable
# install points at whichever one ran setup.sh last.
_gdr_f="$(cd "$(dirname "${BASH_SOURCE[0]:-$0}")" && pwd)"
case ":${PYTHONPATH:-}:" in
  *":$_gdr_f:"*) ;;
  *) export PYTHONPATH="$_gdr_f${PYTHONPATH:+:$PYTHONPATH}" ;;
esac
unset _gdr_f
if [ -z "${DRJIT_LIBLLVM_PATH:-}" ]; then
  for _gdr_f in $(dpkg -L libllvm19 2>/dev/null | grep -E '/libLLVM\.so\.19(\.[0-9]+)*$') \
                /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 /usr/lib/*/libLLVM-19.so; do
    if [ -f "$_gdr_f" ]; then export DRJIT_LIBLLVM_PATH="$_gdr_f"; break; fi
  done
  unset _gdr_f
fi
if [ -z "${ORT_DYLIB_PATH:-}" ]; then
  for _gdr_f in "$GDRECON_VENV"/lib/python3*/site-packages/onnxruntime/capi/libonnxruntime.so.*; do
    if [ -f "$_gdr_f" ]; then export ORT_DYLIB_PATH="$_gdr_f"; break; fi
  done
  unset _gdr_f
fi
