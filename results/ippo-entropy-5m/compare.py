"""IPPO at the grid's 5 M with the entropy bonus against the grid's IPPO, same seeds (from the
repository root):

    python3 results/ippo-entropy-5m/compare.py

Per scene: means over seeds (training window, then the unseen seed 1000 with the mean action
and with sampled actions: success / crash / timeout), then bonus − grid per seed, mean ± 95 % t.
"""
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("grid_tables", ROOT / "scripts" / "grid-tables.py")
grid_tables = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(grid_tables)

SEEDS = [1, 2, 3]
UNSEEN_SEED = 1000
ARMS = [("IPPO (grid-5m)", "results/grid-5m"), ("IPPO, entropy 0.005", "results/ippo-entropy-5m")]
COLUMNS = ["training success", "crash", "timeout", "mean action: success", "crash", "timeout",
           "sampled: success", "crash", "timeout"]


def measures(run_dir, scene):
    """The columns' values of one run, in order."""
    w = grid_tables.read_progress(run_dir)[-1]["scene_window"]
    values = [w["success_rate"], w["crash_rate"], w["timeout_rate"]]
    for actions in ("mean", "sample"):
        m = grid_tables.read_eval(run_dir, scene, UNSEEN_SEED, actions)["metrics"]
        values += [m["scene_success_rate"]["value"], m["scene_crash_rate"]["value"],
                   m["timeout_rate"]["value"]]
    return values


def main():
    header = "| scene | arm | " + " | ".join(COLUMNS) + " |\n|" + "---|" * (len(COLUMNS) + 2)
    print(header)
    table = {}
    for scene in ("intersection", "roundabout"):
        for label, out in ARMS:
            runs = [measures(ROOT / out / f"runs/ippo-{scene}-s{s}", scene) for s in SEEDS]
            table[scene, label] = runs
            cells = [grid_tables.fmt([r[i] for r in runs]) for i in range(len(COLUMNS))]
            print(f"| {scene} | {label} | " + " | ".join(cells) + " |")
    print(f"\nEntropy 0.005 − grid-5m, same seed (n = {len(SEEDS)}):\n")
    print(header)
    for scene in ("intersection", "roundabout"):
        base, arm = (table[scene, label] for label, _ in ARMS)
        cells = [grid_tables.fmt([a[i] - b[i] for a, b in zip(arm, base)], signed=True)
                 for i in range(len(COLUMNS))]
        print(f"| {scene} | bonus − grid | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
