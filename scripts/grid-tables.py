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
import sys
import tomllib
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "python"))

# The smoothing (CoPO's, over SMOOTHING scene episodes: the reference rows are such means,
# where the runs' own rows are their windows of run.stats_window_scene_episodes) and the
# intervals over seeds.
from junction.analysis import (  # noqa: E402
    SMOOTHING,
    mean_ci,
    read_progress,
    smoothed_scene_success,
)

METHOD_ORDER = ["cl", "ippo", "ccppo-mf", "ccppo-concat", "copo", "dynamic-lcf"]
METHOD_LABEL = {"cl": "CL", "ippo": "IPPO", "ccppo-mf": "CCPPO-MF",
                "ccppo-concat": "CCPPO-Concat", "copo": "CoPO", "dynamic-lcf": "dynamic LCF"}
SCENE_AGENTS = {"intersection": 30, "roundabout": 40}
ENV_STEP_MARKS = [50_000, 100_000, 150_000, 200_000]
# CoPO's published curves (RLlib on MetaDrive 0.2.5, 8 seeds; shared/reference/metadrive-copo.md).
REFERENCE = [
    ("intersection", "*CoPO's IPPO on MetaDrive (reference)*",
     {100_000: 0.19, 150_000: 0.33, 200_000: 0.50}),
    ("intersection", "*CoPO on MetaDrive (reference)*", {200_000: 0.54}),
    ("roundabout", "*CoPO's IPPO on MetaDrive (reference)*", {100_000: 0.13, 200_000: 0.32}),
]


def fmt(values, digits=2, signed=False):
    mean, half = mean_ci(values)
    if mean is None:
        return "–"
    sign = "+" if signed else ""
    text = f"{mean:{sign}.{digits}f}"
    return text if half is None else f"{text} ± {half:.{digits}f}"


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
