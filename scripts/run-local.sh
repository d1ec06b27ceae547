#!/usr/bin/env bash
# README command 1's job: one `learner serve` and ACTORS `actor` processes talking gRPC on
# loopback, training on the default 4-way intersection for MAX_SECONDS.
#   MAX_SECONDS=600 ACTORS=2 scripts/run-local.sh [extra learner flags, e.g. --set ppo.learning_rate=1e-4]
# Ctrl-C stops the run cleanly (the learner writes a final checkpoint first).
set -euo pipefail
# Children get their own process groups, so a terminal's Ctrl-C reaches only this script,
# which then asks each child exactly once to stop (a second signal makes the learner skip its
# final checkpoint).
set -m
cd "$(dirname "$0")/.."

BIN=${BIN:-target/release}
ACTORS=${ACTORS:-2}
MAX_SECONDS=${MAX_SECONDS:-300}
RUN_DIR=${RUN_DIR:-runs/local-$(date +%Y%m%d-%H%M%S)}
pids=()

stop() {
    trap - INT TERM
    echo "run-local: stopping"
    kill -TERM "${pids[@]}" 2>/dev/null || true
    wait || true
    exit 130
}
trap stop INT TERM

mkdir -p "$RUN_DIR"
"$BIN/learner" serve --addr 127.0.0.1:0 --metrics-addr 127.0.0.1:0 --run-dir "$RUN_DIR" \
    --max-seconds "$MAX_SECONDS" "$@" &
learner=$!
pids+=("$learner")

# The learner writes its bound addresses once it serves.
for _ in $(seq 1 600); do
    [ -s "$RUN_DIR/endpoints.json" ] && break
    kill -0 "$learner" 2>/dev/null || { echo "run-local: the learner exited during start-up" >&2; exit 1; }
    sleep 0.1
done
grpc=$(sed -n 's/.*"grpc":"\([^"]*\)".*/\1/p' "$RUN_DIR/endpoints.json")
metrics=$(sed -n 's/.*"metrics":"\([^"]*\)".*/\1/p' "$RUN_DIR/endpoints.json")
echo "run-local: learner on $grpc, metrics at http://$metrics/metrics, run directory $RUN_DIR"

for i in $(seq 1 "$ACTORS"); do
    "$BIN/actor" --learner "http://$grpc" --seed "$i" --name "local-$i" &
    pids+=("$!")
done

status=0
wait "$learner" || status=$?
# Actors exit by themselves once the learner announces the end of the run.
for pid in "${pids[@]:1}"; do
    wait "$pid" || true
done
echo "run-local: finished (learner exit status $status); checkpoints in $RUN_DIR/checkpoints, curve in $RUN_DIR/progress.jsonl"
exit "$status"
