#!/usr/bin/env bash
# The learner trained on MetaDrive's own intersection with IPPO, its success curve beside
# CoPO's published IPPO curve, and the cross-simulator 2 × 2: policies trained in Junction's
# twin of that intersection and the MetaDrive-trained ones, each evaluated in the twin and in
# MetaDrive (1000 agent episodes each), over training seeds.
#
#   scripts/metadrive-experiments.sh [JUNCTION_RUN...]
#   BUDGET=5000000 SEEDS="1 2 3" TWIN_SEEDS="1 2 3" OUT=results/cross-sim-5m scripts/metadrive-experiments.sh
#
# JUNCTION_RUN: run directories, checkpoint directories or policy.safetensors trained in
# Junction's simulator, evaluated in both as the twin's row beside TWIN_SEEDS' runs.
#
# Resumable: rerun the same command. A training run that reached BUDGET is kept; one that was
# stopped continues from its newest checkpoint (`learner serve --resume`); an evaluation whose
# JSON exists is kept. Ctrl-C stops the current step (the learner writes a final checkpoint).
#
# Knobs (environment variables; defaults in brackets):
#   BUDGET          agent-steps per training run (run.max_agent_steps) [2500000]
#   SEEDS           run.seed values of the MetaDrive-trained runs [1 2]
#   TWIN_SEEDS      run.seed values of runs trained on JUNCTION_EVAL in Junction's simulator
#                   (scripts/ablation.sh, local mode, the defaults, BUDGET agent-steps each):
#                   the twin's row of the 2 × 2 [none]
#   ACTORS          MetaDrive actor processes per run (one core each, MetaDrive is
#                   single-threaded; the learner's updates take the rest) [2]
#   SCENARIO        the MetaDrive scenario to train on [intersection-on-metadrive]
#   JUNCTION_EVAL   Junction's scenario for the "evaluated in Junction" column: its twin of
#                   MetaDrive's intersection [intersection-metadrive]
#   EVAL_EPISODES   agent episodes per evaluation [1000]
#   EVAL_SEED       evaluation seed, held out from training's [1000]
#   MARKS           agent-step marks of the curve table
#                   [250000,500000,1000000,1500000,2000000,2500000,5000000]
#   PROGRESS_S      seconds between progress.jsonl lines [10]
#   LEARNER_FLAGS   extra `learner serve` flags, e.g. "--set ppo.learning_rate=1e-4"
#   OUT             results directory [results/metadrive]
#   BIN             directory of the learner and actor binaries [target/release]
#
# Writes OUT/REPORT.md (`python -m junction.analysis tables`: the curves at the marks beside
# CoPO's, the 2 × 2 over training seeds, every evaluation), OUT/report/ (`python -m
# junction.analysis report` over the runs), OUT/runs/ippo-s<seed>/ (each MetaDrive-trained
# run's learner.log, actor-<k>.log, progress.jsonl, checkpoints), OUT/runs/twin-s<seed>/ (the
# twin's runs, evaluated at home in their eval/) and OUT/eval/<cell>/ (eval JSON/CSV).
set -uo pipefail
cd "$(dirname "$0")/.."

BIN=${BIN:-target/release}
BUDGET=${BUDGET:-2500000}
SEEDS=${SEEDS:-1 2}
ACTORS=${ACTORS:-2}
SCENARIO=${SCENARIO:-intersection-on-metadrive}
JUNCTION_EVAL=${JUNCTION_EVAL:-intersection-metadrive}
EVAL_EPISODES=${EVAL_EPISODES:-1000}
EVAL_SEED=${EVAL_SEED:-1000}
MARKS=${MARKS:-250000,500000,1000000,1500000,2000000,2500000,5000000}
PROGRESS_S=${PROGRESS_S:-10}
LEARNER_FLAGS=${LEARNER_FLAGS:-}
OUT=${OUT:-results/metadrive}
PY=.venv/bin/python
TWIN_SEEDS=${TWIN_SEEDS:-}
junction_runs=("$@")
STARTED=$(date +%s)

say() { echo "metadrive-experiments: $*" >&2; }
die() { say "$*"; exit 1; }

for tool in learner actor; do
    [ -x "$BIN/$tool" ] || die "$BIN/$tool is missing: run make build first"
