#!/usr/bin/env python3
"""The tables of RESULTS.md's grid section, from an experiment grid's run directories.

    scripts/grid-tables.py results/grid-5m > tables.md
    scripts/grid-tables.py results/grid-5m results/seeds456-5m/* 1000   # more seeds, one table
    scripts/grid-tables.py --replace results/grid-5m results/dlcf-phi10-roundabout-5m/grid-s123.tsv

Reads each OUT/grid.tsv (the runs `scripts/experiments.sh` finished; several OUTs are read as
one grid, so seeds added later in other directories join the same tables; an OUT may also name
a grid.tsv-shaped file itself). The same method, scene and seed in two OUTs is an error, or
with --replace the later one's run replaces the earlier's (a method re-run at new defaults).
Then, per run, progress.jsonl
and the evaluation JSON of `actor eval` (mean action, and sampled where present). Prints, in
Markdown: every run's figures, Table 1 per scene, each method against IPPO of the same seed, and the training
curves at CoPO's reference environment steps (for runs with progress.jsonl's `scene_totals`, a
second row smoothed over 100 scene episodes, as CoPO's curves are). `learner report` (the grid's report/) covers
one run at a time and the 95 % intervals of one evaluation; these tables are over seeds.
Standard library only, so it runs without the venv.
"""

import csv
import json
import math
import sys
import tomllib
from pathlib import Path

# Two-sided 95 % quantiles of Student's t by degrees of freedom (tables; no scipy here).
T975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306,
        9: 2.262, 10: 2.228, 15: 2.131, 20: 2.086, 30: 2.042}

METHOD_ORDER = ["cl", "ippo", "ccppo-mf", "ccppo-concat", "copo", "dynamic-lcf"]
METHOD_LABEL = {"cl": "CL", "ippo": "IPPO", "ccppo-mf": "CCPPO-MF",
                "ccppo-concat": "CCPPO-Concat", "copo": "CoPO", "dynamic-lcf": "dynamic LCF"}
SCENE_AGENTS = {"intersection": 30, "roundabout": 40}
ENV_STEP_MARKS = [50_000, 100_000, 150_000, 200_000]
# CoPO's smoothing of its curves (RLlib's metrics_smoothing_episodes): the reference rows are
# means over the last 100 environment episodes, where the runs' own rows are their windows of
# run.stats_window_scene_episodes.
SMOOTHING = 100
# CoPO's published curves (RLlib on MetaDrive 0.2.5, 8 seeds; shared/reference/metadrive-copo.md).
REFERENCE = [
    ("intersection", "*CoPO's IPPO on MetaDrive (reference)*",
     {100_000: 0.19, 150_000: 0.33, 200_000: 0.50}),
    ("intersection", "*CoPO on MetaDrive (reference)*", {200_000: 0.54}),
    ("roundabout", "*CoPO's IPPO on MetaDrive (reference)*", {100_000: 0.13, 200_000: 0.32}),
]


def t_quantile(df):
    """The tabled quantile at the largest tabled df not above df (conservative)."""
    return T975[max(k for k in T975 if k <= df)]


def mean_ci(values):
    """Mean and half-width of the 95 % t interval (None where a single value gives none)."""
    values = [v for v in values if v is not None]
    if not values:
        return None, None
    mean = sum(values) / len(values)
    if len(values) < 2:
        return mean, None
    var = sum((v - mean) ** 2 for v in values) / (len(values) - 1)
    return mean, t_quantile(len(values) - 1) * math.sqrt(var / len(values))


def fmt(values, digits=2, signed=False):
    mean, half = mean_ci(values)
    if mean is None:
        return "–"
    sign = "+" if signed else ""
    text = f"{mean:{sign}.{digits}f}"
    return text if half is None else f"{text} ± {half:.{digits}f}"


def read_progress(run_dir):
    lines = []
    with open(run_dir / "progress.jsonl") as f:
        for line in f:
            line = line.strip()
            if line:
                lines.append(json.loads(line))
    return lines


