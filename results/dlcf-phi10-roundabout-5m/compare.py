"""φ bounded at 10° against the same seeds' IPPO, dynamic LCF at 20° and r_N centred (run from
the repository root):

    python3 results/dlcf-phi10-roundabout-5m/compare.py roundabout
    python3 results/dlcf-phi10-roundabout-5m/compare.py intersection

The φ ≤ 10° runs are results/dlcf-phi10-<scene>-5m's, the others those that
results/dlcf-centred-<scene>-5m/compare.py tables. Its measures and columns: training, the last
window; evaluation, the final checkpoints on the validation seed 777, mean and sampled actions.
Then seeds 1-6 in training and on the unseen seed 1000, the grid's evaluation (seeds 1-3's IPPO
and φ ≤ 20° runs are results/grid-5m's, 4-6 results/seeds456-5m's; their checkpoints were
evaluated on 1000 only and seeds 1-3's not kept, so 777 pairs only seeds 4-6).
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
    print_means(table, columns, lambda m: "success" in m)
    arm = table["dynamic LCF, φ ≤ 10°"]
    for base_label in ("IPPO", "dynamic LCF, r_N mean"):
        base = table[base_label]
        seeds = [s for s in centred.SEEDS if "success" in arm[s] and "success" in base[s]]
        print(f"\nφ ≤ 10° − {base_label}, same seed (n = {len(seeds)}; seed by seed in brackets):\n")
        print_paired(arm, base, seeds, columns)
    print_six_seed_pairs(scene, here)


def print_means(table, columns, done):
    """One table row per arm of `table` (label → seed → measures): over its runs that are
    `done`, the mean ± 95 % t of each column."""
    print("| arm | n | " + " | ".join(c for c, _ in columns) + " |")
    print("|" + "---|" * (len(columns) + 2))
    for label, runs in table.items():
        ms = [m for m in runs.values() if done(m)]
        cells = [fmt([m[k] for m in ms if m.get(k) is not None], digits(k)) for _, k in columns]
        print(f"| {label} | {len(ms)} | " + " | ".join(cells) + " |")


def print_paired(arm, base, seeds, columns, count=False):
    """One table row of arm − base per column over `seeds` where both have the measure, each
    seed's difference in brackets (after their number with `count`)."""
    print("| " + " | ".join(c for c, _ in columns) + " |")
    print("|" + "---|" * len(columns))
    cells = []
    for _, k in columns:
        diffs = [arm[s][k] - base[s][k] for s in seeds
                 if arm[s].get(k) is not None and base[s].get(k) is not None]
        each = ", ".join(f"{d:+.{digits(k)}f}" for d in diffs)
        n = f"n = {len(diffs)}: " if count else ""
        cells.append(f"{fmt(diffs, digits(k), signed=True)} ({n}{each})" if diffs else "–")
    print("| " + " | ".join(cells) + " |")


UNSEEN_SEED = 1000
SIX_SEEDS = [
    ("training success", "success"), ("crash", "crash"), ("timeout", "timeout"),
    ("unseen, mean action: success", "mean scene_success_rate"), ("crash", "mean scene_crash_rate"),
    ("timeout", "mean timeout_rate"),
    ("sampled: success", "sample scene_success_rate"), ("crash", "sample scene_crash_rate"),
]


def six_seed_measures(scene, run_dir):
    """Training (last window) and the evaluations on the unseen seed, as the grid reports them."""
    out = {k: v for k, v in centred.measures(scene, run_dir, run_dir).items()
           if k in ("success", "crash", "timeout")}
    for actions in ("mean", "sample"):
        e = centred.grid_tables.read_eval(run_dir, scene, UNSEEN_SEED, actions)
        for key in ("scene_success_rate", "scene_crash_rate", "timeout_rate"):
            out[f"{actions} {key}"] = e["metrics"][key]["value"] if e else None
    return out


def print_six_seed_pairs(scene, here):
    """φ ≤ 10° − IPPO and − φ ≤ 20° over seeds 1-6, in training and on the unseen seed 1000
    (the grid's evaluation: results/grid-5m has seeds 1-3, results/seeds456-5m seeds 4-6)."""
    grid = ROOT / "results" / "grid-5m" / "runs"
    seeds456 = ROOT / "results" / "seeds456-5m"

    def baseline(method, s):
        if s <= 3:
            return grid / f"{method}-{scene}-s{s}"
        return seeds456 / f"{scene}-s{s}" / "runs" / f"{method}-{scene}-s{s}"

    seeds = range(1, 7)
    arm = {s: six_seed_measures(scene, here / f"runs/phi10-s{s}") for s in seeds}
    for label, method in (("IPPO", "ippo"), ("φ ≤ 20°", "dynamic-lcf")):
        base = {s: six_seed_measures(scene, baseline(method, s)) for s in seeds}
        print(f"\nφ ≤ 10° − {label}, seeds 1-6, training and unseen seed {UNSEEN_SEED} "
              f"(n: the seeds where both have the measure):\n")
        # The arm's training counts once the run was evaluated (one still training has a
        # progress file too).
        evaluated = [s for s in seeds if arm[s].get("mean scene_success_rate") is not None]
        print_paired(arm, base, evaluated, SIX_SEEDS, count=True)


if __name__ == "__main__":
    main()
