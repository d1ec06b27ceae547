#!/usr/bin/env bash
# The experiment grid of issue #7 (paper §4): every method × scene × seed trained to an
# agent-step budget (the local mode: learner + actors over shared memory), each final
# checkpoint evaluated with `actor eval`, then `python -m junction.analysis report` and
# OUT/RESULTS.md.
#
#   make experiments BUDGET=200000                      # or: scripts/experiments.sh
#   BUDGET=2000000 SEEDS="1 2 3" METHODS="ippo copo" SCENES="intersection" scripts/experiments.sh
#
# Knobs (environment variables; defaults in brackets):
#   BUDGET           agent-steps each run trains for (run.max_agent_steps) [200000]
#   METHODS          learner.algo values, in table order [cl ippo ccppo-mf ccppo-concat copo dynamic-lcf]
#   SCENES           scenario names or files [intersection roundabout]
#   SEEDS            run.seed values [1 2 3]
#   ACTORS           actor processes per run [2]
#   MAX_RUN_SECONDS  wall-clock cap per training run, 0 = none [3600]
#   PROGRESS_S       seconds between progress.jsonl lines (points on the curves) [5]
#   EVAL_EPISODES    agent episodes per evaluation [1000]
#   EVAL_SEED        evaluation seed (held out from training's seeds) [1000]
#   EVAL_SCENES      scenes per evaluation [4]
#   EVAL_SAMPLED     1: evaluate with sampled actions as well as the mean action (`actor eval
#                    --actions sample`, eval-<scenario>-seed<S>-sample.*, log eval-sample.log;
#                    the report tables the mean action's) [1]
#   SUCCESS          success rate of the time-to-success table [0.8]
#   LEARNER_FLAGS    extra `learner serve` flags for every run, e.g. "--set ppo.learning_rate=1e-4"
#   FLAGS_<method>   extra flags for one method's runs, "-" in its name written "_"
#                    (FLAGS_ccppo_concat="--set ccppo.neighbours=8"). cl defaults to
#                    "--set curriculum.stage_agent_steps=<BUDGET/4>": its four stages fit the
#                    budget, as in CoPO's schedule.
#   OUT              results directory [results/grid-<date>]
#   RESUME           1: continue the grid in an existing OUT, keeping every run that its
#                    grid.tsv records as trained and evaluated, and continuing a run stopped
#                    part-way from its newest checkpoint [0]
#   BIN              directory of the actor and learner binaries [target/release]
#
# A method this build does not have is skipped and reported; a run that fails is recorded
# and the grid goes on. Ctrl-C stops the current run cleanly and reports what finished.
set -uo pipefail
# The whole script is one block, read before any of it runs: editing this file while a long
# run executes it cannot change what that run does next.
{
cd "$(dirname "$0")/.."

BIN=${BIN:-target/release}
BUDGET=${BUDGET:-200000}
METHODS=${METHODS:-cl ippo ccppo-mf ccppo-concat copo dynamic-lcf}
SCENES=${SCENES:-intersection roundabout}
SEEDS=${SEEDS:-1 2 3}
ACTORS=${ACTORS:-2}
MAX_RUN_SECONDS=${MAX_RUN_SECONDS:-3600}
PROGRESS_S=${PROGRESS_S:-5}
EVAL_EPISODES=${EVAL_EPISODES:-1000}
EVAL_SEED=${EVAL_SEED:-1000}
EVAL_SCENES=${EVAL_SCENES:-4}
EVAL_SAMPLED=${EVAL_SAMPLED:-1}
SUCCESS=${SUCCESS:-0.8}
LEARNER_FLAGS=${LEARNER_FLAGS:-}
OUT=${OUT:-results/grid-$(date +%Y%m%d-%H%M%S)}

say() { echo "experiments: $*"; }

for tool in learner actor; do
    [ -x "$BIN/$tool" ] || { say "$BIN/$tool is missing: run make build first" >&2; exit 1; }
done
case "$BUDGET" in '' | *[!0-9]*) say "BUDGET must be a number of agent-steps, not '$BUDGET'" >&2; exit 1 ;; esac

