"""φ bounded at 10° against the same seeds' IPPO, dynamic LCF at 20° and r_N centred (run from
the repository root):

    python3 results/dlcf-phi10-roundabout-5m/compare.py roundabout
    python3 results/dlcf-phi10-roundabout-5m/compare.py intersection

The φ ≤ 10° runs are results/dlcf-phi10-<scene>-5m's, the others those that
results/dlcf-centred-<scene>-5m/compare.py tables. Its measures and columns: training, the last
window; evaluation, the final checkpoints on the validation seed 777, mean and sampled actions.
Then seeds 1-6 in training alone: seeds 1-3's IPPO and φ ≤ 20° runs are results/grid-5m's,
whose checkpoints were evaluated on the unseen seed only and not kept.
"""
import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location(
    "centred", ROOT / "results" / "dlcf-centred-roundabout-5m" / "compare.py")
centred = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(centred)
fmt = centred.fmt


def digits(key):
    return 0 if key == "steps" else 2


def main():
    scene = sys.argv[1] if len(sys.argv) > 1 else "roundabout"
    here = ROOT / "results" / f"dlcf-phi10-{scene}-5m"
    arms = centred.arms(scene) + [("dynamic LCF, φ ≤ 10°", lambda s: (here / f"runs/phi10-s{s}",) * 2)]
    table = {label: {s: centred.measures(scene, *dirs(s)) for s in centred.SEEDS} for label, dirs in arms}
    columns = centred.COLUMNS
    print(f"{scene}, seeds {centred.SEEDS}, 5 M agent-steps (mean ± 95 % t over the seeds with data):\n")
    print("| arm | n | " + " | ".join(c for c, _ in columns) + " |")
    print("|" + "---|" * (len(columns) + 2))
    for label, runs in table.items():
        done = [m for m in runs.values() if "success" in m]
        cells = [fmt([m[k] for m in done if m.get(k) is not None], digits(k)) for _, k in columns]
        print(f"| {label} | {len(done)} | " + " | ".join(cells) + " |")
    arm = table["dynamic LCF, φ ≤ 10°"]
    for base_label in ("IPPO", "dynamic LCF, r_N mean"):
        base = table[base_label]
        seeds = [s for s in centred.SEEDS if "success" in arm[s] and "success" in base[s]]
        print(f"\nφ ≤ 10° − {base_label}, same seed (n = {len(seeds)}; seed by seed in brackets):\n")
        print("| " + " | ".join(c for c, _ in columns) + " |")
        print("|" + "---|" * len(columns))
        cells = []
        for _, k in columns:
            diffs = [arm[s][k] - base[s][k] for s in seeds
                     if arm[s].get(k) is not None and base[s].get(k) is not None]
            each = ", ".join(f"{d:+.{digits(k)}f}" for d in diffs)
            cells.append(f"{fmt(diffs, digits(k), signed=True)} ({each})" if diffs else "–")
        print("| " + " | ".join(cells) + " |")
    print_training_pairs(scene, here)


TRAINING = [("success", "success"), ("crash", "crash"), ("timeout", "timeout")]


def print_training_pairs(scene, here):
    """φ ≤ 10° − IPPO and − φ ≤ 20° in training over every seed both have run (1-6)."""
    grid = ROOT / "results" / "grid-5m" / "runs"
    seeds456 = ROOT / "results" / "seeds456-5m"

    def baseline(method, s):
        if s <= 3:
            return grid / f"{method}-{scene}-s{s}"
        return seeds456 / f"{scene}-s{s}" / "runs" / f"{method}-{scene}-s{s}"

    seeds = range(1, 7)
    arm = {s: centred.measures(scene, here / f"runs/phi10-s{s}", here / f"runs/phi10-s{s}") for s in seeds}
    for label, method in (("IPPO", "ippo"), ("φ ≤ 20°", "dynamic-lcf")):
        base = {s: centred.measures(scene, baseline(method, s), baseline(method, s)) for s in seeds}
        # A φ ≤ 10° run counts once evaluated (a run still training has a progress file too).
        done = [s for s in seeds if arm[s].get("mean scene_success_rate") is not None
                and "success" in base[s]]
        print(f"\nTraining, φ ≤ 10° − {label}, same seed (n = {len(done)}, seeds {done}):\n")
        print("| " + " | ".join(c for c, _ in TRAINING) + " |")
        print("|" + "---|" * len(TRAINING))
        cells = []
        for _, k in TRAINING:
            diffs = [arm[s][k] - base[s][k] for s in done]
            each = ", ".join(f"{d:+.2f}" for d in diffs)
            cells.append(f"{fmt(diffs, 2, signed=True)} ({each})" if diffs else "–")
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