def without_rolled_back(lines):
    """One history whose agent-steps only grow: a resumed learner trains on from its newest
    checkpoint, so each line drops the lines before it that are further on than itself (the
    training the resume rolled back), as `learner report` reads runs."""
    kept = []
    for line in lines:
        while kept and kept[-1]["agent_steps"] > line["agent_steps"]:
            kept.pop()
        kept.append(line)
    return kept


def smoothed_scene_success(lines, episodes=SMOOTHING, key="agent_steps"):
    """MetaDrive's training success smoothed as CoPO smoothed it, over the last `episodes`
    scene episodes (at least; whole progress lines apart), from the lines' `scene_totals`:
    (line[key], rate) per line with that many episodes of the run behind it, as `learner
    report` computes it. Empty for runs written before `scene_totals` existed."""
    lines = without_rolled_back(lines)
    out, behind, offset, previous = [], [(0, 0.0)], (0, 0.0), None
    for line in lines:
        totals = line.get("scene_totals")
        if not totals:
            return []
        # A resumed process counts from 0 again (its clock too): its totals continue the run's.
        if previous is not None and (
                totals["scene_episodes"] < previous["scene_totals"]["scene_episodes"]
                or line.get("elapsed_s", 0) < previous.get("elapsed_s", 0)):
            offset = behind[-1]
        here = (offset[0] + totals["scene_episodes"], offset[1] + totals["success"])
        base = next((b for b in reversed(behind) if b[0] <= here[0] - episodes), None)
        if base is not None:
            out.append((line[key], (here[1] - base[1]) / (here[0] - base[0])))
        behind.append(here)
        previous = line
    return out


def read_eval(run_dir, scene, seed, actions):
    suffix = "" if actions == "mean" else f"-{actions}"
    path = run_dir / "eval" / f"eval-{scene}-seed{seed}{suffix}.json"
    if not path.exists():
        return None
    return json.loads(path.read_text())


def last_stage_start(run_dir, budget):
    """CL's last stage (all agents) starts at the second-to-last curriculum fraction."""
    with open(run_dir / "config.toml", "rb") as f:
        stages = tomllib.load(f)["curriculum"]["stages"]
    return stages[-2] * budget if len(stages) > 1 else 0.0


class Run:
    def __init__(self, row, eval_seed):
        self.method, self.scene, self.seed = row["method"], row["scene"], int(row["seed"])
        self.dir = Path(row["run_dir"])
        self.progress = read_progress(self.dir)
        last = self.progress[-1]
        self.budget = last["agent_steps"]
        self.env_steps = last["env_steps"]
        self.success = last["scene_window"]["success_rate"]
        self.crash = last["scene_window"]["crash_rate"]
        start = last_stage_start(self.dir, self.budget) if self.method == "cl" else 0.0
        self.best = max(p["scene_window"]["success_rate"] for p in self.progress
                        if p["agent_steps"] >= start and p["scene_window"]["scene_episodes"] > 0)
        self.phi = (last.get("lcf") or {}).get("mean_deg")
        self.mean_eval = read_eval(self.dir, self.scene, eval_seed, "mean")
        self.sample_eval = read_eval(self.dir, self.scene, eval_seed, "sample")
        self.smoothed = smoothed_scene_success(self.progress, SMOOTHING, key="env_steps")

    def eval_metric(self, actions, name):
        result = self.mean_eval if actions == "mean" else self.sample_eval
        return None if result is None else result["metrics"][name]["value"]

    def scene_timeout(self, actions):
        """MetaDrive's shares sum to one per scene episode; the eval reports all but this."""
        shares = [self.eval_metric(actions, f"scene_{k}_rate")
                  for k in ("success", "crash", "out_of_road")]
        return None if None in shares else 1.0 - sum(shares)

    def success_at(self, env_steps, smoothed=False):
        """The training window at the last progress line by env_steps, or with `smoothed` the
        success over the SMOOTHING scene episodes before it (None: not reached, or no
        scene_totals to smooth from)."""
        if self.progress[-1]["env_steps"] < env_steps:
            return None
        if smoothed:
            before = [rate for steps, rate in self.smoothed if steps <= env_steps]
            return before[-1] if before else None
        return [p for p in self.progress if p["env_steps"] <= env_steps][-1]["scene_window"][
            "success_rate"]


