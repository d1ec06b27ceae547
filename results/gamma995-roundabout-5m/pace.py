"""Pace against the discount, from kept results (run from the repository root):

    python3 results/gamma995-roundabout-5m/pace.py

1. The intersection: the discount study's evaluations (seeds 1-3, validation seed 777, mean
   action): MetaDrive's success and crash, timeouts per agent episode, steps per agent episode,
   arrivals and failures per 300 scene steps.
2. The roundabout arms (this directory, γ = 0.995) against the 5 M grid's runs of the same
   method and seed at γ = 0.999: the training window (MetaDrive's success, crash, timeout,
   steps per agent episode) at 2.5 M and at the end, the same seed's differences, and evaluations on the validation seed
   (pilot) or the unseen seed 1000 (grid, as the grid evaluates).
"""
import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("grid_tables", ROOT / "scripts" / "grid-tables.py")
grid_tables = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(grid_tables)
fmt = grid_tables.fmt

INTERSECTION = [
    ("0.99, 5 M", "results/mdbrake-5m/runs/mdbrake-s{}"),
    ("0.995, 7.5 M", "results/gamma-7m5/runs/gamma995-s{}"),
    ("0.999, 7.5 M", "results/gamma999-7m5/runs/gamma999-s{}"),
    ("0.999 annealed, 15 M", "results/lr-linear-scratch-15m/runs/linear-s{}"),
]
EVAL_METRICS = [
    ("scene_success_rate", 2), ("scene_crash_rate", 2), ("timeout_rate", 2),
    ("length_mean", 0), ("successes_per_300", 1), ("failures_per_300", 1),
]
PILOT = [
    ("IPPO", "results/grid-5m/runs/ippo-roundabout-s{}", "results/gamma995-roundabout-5m/runs/ippo-g995-s{}"),
    ("dynamic LCF", "results/grid-5m/runs/dynamic-lcf-roundabout-s{}", "results/gamma995-roundabout-5m/runs/dlcf-g995-s{}"),
]


def eval_cells(runs, scene, seed, actions="mean"):
    evals = [grid_tables.read_eval(ROOT / r, scene, seed, actions) for r in runs]
    evals = [e for e in evals if e]
    if not evals:
        return ["–"] * len(EVAL_METRICS)
    return [fmt([e["metrics"][k]["value"] for e in evals], digits) for k, digits in EVAL_METRICS]


def window_at(progress, agent_steps):
    before = [p for p in progress if p["agent_steps"] <= agent_steps]
    return (before or progress)[-1]


def training_cells(runs):
    progress = [grid_tables.read_progress(ROOT / r) for r in runs if (ROOT / r / "progress.jsonl").exists()]
    if not progress:
        return ["–"] * 6
    mid = [window_at(p, 2_500_000) for p in progress]
    end = [p[-1] for p in progress]
    return [
        fmt([m["scene_window"]["success_rate"] for m in mid]),
        fmt([e["scene_window"]["success_rate"] for e in end]),
        fmt([e["scene_window"]["crash_rate"] for e in end]),
        fmt([e["scene_window"]["timeout_rate"] for e in end]),
        fmt([e["window"]["mean_length"] for e in end], 0),
        fmt([e["agent_steps"] / 1e6 for e in end], 1),
    ]


def main():
    seeds = [int(s) for s in sys.argv[1:]] or [1, 2, 3]
    print("Intersection, evaluated (seeds 1-3, validation seed 777, mean action):\n")
    print("| γ, budget | success | crash | timeout | steps per agent | arrivals per 300 steps | failures per 300 steps |")
    print("|---|---|---|---|---|---|---|")
    for label, pattern in INTERSECTION:
        runs = [pattern.format(s) for s in (1, 2, 3)]
        print(f"| {label} | " + " | ".join(eval_cells(runs, "intersection", 777)) + " |")

    print(f"\nRoundabout, training (seeds {', '.join(map(str, seeds))}):\n")
    print("| method, γ | success at 2.5 M | success at end | crash at end | timeout at end | steps per agent | agent-steps (M) |")
    print("|---|---|---|---|---|---|---|")
    for method, grid, pilot in PILOT:
        for gamma, pattern in (("0.999 (grid)", grid), ("0.995", pilot)):
            runs = [pattern.format(s) for s in seeds]
            print(f"| {method}, {gamma} | " + " | ".join(training_cells(runs)) + " |")

    print()
    for method, grid, pilot in PILOT:
        pairs = [(grid.format(s), pilot.format(s)) for s in seeds]
        if not all((ROOT / p / "progress.jsonl").exists() for pair in pairs for p in pair):
            continue
        low = [grid_tables.read_progress(ROOT / p) for _, p in pairs]
        high = [grid_tables.read_progress(ROOT / g) for g, _ in pairs]
        diff = lambda pick: fmt([pick(a) - pick(b) for a, b in zip(low, high)], signed=True)
        print(f"{method}, 0.995 − 0.999 seed by seed: success at 2.5 M "
              f"{diff(lambda p: window_at(p, 2_500_000)['scene_window']['success_rate'])}, at the end "
              f"{diff(lambda p: p[-1]['scene_window']['success_rate'])}, crash at the end "
              f"{diff(lambda p: p[-1]['scene_window']['crash_rate'])}, timeout at the end "
              f"{diff(lambda p: p[-1]['scene_window']['timeout_rate'])}")

    # Both arms here ran the same seeds and were evaluated on the same validation seed: pair them.
    ippo_runs = [PILOT[0][2].format(s) for s in seeds]
    dlcf_runs = [PILOT[1][2].format(s) for s in seeds]
    if all((ROOT / r / "progress.jsonl").exists() for r in ippo_runs + dlcf_runs):
        ippo_progress = [grid_tables.read_progress(ROOT / r)[-1] for r in ippo_runs]
        dlcf_progress = [grid_tables.read_progress(ROOT / r)[-1] for r in dlcf_runs]
        cells = [fmt([d["scene_window"][k] - i["scene_window"][k]
                      for d, i in zip(dlcf_progress, ippo_progress)], signed=True)
                 for k in ("success_rate", "crash_rate")]
        for actions in ("mean", "sample"):
            evals = [[grid_tables.read_eval(ROOT / r, "roundabout", 777, actions) for r in runs]
                     for runs in (dlcf_runs, ippo_runs)]
            if all(evals[0]) and all(evals[1]):
                cells += [fmt([d["metrics"][k]["value"] - i["metrics"][k]["value"]
                               for d, i in zip(*evals)], signed=True)
                          for k in ("scene_success_rate", "scene_crash_rate")]
        print("\nAt γ = 0.995, dynamic LCF − IPPO seed by seed (training success / crash at the end; "
              "validation seed 777 mean action, then sampled, success / crash): " + " / ".join(cells))

    print(f"\nRoundabout, evaluated (seeds {', '.join(map(str, seeds))}; γ = 0.999 on the unseen seed 1000 "
          "as the grid evaluates, γ = 0.995 on the validation seed 777):\n")
    print("| method, γ, actions | success | crash | timeout | steps per agent | arrivals per 300 steps | failures per 300 steps |")
    print("|---|---|---|---|---|---|---|")
    for method, grid, pilot in PILOT:
        for actions in ("mean", "sample"):
            for gamma, pattern, seed in (("0.999", grid, 1000), ("0.995", pilot, 777)):
                runs = [pattern.format(s) for s in seeds]
                print(f"| {method}, {gamma}, {actions} | "
                      + " | ".join(eval_cells(runs, "roundabout", seed, actions)) + " |")


if __name__ == "__main__":
    main()
