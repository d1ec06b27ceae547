"""φ ≤ 10° with the entropy bonus on the roundabout at 5 M against the same seeds without it
and IPPO (run from the repository root):

    python3 results/dlcf-phi10-entropy-roundabout-5m/compare.py

Training (the last window) and the grid's evaluation (the unseen seed 1000, mean and sampled
actions), measured and paired as results/dlcf-phi10-roundabout-5m/compare.py does. The runs
without the bonus are results/dlcf-phi10-roundabout-5m's; IPPO's are results/grid-5m's.
"""
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location(
    "phi10", ROOT / "results" / "dlcf-phi10-roundabout-5m" / "compare.py")
phi10 = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(phi10)

SCENE = "roundabout"
SEEDS = [1, 2, 3]
ARMS = [
    ("φ ≤ 10° + bonus", lambda s: ROOT / f"results/dlcf-phi10-entropy-roundabout-5m/runs/phi10-ent005-s{s}"),
    ("φ ≤ 10°", lambda s: ROOT / f"results/dlcf-phi10-roundabout-5m/runs/phi10-s{s}"),
    ("IPPO", lambda s: ROOT / f"results/grid-5m/runs/ippo-{SCENE}-s{s}"),
]


def main():
    table = {label: {s: phi10.six_seed_measures(SCENE, run(s)) for s in SEEDS} for label, run in ARMS}
    columns = phi10.SIX_SEEDS
    print(f"{SCENE}, seeds {SEEDS}, 5 M agent-steps (mean ± 95 % t over the evaluated seeds):\n")
    phi10.print_means(table, columns, lambda m: m.get("mean scene_success_rate") is not None)
    arm = table["φ ≤ 10° + bonus"]
    evaluated = [s for s in SEEDS if arm[s].get("mean scene_success_rate") is not None]
    for base_label in ("φ ≤ 10°", "IPPO"):
        print(f"\nφ ≤ 10° + bonus − {base_label}, same seed (seed by seed in brackets):\n")
        phi10.print_paired(arm, table[base_label], evaluated, columns, count=True)


if __name__ == "__main__":
    main()
