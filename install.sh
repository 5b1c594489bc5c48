#!/usr/bin/env bash
# Set up EndoGSim in ./.venv. Usage: ./install.sh [test] [cuda]
#   test  also install the test dependencies (pytest)
#   cuda  force the CUDA extras (gsplat); chosen automatically when nvidia-smi sees a GPU
# Without a GPU it installs the CPU build of PyTorch (2.13.0), never the multi-GB CUDA build.
set -euo pipefail
cd "$(dirname "$0")"
PY=${PYTHON:-python3}
want_test=0; want_cuda=0
for arg in "$@"; do
  case "$arg" in
    test) want_test=1 ;;
    cuda) want_cuda=1 ;;
    *) echo "install.sh: unknown argument '$arg' (expected: test, cuda)" >&2; exit 2 ;;
  esac
done
if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then want_cuda=1; fi

[ -x .venv/bin/python ] || "$PY" -m venv .venv
PIP=".venv/bin/python -m pip"
$PIP install --quiet --upgrade pip
if [ "$want_cuda" = 1 ]; then
  $PIP install --quiet "torch>=2.4,<2.15"
else
  # The CPU build. TORCH_INDEX_URL may name PyTorch's CPU wheel index where the default index
  # would serve a CUDA build (plain Linux PyPI does).
  $PIP install --quiet "torch==2.13.0" ${TORCH_INDEX_URL:+--index-url "$TORCH_INDEX_URL"}
fi
extras=""
[ "$want_test" = 1 ] && extras="test"
[ "$want_cuda" = 1 ] && extras="${extras:+$extras,}cuda"
$PIP install --quiet -e ".${extras:+[$extras]}"
echo "EndoGSim installed in $(pwd)/.venv ($( .venv/bin/python -c 'import torch; print("torch", torch.__version__)'))"
