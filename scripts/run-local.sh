#!/usr/bin/env bash
# README command 1's job: `learner serve --local-actors ACTORS`, the one-command local mode. The
# learner starts ACTORS `actor` processes connected to it over shared memory, restarts any that
# dies, and stops them when it exits; it trains on the default 4-way intersection for
# MAX_SECONDS.
#   MAX_SECONDS=600 ACTORS=2 PRESET=fast scripts/run-local.sh [extra learner flags, e.g. --set ppo.learning_rate=1e-4]
# RESUME=1 with RUN_DIR continues that run from its newest checkpoint (`learner serve --resume`).
# Ctrl-C stops the run cleanly (the learner writes a final checkpoint first).
set -euo pipefail
cd "$(dirname "$0")/.."

BIN=${BIN:-target/release}
ACTORS=${ACTORS:-2}
MAX_SECONDS=${MAX_SECONDS:-300}
# The fast preset (presets/fast.toml): one pass over large minibatches, the shortest wall-clock
# to a driving policy on two cores. PRESET= (empty) trains at the method grid's defaults.
PRESET=${PRESET-fast}
PRESET_FLAGS=()
[ -n "$PRESET" ] && PRESET_FLAGS=(--preset "$PRESET")
RUN_DIR=${RUN_DIR:-runs/local-$(date +%Y%m%d-%H%M%S)}
RUN_DIR_FLAG=--run-dir
[ "${RESUME:-0}" = 1 ] && RUN_DIR_FLAG=--resume

mkdir -p "$RUN_DIR"
echo "run-local: ${ACTORS} local actors over shared memory, preset ${PRESET:-none (the defaults)}; run directory $RUN_DIR (bound addresses in $RUN_DIR/endpoints.json)"
# exec: the terminal's Ctrl-C goes to the learner alone, which stops its actors in order.
# A shared-memory name of this run's own, so a second local run on the host does not clash.
exec "$BIN/learner" serve --addr 127.0.0.1:0 --metrics-addr 127.0.0.1:0 "$RUN_DIR_FLAG" "$RUN_DIR" \
    --shm-name "local-$$" --local-actors "$ACTORS" --max-seconds "$MAX_SECONDS" "${PRESET_FLAGS[@]}" "$@"
