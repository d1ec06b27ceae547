#!/usr/bin/env bash
# Idempotent set-up for a fresh clone: a project-local Python venv with the PyTorch that tch
# links against (LIBTORCH_USE_PYTORCH=1). Seconds when already done; ~1 minute and ~2.8 GB of
# download the first time. protoc needs nothing: the build uses a vendored one.
set -euo pipefail
cd "$(dirname "$0")/.."

TORCH_VERSION=2.13.0
VENV=.venv

command -v cargo >/dev/null || { echo "setup: cargo not found; install Rust (https://rustup.rs)" >&2; exit 1; }
PYTHON=${PYTHON:-python3}
command -v "$PYTHON" >/dev/null || { echo "setup: $PYTHON not found; install Python 3.9+" >&2; exit 1; }

installed_torch() {
    # Reading the version file avoids importing torch (slow).
    local f
    f=$(ls "$VENV"/lib/python3*/site-packages/torch/version.py 2>/dev/null | head -n1) || true
    [ -n "$f" ] && sed -n "s/^__version__ = '\([0-9.]*\).*/\1/p" "$f"
}

if [ "$(installed_torch)" = "$TORCH_VERSION" ]; then
    echo "setup: PyTorch $TORCH_VERSION present in $VENV"
    exit 0
fi
if [ ! -x "$VENV/bin/python" ]; then
    echo "setup: creating $VENV"
    "$PYTHON" -m venv "$VENV"
fi
echo "setup: installing PyTorch $TORCH_VERSION into $VENV (first time only; ~2.8 GB download)"
"$VENV/bin/python" -m pip install --disable-pip-version-check --no-input --quiet "torch==$TORCH_VERSION"
[ "$(installed_torch)" = "$TORCH_VERSION" ] || { echo "setup: PyTorch $TORCH_VERSION did not install" >&2; exit 1; }
echo "setup: done"
