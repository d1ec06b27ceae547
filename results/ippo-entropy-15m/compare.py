"""IPPO to 15 M with the entropy bonus against the same seeds without it (from the root):

    python3 results/ippo-entropy-15m/compare.py

The tables of results/dlcf-phi10-12m/curves.py at the 15 M marks: per seed the training
window (MetaDrive's success / crash / timeout), the best window and the lowest after it, the
final checkpoint on the unseen seed 1000; then means over seeds and the paired differences.
"""
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("curves", ROOT / "results/dlcf-phi10-12m/curves.py")
curves = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(curves)

ARMS = [
    ("IPPO", lambda s: ROOT / f"results/ippo-15m-unseen/runs/linear-s{s}"),
    ("IPPO, entropy 0.005", lambda s: ROOT / f"results/ippo-entropy-15m/runs/ippo-ent005-s{s}"),
]
MARKS = [2.5e6, 5e6, 7.5e6, 10e6, 12.5e6, 15e6]

if __name__ == "__main__":
    curves.main(ARMS, [("IPPO, entropy 0.005", "IPPO")], MARKS)
