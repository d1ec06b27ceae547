#!/usr/bin/env bash
# Builds the `junction` Python package (python/) into the project venv that scripts/setup.sh
# made: its Python dependencies (first time only, from PyPI), the gRPC stubs generated from
# proto/ (python/junction/_proto, not committed), and the native module (maturin develop: the
# package is installed editable, so python/junction's sources are live). Seconds when up to
# date. `make test` and `make python` run it; `make run` does not need it.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=.venv
PY="$VENV/bin/python"
[ -x "$PY" ] || { echo "build-python: $VENV is missing: run scripts/setup.sh first" >&2; exit 1; }

# Pinned to what the package, its tests and the MetaDrive actor were verified with.
# metadrive-simulator installs physics only here: its asset download is skipped at run time
# (junction/metadrive_env.py), and the package's MetaDrive tests are skipped without it.
DEPS=(
    maturin==1.16.0 numpy==2.4.6 gymnasium==1.4.0 pettingzoo==1.27.0 pytest==9.2.0
    grpcio==1.85.3 grpcio-tools==1.85.1 protobuf==7.36.2 metadrive-simulator==0.4.3
)
missing=()
for dep in "${DEPS[@]}"; do
    name=${dep%%==*} want=${dep##*==}
    have=$("$PY" -c "import importlib.metadata as m; print(m.version('$name'))" 2>/dev/null || true)
    [ "$have" = "$want" ] || missing+=("$dep")
done
if [ ${#missing[@]} -gt 0 ]; then
    echo "build-python: installing ${missing[*]} into $VENV (first time only; metadrive-simulator ~3 minutes)"
    "$PY" -m pip install --disable-pip-version-check --no-input --no-cache-dir --quiet "${missing[@]}"
fi

# gRPC stubs: importable as junction._proto.junction_pb2(_grpc).
stubs=python/junction/_proto
if [ ! -f "$stubs/junction_pb2_grpc.py" ] || [ proto/junction.proto -nt "$stubs/junction_pb2_grpc.py" ]; then
    mkdir -p "$stubs"
    : > "$stubs/__init__.py"
    "$PY" -m grpc_tools.protoc --proto_path=junction/_proto=proto \
        --python_out=python --grpc_python_out=python proto/junction.proto
fi

# The native module; cargo's own up-to-date check makes a rebuild cheap. Its log is shown
# only when it fails.
log=$(mktemp)
trap 'rm -f "$log"' EXIT
if ! (cd python && VIRTUAL_ENV="$PWD/../$VENV" PATH="$PWD/../$VENV/bin:$PATH" \
        "../$VENV/bin/maturin" develop --release) >"$log" 2>&1; then
    cat "$log" >&2
    echo "build-python: maturin develop failed" >&2
    exit 1
fi
"$PY" -c "import junction, junction._proto.junction_pb2_grpc" \
    || { echo "build-python: the package does not import" >&2; exit 1; }
echo "build-python: junction installed in $VENV (editable, python/junction)"