done
"$PY" -c "import junction._proto, metadrive" 2>/dev/null \
    || die "the junction package or metadrive-simulator is missing: run make python first"
case "$BUDGET" in '' | *[!0-9]*) die "BUDGET must be a number of agent-steps, not '$BUDGET'" ;; esac
for run in "${junction_runs[@]}"; do
    [ -e "$run" ] || die "$run does not exist"
done
mkdir -p "$OUT/runs" "$OUT/eval"

# Agent-steps the run in $1 has trained on (0 without progress).
trained() {
    [ -s "$1/progress.jsonl" ] || { echo 0; return; }
    tail -n 1 "$1/progress.jsonl" | "$PY" -c "import json, sys; print(json.loads(sys.stdin.read()).get('agent_steps', 0))" 2>/dev/null || echo 0
}

interrupted=0
trap 'interrupted=1' INT TERM

# Trains (or continues) the run in $1 with seed $2: learner serve on loopback gRPC plus
# ACTORS MetaDrive actors, each restarted if it dies while the learner runs.
train() {
    local run=$1 seed=$2 source
    if [ -d "$run/checkpoints" ] && ls "$run/checkpoints" | grep -q '^ckpt-'; then
        source=(--resume "$run")
        say "seed $seed: continuing $run from $(trained "$run") agent-steps"
    else
        rm -rf "$run"
        mkdir -p "$run"
        source=(--scenario "$SCENARIO" --seed "$seed" --run-dir "$run"
            --set "learner.algo=\"ippo\"" --set "run.max_agent_steps=$BUDGET"
            --set "run.progress_interval_s=$PROGRESS_S")
        say "seed $seed: training $SCENARIO to $BUDGET agent-steps in $run"
    fi
    rm -f "$run/endpoints.json"
    # shellcheck disable=SC2086 # LEARNER_FLAGS is a list of flags
    "$BIN/learner" serve "${source[@]}" --addr 127.0.0.1:0 --metrics-addr 127.0.0.1:0 \
        --shm-name "" --max-seconds 0 $LEARNER_FLAGS >>"$run/learner.log" 2>&1 &
    local learner=$!
    local waited=0
    until [ -s "$run/endpoints.json" ] && grep -q "\"pid\":$learner" "$run/endpoints.json"; do
        kill -0 "$learner" 2>/dev/null || { say "seed $seed: the learner exited at start-up (see $run/learner.log)"; return 1; }
        sleep 0.2
        waited=$((waited + 1))
        [ "$waited" -lt 600 ] || { kill "$learner"; say "seed $seed: the learner did not start"; return 1; }
    done
    local grpc
    grpc=$("$PY" -c "import json; print(json.load(open('$run/endpoints.json'))['grpc'])")
    local actors=()
    for k in $(seq 1 "$ACTORS"); do
        (
            while kill -0 "$learner" 2>/dev/null; do
                "$PY" -m junction.metadrive_actor --learner "http://$grpc" --seed "$k" \
                    --name "metadrive-$k" >>"$run/actor-$k.log" 2>&1 && break
                sleep 5
            done
        ) &
        actors+=($!)
    done
    while kill -0 "$learner" 2>/dev/null; do
        if [ "$interrupted" = 1 ]; then
            kill -TERM "$learner" 2>/dev/null
        fi
        sleep 2
    done
    wait "$learner"
    local status=$?
    for pid in "${actors[@]}"; do
        wait "$pid" 2>/dev/null
    done
    return $status
}

if [ -n "$TWIN_SEEDS" ]; then
    arms=$(mktemp)
    printf 'twin\t\n' >"$arms"
    ARMS="$arms" OUT="$OUT" SCENARIO="$JUNCTION_EVAL" BUDGET="$BUDGET" SEEDS="$TWIN_SEEDS" \
        EVAL_EPISODES="$EVAL_EPISODES" EVAL_SEED="$EVAL_SEED" EVAL_SAMPLED=0 BIN="$BIN" \
        MAX_RUN_SECONDS=0 scripts/ablation.sh || say "the twin's training stopped or failed (see above)"
    rm -f "$arms"
    [ "$interrupted" = 1 ] && die "stopped; rerun the same command to continue"
    for seed in $TWIN_SEEDS; do
        junction_runs+=("$OUT/runs/twin-s$seed")
    done
