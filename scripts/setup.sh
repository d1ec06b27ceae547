#!/usr/bin/env bash
# Idempotent set-up for a fresh clone; well under a second when already done.
#   scripts/setup.sh          what `make run` and `make build` need, without root: a
#                             project-local Python venv holding the PyTorch that tch links
#                             against (LIBTORCH_USE_PYTORCH=1); ~2.8 GB download the first time.
#   scripts/setup.sh --test   that, plus the test tools `make test` needs: kubernetes-validate
#                             and tensorboard (PyPI, into the venv), promtool and a Prometheus
#                             server (Debian's `prometheus` package: installed with apt-get when
#                             run as root, as on CI; otherwise it must already be on PATH).
# A test tool that is missing and cannot be installed stops it with one line naming the package.
# protoc needs nothing: the build uses a vendored one.
set -euo pipefail
cd "$(dirname "$0")/.."

TORCH_VERSION=2.13.0
TORCH_INSTALL_GB=8
KUBERNETES_VALIDATE_VERSION=1.37.0
TENSORBOARD_VERSION=2.21.0
VENV=.venv

TEST_TOOLS=0
case "${1:-}" in
    "") ;;
    --test) TEST_TOOLS=1 ;;
    *) echo "usage: scripts/setup.sh [--test]" >&2; exit 2 ;;
esac

command -v cargo >/dev/null || { echo "setup: cargo not found; install Rust (https://rustup.rs)" >&2; exit 1; }
PYTHON=${PYTHON:-python3}
command -v "$PYTHON" >/dev/null || { echo "setup: $PYTHON not found; install Python 3.9+" >&2; exit 1; }

installed_torch() {
    # Reading the version file avoids importing torch (slow).
    local f
    f=$(ls "$VENV"/lib/python3*/site-packages/torch/version.py 2>/dev/null | head -n1) || true
    [ -n "$f" ] && sed -n "s/^__version__ = '\([0-9.]*\).*/\1/p" "$f"
}

# Installs PyPI test tools into the venv; on failure one line names them and where pip's
# output is.
pip_install() {
    local log
    log=$(mktemp "${TMPDIR:-/tmp}/junction-setup-pip.XXXXXX")
    if ! "$VENV/bin/python" -m pip install --disable-pip-version-check --no-input --no-cache-dir --quiet "$@" >"$log" 2>&1; then
        echo "setup: test tool missing: could not install PyPI package $* into $VENV (pip's output: $log)" >&2
        exit 1
    fi
    rm -f "$log"
}

if [ ! -x "$VENV/bin/python" ]; then
    echo "setup: creating $VENV"
    "$PYTHON" -m venv "$VENV" || {
        echo "setup: '$PYTHON -m venv' failed; Debian and Ubuntu ship it separately (package python3-venv)" >&2
        exit 1
    }
fi
if [ "$(installed_torch)" != "$TORCH_VERSION" ]; then
    # 2.74 GB of wheels sit in pip's temporary folder while 4.7 GB install beside them; checked
    # first, so a full disk stops here in a second rather than after the download.
    free_gb=$(df -Pk . | awk 'NR == 2 { printf "%d", $4 / 1048576 }')
    if [ "$free_gb" -lt "$TORCH_INSTALL_GB" ]; then
        echo "setup: PyTorch $TORCH_VERSION needs about $TORCH_INSTALL_GB GB free to install (2.7 GB of wheels while installing, 4.7 GB installed); $(pwd) has $free_gb GB free" >&2
        exit 1
    fi
    echo "setup: installing PyTorch $TORCH_VERSION into $VENV (first time only; ~2.8 GB download)"
    # pip's own output here: the download takes minutes and shows its progress. No wheel cache:
    # the venv keeps what it installs, and a cached copy would hold 2.7 GB more for nothing.
    "$VENV/bin/python" -m pip install --disable-pip-version-check --no-input --no-cache-dir "torch==$TORCH_VERSION" || {
        echo "setup: could not install PyPI package torch==$TORCH_VERSION (the libtorch tch links against) into $VENV" >&2
        exit 1
    }
    [ "$(installed_torch)" = "$TORCH_VERSION" ] || { echo "setup: PyTorch $TORCH_VERSION did not install" >&2; exit 1; }
fi
if [ "$TEST_TOOLS" -eq 0 ]; then
    echo "setup: ready to build and run (PyTorch $TORCH_VERSION in $VENV)"
    exit 0
fi

# ---- test tools (make test) ----
if [ ! -x "$VENV/bin/kubernetes-validate" ]; then
    echo "setup: installing kubernetes-validate $KUBERNETES_VALIDATE_VERSION into $VENV (tests of the Kubernetes manifests)"
    pip_install "kubernetes-validate==$KUBERNETES_VALIDATE_VERSION"
fi
if ! "$VENV/bin/python" -c "import tensorboard" >/dev/null 2>&1; then
    echo "setup: installing tensorboard $TENSORBOARD_VERSION into $VENV (the TensorBoard read-back test)"
    pip_install "tensorboard==$TENSORBOARD_VERSION"
fi
# Present means it runs: `command -v` alone also finds a file that cannot be executed.
runs() { "$1" --version >/dev/null 2>&1; }
if ! runs promtool || ! runs prometheus; then
    if [ "$(id -u)" -ne 0 ] || ! command -v apt-get >/dev/null; then
        echo "setup: test tool missing: promtool and prometheus (Debian package 'prometheus'); installing it needs root: sudo apt-get install prometheus" >&2
        exit 1
    fi
    echo "setup: installing Debian's prometheus package (promtool and a Prometheus server for tests)"
    export DEBIAN_FRONTEND=noninteractive
    if ! { apt-get update -qq && apt-get install -y -qq --no-install-recommends prometheus; } >/dev/null 2>&1; then
        echo "setup: test tool missing: promtool and prometheus (Debian package 'prometheus'); apt-get install prometheus failed" >&2
        exit 1
    fi
    # The package starts a system service where an init system runs; tests start their own.
    (command -v service >/dev/null && service prometheus stop) >/dev/null 2>&1 || true
fi
echo "setup: ready to test (PyTorch $TORCH_VERSION, kubernetes-validate, tensorboard in $VENV; $(promtool --version 2>&1 | head -n1))"
