#!/usr/bin/env bash
# Chaos soak (issue 42): scripts/chaos-soak.sh --minutes M --seed N [--out DIR] [--actors K]
# A learner, K gRPC actors, a hostile client and Prometheus on hosts of their own (network
# namespaces, scripts/netns.sh), TLS and the token on, faults drawn from the seed, then a clean
# stop and the fragment ledgers reconciled. Needs root and `ip netns` (else exits 77, skipped),
# the release binaries (cargo build --release --bins) and `make python` (the hostile client's
# gRPC stubs). docs/FAULTS.md ("Soak") has the details; scripts/chaos_soak.py --help the flags.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
[[ -x $PY ]] || PY=python3
exec "$PY" scripts/chaos_soak.py "$@"
