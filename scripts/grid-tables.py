#!/usr/bin/env python3
"""The tables of RESULTS.md's grid sections, from an experiment grid's runs.

    scripts/grid-tables.py results/grid-5m > tables.md
    scripts/grid-tables.py results/grid-5m results/seeds456-5m/*-s? 1000   # more seeds, one table
    scripts/grid-tables.py --replace results/grid-5m results/dlcf-phi10-roundabout-5m/grid-s123.tsv

Reads each OUT/grid.tsv (the runs `scripts/experiments.sh` finished; several OUTs are read as
one grid, so seeds added later in other directories join the same tables; an OUT may also name
a grid.tsv-shaped file itself). The same method, scene and seed in two OUTs is an error, or
with --replace the later one's run replaces the earlier's (a method re-run at new defaults).
Each run is read from its directory (progress.jsonl, eval/*.json) or, once the raw files are
gone, from the summary.json of the results folder that held it. Prints, in Markdown: every
run's figures, Table 1 per scene, each method against IPPO of the same seed, and the training
curves at CoPO's reference environment steps. A thin front to `junction.analysis` (its
`grid` command prints the same from results folders): standard library only, no venv needed.
"""

import csv
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "python"))

from junction.analysis import (  # noqa: E402,F401  (smoothed_scene_success: for importers)
    SMOOTHING,
    RawRun,
    RunRecord,
    mean_ci,
    record_from_run,
    read_progress,
    smoothed_scene_success,
)
from junction.analysis.summary import SUMMARY, read_summary  # noqa: E402
from junction.analysis.tables import grid_tables  # noqa: E402


def record_of(run_dir: Path, row: dict) -> RunRecord:
    """The run from its directory (method, scene and seed as grid.tsv names them), else from
    the summary.json of a folder above it."""
    if (run_dir / "progress.jsonl").exists():
        run = RawRun(run_dir)
        run.method, run.scene, run.seed = row["method"], row["scene"], int(row["seed"])
        inside = run_dir.parent.name == "runs"
        return RunRecord(record_from_run(run, f"runs/{run_dir.name}" if inside else run_dir.name),
                         str(run_dir.parent.parent if inside else run_dir.parent))
    for folder in run_dir.parents:
        if (folder / SUMMARY).exists():
            name = str(run_dir.relative_to(folder))
            for entry in read_summary(folder)["runs"]:
                if entry["name"] == name:
                    return RunRecord(entry, str(folder))
            break
    sys.exit(f"{run_dir}: no progress.jsonl, nor a summary.json above it that has the run")


def read_grid(root: Path):
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
            candidates = [REPO / run_dir, root / "runs" / run_dir.name]
            run_dir = next((c for c in candidates if c.exists()), REPO / run_dir)
        record = record_of(run_dir, row)
        record.method, record.scene, record.seed = row["method"], row["scene"], int(row["seed"])
        runs.append(record)
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
        for run in read_grid(root):
            key = (run.method, run.scene, run.seed)
            # The same run twice would count one seed as two in every interval.
            if key in seen and not replace:
                sys.exit(f"{run.method} on {run.scene}, seed {run.seed}, is in both {seen[key]} "
                         f"and {root}: give each run once (or --replace)")
            seen[key] = root
            by_key[key] = run
    print(grid_tables(list(by_key.values()), eval_seed), end="")


if __name__ == "__main__":
    main()