def budget_label(runs):
    """The grid's budget as RESULTS names it (5 M): runs stop just past it."""
    return f"{min(r.budget for r in runs) / 1e6:.1f}".rstrip("0").rstrip(".") + " M"


def per_run(runs, eval_seed):
    at = budget_label(runs)
    print("### Runs (MetaDrive's success / crash / timeout)\n")
    print(f"| run | training at {at} | unseen seed {eval_seed}, mean action "
          f"| unseen seed {eval_seed}, sampled |")
    print("|---|---|---|---|")
    order = {m: i for i, m in enumerate(METHOD_ORDER)}
    for r in sorted(runs, key=lambda r: (order.get(r.method, 99), list(SCENE_AGENTS).index(
            r.scene) if r.scene in SCENE_AGENTS else 99, r.seed)):
        window = r.progress[-1]["scene_window"]
        training = f"{r.success:.2f} / {r.crash:.2f} / {window['timeout_rate']:.2f}"
        if r.method in ("copo", "dynamic-lcf") and r.phi is not None:
            training += f" ({'μ' if r.method == 'copo' else 'φ'} {r.phi:.0f}°)"
        evaluated = []
        for actions in ("mean", "sample"):
            success = r.eval_metric(actions, "scene_success_rate")
            evaluated.append("–" if success is None else
                             f"{success:.3f} / {r.eval_metric(actions, 'scene_crash_rate'):.3f}"
                             f" / {r.scene_timeout(actions):.3f}")
        name = f"{r.method}-{r.scene}-s{r.seed}"
        label = name if r.dir.name == name else f"{name} ({r.dir.parent.parent.name}/{r.dir.name})"
        print(f"| {label} | {training} | " + " | ".join(evaluated) + " |")
    print()


def table1(runs, scene):
    at = budget_label(runs)
    print(f"### Table 1 — {scene} ({SCENE_AGENTS.get(scene, '?')} agents)\n")
    print(f"| method | seeds | env steps (k) | training success at {at} | best window by {at} "
          "| training crash | unseen, mean action: success | crash | timeout | steps per agent "
          "| arrivals per 300 steps | unseen, sampled: success | crash |")
    print("|" + "---|" * 13)
    phis = []
    for method in METHOD_ORDER:
        rs = [r for r in runs if r.scene == scene and r.method == method]
        if not rs:
            print(f"| {METHOD_LABEL[method]} | 0 | not run yet |" + " |" * 10)
            continue
        env_k = sum(r.env_steps for r in rs) / len(rs) / 1000
        cells = [
            fmt([r.success for r in rs]), fmt([r.best for r in rs]), fmt([r.crash for r in rs]),
            fmt([r.eval_metric("mean", "scene_success_rate") for r in rs]),
            fmt([r.eval_metric("mean", "scene_crash_rate") for r in rs]),
            fmt([r.scene_timeout("mean") for r in rs]),
            fmt([r.eval_metric("mean", "length_mean") for r in rs], 0),
            fmt([r.eval_metric("mean", "successes_per_300") for r in rs], 1),
            fmt([r.eval_metric("sample", "scene_success_rate") for r in rs]),
            fmt([r.eval_metric("sample", "scene_crash_rate") for r in rs]),
        ]
        print(f"| {METHOD_LABEL[method]} | {len(rs)} | {env_k:.0f} | " + " | ".join(cells) + " |")
        if method in ("copo", "dynamic-lcf"):
            phis.append((METHOD_LABEL[method], [r.phi for r in sorted(rs, key=lambda r: r.seed)]))
    print()
    for label, values in phis:
        angle = "μ" if label == "CoPO" else "φ"
        print(f"{angle} at {at}, {label}: " + ", ".join(f"{v:.0f}°" for v in values) + "\n")