fi

for seed in $SEEDS; do
    [ "$interrupted" = 1 ] && break
    run=$OUT/runs/ippo-s$seed
    if [ "$(trained "$run")" -ge "$BUDGET" ]; then
        say "seed $seed: trained ($(trained "$run") agent-steps), kept"
        continue
    fi
    t0=$(date +%s)
    train "$run" "$seed" || say "seed $seed: the learner failed (see $run/learner.log)"
    say "seed $seed: $(trained "$run") agent-steps after $(( $(date +%s) - t0 )) s"
done
[ "$interrupted" = 1 ] && die "stopped; rerun the same command to continue"

# One evaluation: cell name $1, policy $2, simulator $3 (junction|metadrive).
evaluate() {
    local cell=$1 policy=$2 simulator=$3 dir=$OUT/eval/$1
    if ls "$dir"/eval-*.json >/dev/null 2>&1; then
        say "eval $cell: kept"
        return 0
    fi
    mkdir -p "$dir"
    say "eval $cell: $EVAL_EPISODES episodes"
    if [ "$simulator" = metadrive ]; then
        "$PY" -m junction.metadrive_eval --checkpoint "$policy" --scenario "$SCENARIO" \
            --episodes "$EVAL_EPISODES" --seed "$EVAL_SEED" --out "$dir" >"$dir/eval.log" 2>&1
    else
        "$BIN/actor" eval --checkpoint "$policy" --scenario "$JUNCTION_EVAL" \
            --episodes "$EVAL_EPISODES" --seed "$EVAL_SEED" --out "$dir" >"$dir/eval.log" 2>&1
    fi || { say "eval $cell failed (see $dir/eval.log)"; rm -f "$dir"/eval-*.json; }
}

for seed in $SEEDS; do
    run=$OUT/runs/ippo-s$seed
    [ -d "$run/checkpoints" ] || continue
    evaluate "metadrive-s$seed-in-metadrive" "$run" metadrive
    evaluate "metadrive-s$seed-in-junction" "$run" junction
done
for run in "${junction_runs[@]}"; do
    [ -e "$run" ] || continue
    name=$(basename "${run%/}")
    [ "$name" = policy.safetensors ] && name=$(basename "$(dirname "$run")")
    evaluate "junction-$name-in-metadrive" "$run" metadrive
    # The twin's runs were evaluated at home by ablation.sh.
    [ -f "$run/eval/eval-$JUNCTION_EVAL-seed$EVAL_SEED.json" ] \
        || evaluate "junction-$name-in-junction" "$run" junction
done

# The analysis module is standard-library Python: the system python3 runs it from python/.
PYTHONPATH=python python3 -m junction.analysis report "$OUT/runs" --out "$OUT/report" \
    --marks "$MARKS" >"$OUT/report.log" 2>&1 \
    || say "the report failed (see $OUT/report.log)"

{
    echo "# IPPO on MetaDrive's intersection, and across simulators"
    echo
    echo "\`$SCENARIO\` (MetaDrive $("$PY" -c "from importlib.metadata import version; print(version('metadrive-simulator'))")),"
    echo "seeds $SEEDS; Junction's twin \`$JUNCTION_EVAL\`, seeds ${TWIN_SEEDS:-none}; $BUDGET agent-steps"
    echo "per run; evaluations of $EVAL_EPISODES agent episodes on seed $EVAL_SEED, mean action."
    echo "Wall time $(( ($(date +%s) - STARTED) / 60 )) min. Made by:"
    echo
    echo "    PYTHONPATH=python python3 -m junction.analysis tables $OUT --marks $MARKS --eval-seed $EVAL_SEED --only marks,run-marks,cross-sim,evals"
    echo
    PYTHONPATH=python python3 -m junction.analysis tables "$OUT" --marks "$MARKS" \
        --eval-seed "$EVAL_SEED" --only marks,run-marks,cross-sim,evals
} >"$OUT/REPORT.md" || say "the tables failed (see $OUT/REPORT.md)"
say "done in $(( ($(date +%s) - STARTED) / 60 )) min: $OUT/REPORT.md"
