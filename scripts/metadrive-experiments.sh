#!/usr/bin/env bash
# Part 3 of issue #14: the learner trained on MetaDrive's own intersection with IPPO (seeds
# 1 and 2 by default), its success curve beside CoPO's published IPPO curve, then the 2 × 2
# cross-simulator evaluation: a policy trained in Junction and the MetaDrive-trained ones, each
# evaluated in Junction's intersection and in MetaDrive's (1000 agent episodes each).
#
#   scripts/metadrive-experiments.sh [JUNCTION_CHECKPOINT]
#   BUDGET=5000000 OUT=results/metadrive-5m scripts/metadrive-experiments.sh results/grid-1m/runs/ippo-intersection-s1
#
# JUNCTION_CHECKPOINT: a run directory, checkpoint directory or policy.safetensors trained in
# Junction's simulator; without it the table has only the MetaDrive-trained rows.
#
# Resumable: rerun the same command. A training run that reached BUDGET is kept; one that was
# stopped continues from its newest checkpoint (`learner serve --resume`); an evaluation whose
# JSON exists is kept. Ctrl-C stops the current step (the learner writes a final checkpoint).
#
# Knobs (environment variables; defaults in brackets):
#   BUDGET          agent-steps per training run (run.max_agent_steps) [2500000]
#   SEEDS           run.seed values [1 2]
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
# Writes OUT/REPORT.md (curve points at the marks, the 2 × 2 table with 95 % intervals, the
# commands), OUT/report/ (`python -m junction.analysis report` over the runs),
# OUT/runs/ippo-s<seed>/ (each run's learner.log, actor-<k>.log, progress.jsonl, checkpoints)
# and OUT/eval/<cell>/ (eval JSON/CSV).
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
JUNCTION_CHECKPOINT=${1:-}
STARTED=$(date +%s)

say() { echo "metadrive-experiments: $*" >&2; }
die() { say "$*"; exit 1; }

for tool in learner actor; do
    [ -x "$BIN/$tool" ] || die "$BIN/$tool is missing: run make build first"
done
"$PY" -c "import junction._proto, metadrive" 2>/dev/null \
    || die "the junction package or metadrive-simulator is missing: run make python first"
case "$BUDGET" in '' | *[!0-9]*) die "BUDGET must be a number of agent-steps, not '$BUDGET'" ;; esac
if [ -n "$JUNCTION_CHECKPOINT" ] && [ ! -e "$JUNCTION_CHECKPOINT" ]; then
    die "$JUNCTION_CHECKPOINT does not exist"
fi
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
if [ -n "$JUNCTION_CHECKPOINT" ]; then
    evaluate "junction-in-metadrive" "$JUNCTION_CHECKPOINT" metadrive
    evaluate "junction-in-junction" "$JUNCTION_CHECKPOINT" junction
fi

# The analysis module is standard-library Python: the system python3 runs it from python/.
PYTHONPATH=python python3 -m junction.analysis report "$OUT/runs" --out "$OUT/report" \
    --marks "$MARKS" >"$OUT/report.log" 2>&1 \
    || say "the report failed (see $OUT/report.log)"

"$PY" - "$OUT" "$BUDGET" "$MARKS" "$SEEDS" "$JUNCTION_CHECKPOINT" "$JUNCTION_EVAL" \
    "$SCENARIO" "$EVAL_EPISODES" "$EVAL_SEED" "$(( $(date +%s) - STARTED ))" <<'EOF'
"""OUT/REPORT.md: the curve at the marks beside CoPO's, and the cross-simulator table."""
import json, sys
from importlib.metadata import version
from pathlib import Path

out, budget, marks, seeds, junction_ckpt, junction_eval, scenario, episodes, eval_seed, wall = sys.argv[1:]
out, marks, seeds = Path(out), [int(m) for m in marks.split(",")], seeds.split()
# CoPO's IPPO on MetaDrive's intersection, 8 seeds: environment steps × 25 agent-steps.
copo = {2_500_000: 0.19, 3_750_000: 0.33, 5_000_000: 0.50, 6_250_000: 0.58, 7_500_000: 0.63}


