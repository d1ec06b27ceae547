#!/usr/bin/env bash
# An ablation: variants ("arms") of one training set-up, each trained for BUDGET agent-steps
# with every seed in the local mode, its final checkpoint evaluated, then `python -m
# junction.analysis report --group-by-dir` (one column per arm) into OUT/report.
#
#   ARMS=results/ablation-5m/arms.tsv OUT=results/ablation-5m scripts/ablation.sh
#
# The arms file has one arm per line, `name<TAB>learner serve flags` ('#' starts a comment,
# an empty flag list is the defaults). The flags are split at spaces and nothing else, so a
# TOML string is written as it is: --set scenario.after_horizon="finish".
# Runs go seed-major (every arm's seed 1, then every arm's seed 2, ...), so a stopped
# ablation already has one seed of every arm. Knobs (environment; defaults in brackets):
#   ARMS             the arms file [required]
#   OUT              results directory [required]
#   BUDGET           agent-steps per run [5000000]
#   SEEDS            run.seed values [1 2 3]
#   ACTORS           local actors per run [2]
#   MAX_RUN_SECONDS  wall-clock cap per run, 0 for none [3600]
#   EVAL_EPISODES    agent episodes per evaluation [1000]
#   EVAL_SEED        evaluation seed: a validation seed, not the one final results use [777]
#   EVAL_SAMPLED     1: evaluate with sampled actions as well as the mean action (`actor eval
#                    --actions sample`, written beside it as eval-<scenario>-seed<S>-sample.*;
#                    the report tables the mean action's) [1]
#   SCENARIO         scenario name or file [intersection]
#   PRESET           a shipped preset the arms start from (`learner serve --preset`) [none:
#                    the defaults]
#   BIN              binaries [target/release]
#   FROM             a runs directory of an earlier ablation with the same arm names: each run
#                    starts as a copy of FROM/<arm>-s<seed> (its evaluation left behind) and
#                    continues from its newest checkpoint to BUDGET agent-steps [none]
# Resumable: the same command again keeps a run whose evaluation exists, continues one stopped
# part-way (checkpoints, no evaluation: a session's end, Ctrl-C) from its newest checkpoint,
# and trains the others.
set -uo pipefail
# The whole script is one block, read before any of it runs: editing this file while a long
# run executes it cannot change what that run does next.
{
cd "$(dirname "$0")/.."

: "${ARMS:?ARMS must name the arms file}" "${OUT:?OUT must name the results directory}"
BIN=${BIN:-target/release}
BUDGET=${BUDGET:-5000000}
SEEDS=${SEEDS:-1 2 3}
ACTORS=${ACTORS:-2}
MAX_RUN_SECONDS=${MAX_RUN_SECONDS:-3600}
EVAL_EPISODES=${EVAL_EPISODES:-1000}
EVAL_SEED=${EVAL_SEED:-777}
EVAL_SAMPLED=${EVAL_SAMPLED:-1}
SCENARIO=${SCENARIO:-intersection}
FROM=${FROM:-}
PRESET=${PRESET:-}

say() { echo "ablation: $(date +%H:%M:%S) $*"; }
[ -f "$ARMS" ] || { say "no arms file $ARMS" >&2; exit 1; }
for tool in learner actor; do
    [ -x "$BIN/$tool" ] || { say "$BIN/$tool is missing: run make build first" >&2; exit 1; }
done
mkdir -p "$OUT/runs"
interrupted=0
trap 'interrupted=1' INT TERM

names=()
flags=()
while IFS=$'\t' read -r name arm_flags; do
    case "$name" in '' | '#'*) continue ;; esac
    names+=("$name")
    flags+=("$arm_flags")
done <"$ARMS"
say "${#names[@]} arms × $(wc -w <<<"$SEEDS") seeds, $BUDGET agent-steps each, into $OUT"

for seed in $SEEDS; do
    for i in "${!names[@]}"; do
        [ "$interrupted" = 1 ] && break 2
        name=${names[$i]}
        run_dir="$OUT/runs/$name-s$seed"
        eval_file="$run_dir/eval/eval-$(basename "$SCENARIO" .toml)-seed$EVAL_SEED.json"
        if [ -f "$eval_file" ]; then
            say "$name seed $seed: kept"
            continue
        fi
        resume=0
        continuing=""
        if compgen -G "$run_dir/checkpoints/ckpt-*" >/dev/null; then
            rm -rf "$run_dir/eval"
            resume=1
            continuing=", continuing from its newest checkpoint"
        elif [ -n "$FROM" ]; then
            rm -rf "$run_dir"
            if [ ! -d "$FROM/$name-s$seed/checkpoints" ]; then
                say "$name seed $seed: no run to continue in $FROM/$name-s$seed"
                continue
            fi
            cp -r "$FROM/$name-s$seed" "$run_dir"
            rm -rf "$run_dir/eval"
            resume=1
            continuing=", continuing $FROM/$name-s$seed"
        else
            rm -rf "$run_dir"
        fi
        mkdir -p "$run_dir"
        say "$name seed $seed: training (${flags[$i]:-defaults})$continuing"
        # shellcheck disable=SC2086 # the arm's flags are a list of flags
        RUN_DIR="$run_dir" RESUME="$resume" ACTORS="$ACTORS" MAX_SECONDS="$MAX_RUN_SECONDS" BIN="$BIN" \
            PRESET="$PRESET" nice scripts/run-local.sh --scenario "$SCENARIO" --seed "$seed" \
            --set "run.max_agent_steps=$BUDGET" --set "run.progress_interval_s=5" \
            ${flags[$i]} >>"$run_dir/train.log" 2>&1
        status=$?
        [ "$interrupted" = 1 ] && break 2
        if [ "$status" -ne 0 ]; then
            say "$name seed $seed: training failed (exit $status, $run_dir/train.log)"
            continue
        fi
        modes=mean
        [ "$EVAL_SAMPLED" = 1 ] && modes="mean sample"
        for actions in $modes; do
            log="$run_dir/eval.log"
            [ "$actions" = mean ] || log="$run_dir/eval-$actions.log"
            say "$name seed $seed: evaluating ($actions actions)"
            if ! nice "$BIN/actor" eval --checkpoint "$run_dir" --episodes "$EVAL_EPISODES" \
                --seed "$EVAL_SEED" --scenes 4 --actions "$actions" --out "$run_dir/eval" \
                >"$log" 2>&1; then
                say "$name seed $seed: evaluation with $actions actions failed ($log)"
            fi
        done
    done
done
if [ "$interrupted" = 1 ]; then
    # The report would mix the stopped run's training windows with the finished runs' evaluations.
    say "interrupted: report not rewritten; the same command resumes (the stopped run from its newest checkpoint)"
    exit 130
fi
say "report"
# The analysis module is standard-library Python: the system python3 runs it from python/.
PYTHONPATH=python python3 -m junction.analysis report --group-by-dir \
    --methods "$(IFS=,; echo "${names[*]}")" --eval-seeds "$EVAL_SEED" \
    --out "$OUT/report" "$OUT/runs"
exit
}