# The extra flags of one method: FLAGS_<method>, or its default.
method_flags() {
    local var="FLAGS_${1//-/_}"
    if [ -n "${!var+set}" ]; then
        echo "${!var}"
    elif [ "$1" = cl ]; then
        echo "--set curriculum.stage_agent_steps=$((BUDGET / 4))"
    fi
}

# Trains one run into $1 (method $2, scene $3, seed $4), continuing it from its newest
# checkpoint when $5 is 1. The one place a run is launched: run-local.sh, i.e. `learner serve
# --local-actors ACTORS` over shared memory.
launch_run() {
    local run_dir=$1 method=$2 scene=$3 seed=$4 continuing=$5
    # shellcheck disable=SC2046,SC2086 # the flag variables are lists of flags
    # The grid trains at the defaults (no preset): it is compared per agent-step.
    RUN_DIR="$run_dir" RESUME="$continuing" ACTORS="$ACTORS" MAX_SECONDS="$MAX_RUN_SECONDS" BIN="$BIN" \
        PRESET= scripts/run-local.sh --scenario "$scene" --seed "$seed" \
        --set "learner.algo=\"$method\"" \
        --set "run.max_agent_steps=$BUDGET" \
        --set "run.progress_interval_s=$PROGRESS_S" \
        $LEARNER_FLAGS $(method_flags "$method")
}

# A field of the last progress line (the learner writes compact JSON).
last_progress() {
    local file=$1/progress.jsonl key=$2
    [ -s "$file" ] || { echo 0; return; }
    tail -n 1 "$file" | grep -o "\"$key\":[0-9.e+-]*" | head -n 1 | cut -d: -f2
}

mkdir -p "$OUT/runs"
started=$(date +%s)
interrupted=0
trap 'interrupted=1' INT TERM

# Methods this build knows: `learner config` refuses an unknown learner.algo.
available=()
unavailable=()
for method in $METHODS; do
    if error=$(RUST_BACKTRACE=0 "$BIN/learner" config --set "learner.algo=\"$method\"" 2>&1 >/dev/null); then
        available+=("$method")
    else
        # The innermost cause, e.g. "unknown variant `x`, expected one of … in `learner.algo`".
        reason=$(grep -v '^\s*$' <<<"$error" | sed 's/^ *[0-9]*: //; s/^ *//' | tail -n 2 | paste -sd' ')
        say "method '$method' is not available in this build, skipped ($reason)"
        unavailable+=("$method")
    fi
done

runs=()
for method in "${available[@]}"; do
    for scene in $SCENES; do
        for seed in $SEEDS; do
            runs+=("$method|$scene|$seed")
        done
    done
