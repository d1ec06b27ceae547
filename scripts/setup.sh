#!/usr/bin/env bash
# Idempotent set-up for a fresh clone; seconds when already done.
#  - a project-local Python venv with the PyTorch that tch links against (LIBTORCH_USE_PYTORCH=1);
#    ~1 minute and ~2.8 GB of download the first time;
#  - test tools: promtool (Debian's `prometheus` package: a real Prometheus server for the
#    metrics and dashboard tests) and kubernetes-validate (PyPI, into the venv) for the manifests.
# protoc needs nothing: the build uses a vendored one.
set -euo pipefail
cd "$(dirname "$0")/.."

TORCH_VERSION=2.13.0
KUBERNETES_VALIDATE_VERSION=1.37.0
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

pip_install() {
    "$VENV/bin/python" -m pip install --disable-pip-version-check --no-input --quiet "$@"
}

if [ ! -x "$VENV/bin/python" ]; then
    echo "setup: creating $VENV"
    "$PYTHON" -m venv "$VENV"
fi
if [ "$(installed_torch)" != "$TORCH_VERSION" ]; then
    echo "setup: installing PyTorch $TORCH_VERSION into $VENV (first time only; ~2.8 GB download)"
    pip_install "torch==$TORCH_VERSION"
    [ "$(installed_torch)" = "$TORCH_VERSION" ] || { echo "setup: PyTorch $TORCH_VERSION did not install" >&2; exit 1; }
fi
if [ ! -x "$VENV/bin/kubernetes-validate" ]; then
    echo "setup: installing kubernetes-validate $KUBERNETES_VALIDATE_VERSION into $VENV"
    pip_install "kubernetes-validate==$KUBERNETES_VALIDATE_VERSION"
fi
if ! command -v promtool >/dev/null || ! command -v prometheus >/dev/null; then
    if [ "$(id -u)" -ne 0 ] || ! command -v apt-get >/dev/null; then
        echo "setup: promtool/prometheus missing; install Debian's 'prometheus' package (needs root)" >&2
        exit 1
    fi
    echo "setup: installing Debian's prometheus package (promtool and a Prometheus server for tests)"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends prometheus >/dev/null
    # The package starts a system service where an init system runs; tests start their own.
    (command -v service >/dev/null && service prometheus stop) >/dev/null 2>&1 || true
fi
echo "setup: ready (PyPI torch $TORCH_VERSION in $VENV, $(promtool --version 2>&1 | head -n1))"
