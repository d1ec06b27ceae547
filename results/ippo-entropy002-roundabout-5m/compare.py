"""IPPO on the roundabout at the grid's 5 M with entropy_coef 0.002 and 0.005 against the grid's
IPPO, same seeds (from the repository root):

    python3 results/ippo-entropy002-roundabout-5m/compare.py

Means over seeds (training window, then the unseen seed 1000 with the mean action and with
sampled actions: success / crash / timeout), then each bonus − grid, mean ± 95 % t with each
seed's difference in brackets. The decision rests on the training columns; the unseen seed is
reported, not steered by. Measures and tables are results/dlcf-phi10-roundabout-5m/compare.py's.
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
    ("IPPO (grid-5m)", "results/grid-5m/runs/ippo-roundabout-s{}"),
    ("IPPO, entropy 0.005", "results/ippo-entropy-5m/runs/ippo-roundabout-s{}"),
    ("IPPO, entropy 0.002", "results/ippo-entropy002-roundabout-5m/runs/ippo-ent002-s{}"),
]
COLUMNS = phi10.SIX_SEEDS + [("timeout", "sample timeout_rate")]


def main():
    table = {label: {s: phi10.six_seed_measures(SCENE, ROOT / pattern.format(s)) for s in SEEDS}
             for label, pattern in ARMS}
    print(f"{SCENE}, seeds {SEEDS}, 5 M agent-steps (mean ± 95 % t):\n")
    phi10.print_means(table, COLUMNS, lambda m: m.get("success") is not None)
    base = table[ARMS[0][0]]
    for label, _ in ARMS[1:]:
        seeds = [s for s in SEEDS if table[label][s].get("success") is not None]
        print(f"\n{label} − grid-5m, same seed (n = {len(seeds)}; seed by seed in brackets):\n")
        phi10.print_paired(table[label], base, seeds, COLUMNS)


if __name__ == "__main__":
    main()