def at(lines, mark, key):
    """The value of `key` on the first progress line at or past `mark` agent-steps."""
    for line in lines:
        if line.get("agent_steps", 0) >= mark:
            return key(line)
    return None


md = ["# IPPO on MetaDrive's intersection, and across simulators", ""]
md += [f"Scenario `{scenario}` (MetaDrive {version('metadrive-simulator')}, physics only), "
       f"budget {int(budget):,} agent-steps per seed, seeds {' '.join(seeds)}; evaluations of "
       f"{episodes} agent episodes, seed {eval_seed}. Wall time {int(wall) // 60} min.", ""]
md += ["## Training success at agent-step marks", "",
       "MetaDrive's definition (per MetaDrive episode the share of its agents that arrived, "
       "averaged over the last scene episodes of `progress.jsonl`'s `scene_window`; the "
       "stochastic training policy) and ours (share of the last agent episodes, `window`). "
       "CoPO's IPPO: its learning-curve figure, 8 seeds, environment steps × 25.", ""]
md.append("| agent-steps | " + " | ".join(f"seed {s} (MetaDrive's / ours)" for s in seeds)
          + " | CoPO's IPPO |")
md.append("|---|" + "---|" * (len(seeds) + 1))
runs = {s: [json.loads(l) for l in (out / f"runs/ippo-s{s}/progress.jsonl").read_text().splitlines()
            if l.strip()] if (out / f"runs/ippo-s{s}/progress.jsonl").exists() else [] for s in seeds}
for mark in marks:
    if mark > int(budget) and mark not in copo:
        continue
    cells = []
    for s in seeds:
        scene = at(runs[s], mark, lambda l: l.get("scene_window", {}).get("success_rate"))
        ours = at(runs[s], mark, lambda l: l.get("window", {}).get("success_rate"))
        cells.append("—" if scene is None else f"{scene:.3f} / {ours:.3f}")
    reference = f"{copo[mark]:.2f}" if mark in copo else "—"
    md.append(f"| {mark:,} | " + " | ".join(cells) + f" | {reference} |")
md.append("")


def cell(name):
    files = sorted((out / "eval" / name).glob("eval-*.json"))
    if not files:
        return None
    return json.loads(files[0].read_text())


def fmt(estimate):
    if estimate is None:
        return "—"
    low, high = estimate.get("low"), estimate.get("high")
    ci = f" [{low:.3f}, {high:.3f}]" if low is not None and high is not None else ""
    return f"{estimate['value']:.3f}{ci}"


md += ["## Cross-simulator evaluation", "",
       f"Every agent takes the policy's mean action. *In Junction*: `actor eval` on "
       f"`{junction_eval}` (Junction's twin of MetaDrive's intersection); *in MetaDrive*: "
       f"`python -m junction.metadrive_eval` on `{scenario}`. Success and crash over agent "
       "episodes with 95 % Wilson intervals; MetaDrive's success rate (per MetaDrive episode) "
       "with a 95 % t interval over scene episodes.", "",
       "| trained in | evaluated in | episodes | success | crash | out of road | success (MetaDrive's) |",
       "|---|---|---|---|---|---|---|"]
rows = [(f"MetaDrive, seed {s}", f"metadrive-s{s}") for s in seeds]
if junction_ckpt:
    rows.insert(0, (f"Junction (`{junction_ckpt}`)", "junction"))
for label, prefix in rows:
    for where in ("junction", "metadrive"):
        r = cell(f"{prefix}-in-{where}")
        if r is None:
            md.append(f"| {label} | {where} | — | — | — | — | — |")
            continue
        m = r["metrics"]
        md.append(f"| {label} | {'Junction' if where == 'junction' else 'MetaDrive'} | "
                  f"{r['episodes']} | {fmt(m['success_rate'])} | {fmt(m['crash_rate'])} | "
                  f"{fmt(m['out_of_road_rate'])} | {fmt(m.get('scene_success_rate'))} |")
md += ["", "`python -m junction.analysis report` over the runs: "
          "[report/report.md](report/report.md).", ""]
(out / "REPORT.md").write_text("\n".join(md))
print("\n".join(md))
EOF
say "done in $(( ($(date +%s) - STARTED) / 60 )) min: $OUT/REPORT.md"
