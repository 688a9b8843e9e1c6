#!/usr/bin/env bash
# Everything a fresh Debian/Ubuntu machine needs for wtopo: a virtual environment in .venv, the CPU build of
# torch (never the multi-GB CUDA wheel), and wtopo itself (editable). With --test also what the test suite
# needs: the `test` extra (pytest, ruff, pycolmap, and Open3D as the tests' reference) and the system
# libraries Open3D links. Idempotent: a second run only checks.
#
#   bash scripts/setup.sh          # to run wtopo
#   bash scripts/setup.sh --test   # to run the tests too (CI: .ci/run)
set -euo pipefail
cd "$(dirname "$0")/.."
TEST=0
for a in "$@"; do
  case $a in
    --test) TEST=1 ;;
    *) echo "setup.sh: unknown argument $a (expected --test)" >&2; exit 2 ;;
  esac
done
if [ $TEST = 1 ] && command -v apt-get >/dev/null 2>&1 && ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then
  # open3d-cpu (the tests' reference) links libusb-1.0; libgomp1 for its OpenMP kernels
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 libgomp1 >/dev/null
fi
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
# CPU machines: the torch 2.13.0 CPU build first, so the dependency range below installs nothing more.
.venv/bin/python -c "import torch" 2>/dev/null || .venv/bin/python -m pip install -q "torch==2.13.0"
if [ $TEST = 1 ]; then
  .venv/bin/python -m pip install -q -e ".[test]"
else
  .venv/bin/python -m pip install -q -e .
fi
