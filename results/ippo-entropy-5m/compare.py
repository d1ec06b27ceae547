"""IPPO at the grid's 5 M with the entropy bonus against the grid's IPPO, same seeds (from the
repository root):

    python3 results/ippo-entropy-5m/compare.py

Per scene: means over seeds (training window, then the unseen seed 1000 with the mean action
and with sampled actions: success / crash / timeout), then bonus − grid, mean ± 95 % t with each
seed's difference in brackets. Measures and tables are results/dlcf-phi10-roundabout-5m/compare.py's.
"""
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location(
    "phi10", ROOT / "results" / "dlcf-phi10-roundabout-5m" / "compare.py")
phi10 = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(phi10)

SEEDS = [1, 2, 3]
ARMS = [("IPPO (grid-5m)", "results/grid-5m"), ("IPPO, entropy 0.005", "results/ippo-entropy-5m")]
COLUMNS = phi10.SIX_SEEDS + [("timeout", "sample timeout_rate")]


def main():
    for scene in ("intersection", "roundabout"):
        table = {label: {s: phi10.six_seed_measures(scene, ROOT / out / f"runs/ippo-{scene}-s{s}")
                         for s in SEEDS} for label, out in ARMS}
        print(f"{scene}, seeds {SEEDS}, 5 M agent-steps (mean ± 95 % t):\n")
        phi10.print_means(table, COLUMNS, lambda m: True)
        base, arm = (table[label] for label, _ in ARMS)
        print(f"\nEntropy 0.005 − grid-5m, same seed (n = {len(SEEDS)}; seed by seed in brackets):\n")
        phi10.print_paired(arm, base, SEEDS, COLUMNS)
        print()


if __name__ == "__main__":
    main()