def paired(runs, scenes):
    print("### Against IPPO, seed by seed\n")
    print("Each method minus IPPO of the same seed and scene (mean ± 95 % t over the paired "
          "seeds):\n")
    print("| scene | method − ippo | n | training success | training crash | unseen mean success "
          "| crash | unseen sampled success | crash |")
    print("|" + "---|" * 9)
    for scene in scenes:
        base = {r.seed: r for r in runs if r.scene == scene and r.method == "ippo"}
        for method in sorted({r.method for r in runs if r.scene == scene} - {"ippo"}):
            pairs = [(r, base[r.seed]) for r in runs
                     if r.scene == scene and r.method == method and r.seed in base]
            if not pairs:
                continue

            def diff(get):
                values = [(get(a), get(b)) for a, b in pairs]
                return fmt([x - y for x, y in values if x is not None and y is not None],
                           signed=True)

            cells = [
                diff(lambda r: r.success), diff(lambda r: r.crash),
                diff(lambda r: r.eval_metric("mean", "scene_success_rate")),
                diff(lambda r: r.eval_metric("mean", "scene_crash_rate")),
                diff(lambda r: r.eval_metric("sample", "scene_success_rate")),
                diff(lambda r: r.eval_metric("sample", "scene_crash_rate")),
            ]
            print(f"| {scene} | {method} | {len(pairs)} | " + " | ".join(cells) + " |")
    print()


def curves(runs, scenes):
    print("### Against CoPO's reference curves\n")
    header = " | ".join(f"{m // 1000}k env steps" for m in ENV_STEP_MARKS)
    print(f"| scene | method | {header} |")
    print("|" + "---|" * (2 + len(ENV_STEP_MARKS)))
    for scene in scenes:
        for method in sorted({r.method for r in runs if r.scene == scene} - {"cl"}):
            rs = [r for r in runs if r.scene == scene and r.method == method]
            for smoothed in (False, True):
                # Runs written before scene_totals have no smoothed row.
                if smoothed and not all(r.smoothed for r in rs):
                    continue
                cells = []
                for mark in ENV_STEP_MARKS:
                    values = [r.success_at(mark, smoothed) for r in rs]
                    # A mark some seed did not reach is left out rather than averaged over fewer.
                    cells.append("–" if None in values else fmt(values))
                label = f"{method}, {SMOOTHING} scene episodes" if smoothed else method
                print(f"| {scene} | {label} | " + " | ".join(cells) + " |")
    for scene, label, points in REFERENCE:
        if scene in scenes:
            cells = [f"{points[m]:.2f}" if m in points else "–" for m in ENV_STEP_MARKS]
            print(f"| {scene} | {label} | " + " | ".join(cells) + " |")
    print()


def read_grid(root, eval_seed):
    grid = root if root.suffix == ".tsv" else root / "grid.tsv"
    root = grid.parent
    if not grid.exists():
        sys.exit(f"{grid} not found: run scripts/experiments.sh with OUT={root} first")
    with open(grid) as f:
        rows = [row for row in csv.DictReader(f, delimiter="\t") if row["status"] == "ok"]
    runs = []
    for row in rows:
        run_dir = Path(row["run_dir"])
        # grid.tsv holds paths relative to the repository root; allow any working directory.
        if not run_dir.exists():
            run_dir = root / "runs" / run_dir.name
        runs.append(Run(dict(row, run_dir=str(run_dir)), eval_seed))
    return runs


def main():
    args = sys.argv[1:]
    replace = "--replace" in args
    args = [a for a in args if a != "--replace"]
    eval_seed = int(args.pop()) if args and args[-1].isdigit() else 1000
    if not args:
        sys.exit("usage: scripts/grid-tables.py [--replace] OUT [OUT ...] [EVAL_SEED]   "
                 "(each OUT holds grid.tsv or is one)")
    by_key, seen = {}, {}
    for root in map(Path, args):
        for run in read_grid(root, eval_seed):
            key = (run.method, run.scene, run.seed)
            # The same run twice would count one seed as two in every interval.
            if key in seen and not replace:
                sys.exit(f"{run.method} on {run.scene}, seed {run.seed}, is in both {seen[key]} "
                         f"and {root}: give each run once (or --replace)")
            seen[key] = root
            by_key[key] = run
    runs = list(by_key.values())
    scenes = [s for s in SCENE_AGENTS if any(r.scene == s for r in runs)]
    per_run(runs, eval_seed)
    for scene in scenes:
        table1(runs, scene)
    paired(runs, scenes)
    curves(runs, scenes)


if __name__ == "__main__":
    main()