done
total=${#runs[@]}
say "$total runs (${#available[@]} methods × $(wc -w <<<"$SCENES") scenes × $(wc -w <<<"$SEEDS") seeds), $BUDGET agent-steps each, into $OUT"

grid="$OUT/grid.tsv"
previous="$OUT/grid.previous.tsv"
if [ "${RESUME:-0}" = 1 ] && [ -f "$grid" ]; then
    mv "$grid" "$previous"
else
    rm -f "$previous"
fi
printf 'method\tscene\tseed\tstatus\ttrain_s\teval_s\tagent_steps\trun_dir\n' >"$grid"
good_runs=()
done_count=0
executed=0
for entry in "${runs[@]}"; do
    IFS='|' read -r method scene seed <<<"$entry"
    if [ "$interrupted" = 1 ]; then
        printf '%s\t%s\t%s\tnot run (interrupted)\t\t\t\t\n' "$method" "$scene" "$seed" >>"$grid"
        continue
    fi
    done_count=$((done_count + 1))
    run_dir="$OUT/runs/$method-$(basename "$scene" .toml)-s$seed"
    # RESUME: a run an earlier invocation trained and evaluated without failure is kept.
    earlier=$([ -f "$previous" ] && awk -F'\t' -v d="$run_dir" \
        '$8 == d && $6 != "" && $4 !~ /failed/' "$previous" | tail -n 1)
    if [ -n "$earlier" ]; then
        say "[$done_count/$total] $method on $scene, seed $seed: kept from the earlier invocation"
        echo "$earlier" >>"$grid"
        good_runs+=("$run_dir")
        continue
    fi
    eta=""
    if [ "$executed" -gt 0 ]; then
        eta=", ETA $(((($(date +%s) - started) / executed) * (total - done_count + 1) / 60)) min"
    fi
    executed=$((executed + 1))
    # RESUME: a run stopped part-way (checkpoints, no evaluation) continues from its newest
    # checkpoint; `learner serve` refuses to start a new run over another run's checkpoints.
    continuing=0
    if [ "${RESUME:-0}" = 1 ] && compgen -G "$run_dir/checkpoints/ckpt-*" >/dev/null; then
        continuing=1
    fi
    # A continued run's train_s adds what its earlier invocations spent (their last row).
    earlier_train_s=0
    if [ "$continuing" = 1 ] && [ -f "$previous" ]; then
        earlier_train_s=$(awk -F'\t' -v d="$run_dir" '$8 == d && $5 != "" { s = $5 } END { print s + 0 }' "$previous")
    fi
    say "[$done_count/$total] $method on $scene, seed $seed$eta$([ "$continuing" = 1 ] && echo ", continuing from its newest checkpoint")"
    run_start=$(date +%s)
    mkdir -p "$run_dir"
    launch_run "$run_dir" "$method" "$scene" "$seed" "$continuing" >>"$run_dir/train.log" 2>&1
    train_status=$?
    train_s=$(($(date +%s) - run_start))
    steps=$(last_progress "$run_dir" agent_steps)
    status=ok
    if [ "$interrupted" = 1 ]; then
        status="interrupted during training"
    elif [ "$train_status" -ne 0 ]; then
        status="training failed (exit $train_status, see $run_dir/train.log)"
    elif [ "${steps:-0}" -lt "$BUDGET" ]; then
        # The learner also stops early on a signal sent to it alone, not only at the cap.
        if [ "$MAX_RUN_SECONDS" -gt 0 ] && [ "$train_s" -ge "$MAX_RUN_SECONDS" ]; then
            why="MAX_RUN_SECONDS=$MAX_RUN_SECONDS"
        else
            why="after $train_s s, under MAX_RUN_SECONDS=$MAX_RUN_SECONDS: stopped from outside"
        fi
        status="stopped at ${steps:-0} agent-steps, before the budget ($why)"
    fi
    eval_s=""
    if [ "$train_status" -eq 0 ] && [ "$interrupted" = 0 ]; then
        eval_start=$(date +%s)
        modes=mean
        [ "$EVAL_SAMPLED" = 1 ] && modes="mean sample"
        for actions in $modes; do
            log="$run_dir/eval.log"
            [ "$actions" = mean ] || log="$run_dir/eval-$actions.log"
            if ! "$BIN/actor" eval --checkpoint "$run_dir" --episodes "$EVAL_EPISODES" \
                --seed "$EVAL_SEED" --scenes "$EVAL_SCENES" --actions "$actions" >"$log" 2>&1; then
                status="$status; eval with $actions actions failed (see $log)"
            fi
        done
        eval_s=$(($(date +%s) - eval_start))
        good_runs+=("$run_dir")
    fi
    train_s=$((train_s + earlier_train_s))
    say "[$done_count/$total] $status: ${steps:-0} agent-steps, training ${train_s} s, eval ${eval_s:-–} s"
    printf '%s\t%s\t%s\t%s\t%s\t%s\t%s\t%s\n' "$method" "$scene" "$seed" "$status" \
        "$train_s" "$eval_s" "${steps:-0}" "$run_dir" >>"$grid"
done
trap - INT TERM

wall=$(($(date +%s) - started))
report_status=0
if [ "${#good_runs[@]}" -gt 0 ]; then
    # The analysis module is standard-library Python: the system python3 runs it from python/.
    PYTHONPATH=python python3 -m junction.analysis report "${good_runs[@]}" --out "$OUT/report" \
        --methods "$(tr ' ' ',' <<<"$METHODS")" \
        --scenes "$(for s in $SCENES; do basename "$s" .toml; done | paste -sd,)" \
        --success-threshold "$SUCCESS" --eval-seeds "$EVAL_SEED" || report_status=$?
else
    say "no run finished training: no report"
    report_status=1
fi

# RESULTS.md: how the grid was made, what happened to every run, then the report.
{
    echo "# Results: the experiment grid"
    echo
    echo "Made by \`scripts/experiments.sh\` on $(date -u +%Y-%m-%d) in $((wall / 60)) min $((wall % 60)) s of wall time$([ -f "$previous" ] && echo " (this invocation; RESUME=1 kept earlier runs)")"
    echo "on $(nproc) cores ($(grep -m1 'model name' /proc/cpuinfo 2>/dev/null | cut -d: -f2 | sed 's/^ //'))."
    echo
    echo '```sh'
    echo "BUDGET=$BUDGET METHODS=\"$METHODS\" SCENES=\"$SCENES\" SEEDS=\"$SEEDS\" ACTORS=$ACTORS \\"
    echo "  EVAL_EPISODES=$EVAL_EPISODES EVAL_SEED=$EVAL_SEED EVAL_SCENES=$EVAL_SCENES EVAL_SAMPLED=$EVAL_SAMPLED MAX_RUN_SECONDS=$MAX_RUN_SECONDS \\"
    echo "  PROGRESS_S=$PROGRESS_S SUCCESS=$SUCCESS LEARNER_FLAGS=\"$LEARNER_FLAGS\" scripts/experiments.sh"
    echo '```'
    echo
    echo "- Budget: $BUDGET agent-steps per run; $ACTORS local actors per run (\`learner serve --local-actors\`, shared memory), learner on the CPU."
    echo "- Training seeds (\`run.seed\`): $SEEDS. Evaluation: \`actor eval\` of each final checkpoint, $EVAL_EPISODES agent episodes, seed $EVAL_SEED, $EVAL_SCENES scenes (held-out traffic), with the mean action$([ "$EVAL_SAMPLED" = 1 ] && echo " and with sampled actions (\`--actions sample\`, beside it as \`eval-*-sample.json\`; the tables are the mean action's)")."
    echo "- Methods: ${available[*]:-none}."
    for method in "${available[@]}"; do
        flags=$(method_flags "$method")
        [ -n "$flags" ] && echo "- Extra flags for $method: \`$flags\`."
    done
    if [ "${#unavailable[@]}" -gt 0 ]; then
        echo "- **Not available in this build, skipped:** ${unavailable[*]}."
    fi
    if [ "$interrupted" = 1 ]; then
        echo "- **Interrupted**: runs marked 'not run' did not happen."
    fi
    echo
    echo "## Runs"
    echo
    echo "| method | scene | seed | status | training (s) | eval (s) | agent-steps |"
    echo "|---|---|---|---|---|---|---|"
    tail -n +2 "$grid" | while IFS=$'\t' read -r m s d st t e a _; do
        echo "| $m | $s | $d | $st | $t | $e | $a |"
    done
    echo
    if [ -f "$OUT/report/report.md" ]; then
        # The report's headings one level down, its figure links relative to this file.
        tail -n +2 "$OUT/report/report.md" | sed -e 's/^## /### /' -e 's/^# /## /' \
            -e 's#](figures/#](report/figures/#g'
    else
        echo "No report: \`python -m junction.analysis report\` failed or had no finished run (exit $report_status)."
    fi
} >"$OUT/RESULTS.md"

say "done in $((wall / 60)) min: $OUT/RESULTS.md (grid $grid)"
[ "$interrupted" = 0 ] && [ "$report_status" = 0 ]
exit
}
