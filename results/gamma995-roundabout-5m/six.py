"""Six seeds of γ = 0.995 on the roundabout against γ = 0.999 (run from the repository root):

    python3 results/gamma995-roundabout-5m/six.py

Training: the last window of each run (MetaDrive's success, crash, timeout, steps per agent
episode, φ). Evaluation: final checkpoints on the validation seed 777, mean and sampled actions.
γ = 0.995: this directory's runs, seeds 1-6. γ = 0.999: the 5 M grid's runs for seeds 1-3
(evaluated there on the unseen seed 1000 only, their checkpoints not kept: no validation-seed
figures) and results/seeds456-5m's for seeds 4-6 (evaluated again on the validation seed in
results/dlcf-centred-roundabout-5m/baselines).
"""
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("grid_tables", ROOT / "scripts" / "grid-tables.py")
grid_tables = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(grid_tables)
_spec = importlib.util.spec_from_file_location(
    "centred", ROOT / "results" / "dlcf-centred-roundabout-5m" / "compare.py")
centred = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(centred)
fmt = grid_tables.fmt
SEEDS = [1, 2, 3, 4, 5, 6]
EVAL_SEED = 777
HERE = ROOT / "results" / "gamma995-roundabout-5m"


def at_0999(method):
    """(training run, evaluation run) of `method` at γ = 0.999 for a seed."""
    def dirs(seed):
        if seed <= 3:
            run = ROOT / f"results/grid-5m/runs/{method}-roundabout-s{seed}"
            return run, run
        return (ROOT / f"results/seeds456-5m/roundabout-s{seed}/runs/{method}-roundabout-s{seed}",
                ROOT / f"results/dlcf-centred-roundabout-5m/baselines/{method}-s{seed}")
    return dirs


ARMS = [
    ("IPPO, 0.999", at_0999("ippo")),
    ("IPPO, 0.995", lambda s: (HERE / f"runs/ippo-g995-s{s}",) * 2),
    ("dynamic LCF, 0.999", at_0999("dynamic-lcf")),
    ("dynamic LCF, 0.995", lambda s: (HERE / f"runs/dlcf-g995-s{s}",) * 2),
]
COLUMNS = [
    ("training success", "success"), ("crash", "crash"), ("timeout", "timeout"),
    ("steps per agent", "steps"), ("φ (°)", "phi"),
    ("eval mean: success", "mean scene_success_rate"), ("crash", "mean scene_crash_rate"),
    ("timeout", "mean timeout_rate"),
    ("eval sampled: success", "sample scene_success_rate"), ("crash", "sample scene_crash_rate"),
]
PAIRS = [
    ("dynamic LCF − IPPO at γ = 0.995", "dynamic LCF, 0.995", "IPPO, 0.995"),
    ("dynamic LCF − IPPO at γ = 0.999", "dynamic LCF, 0.999", "IPPO, 0.999"),
    ("IPPO, 0.995 − 0.999", "IPPO, 0.995", "IPPO, 0.999"),
    ("dynamic LCF, 0.995 − 0.999", "dynamic LCF, 0.995", "dynamic LCF, 0.999"),
]


def measures(train_dir, eval_dir):
    """Every measure of one run by name; None where it is missing (φ where the method has none)."""
    out = {}
    if (train_dir / "progress.jsonl").exists():
        last = grid_tables.read_progress(train_dir)[-1]
        out |= {
            "success": last["scene_window"]["success_rate"],
            "crash": last["scene_window"]["crash_rate"],
            "timeout": last["scene_window"]["timeout_rate"],
            "steps": last["window"]["mean_length"],
        }
        if "dlcf" in train_dir.name or "dynamic-lcf" in train_dir.name:
            out["phi"] = (last.get("lcf") or {}).get("mean_deg")
    for actions in ("mean", "sample"):
        e = grid_tables.read_eval(eval_dir, "roundabout", EVAL_SEED, actions)
        for key in ("scene_success_rate", "scene_crash_rate", "timeout_rate"):
            out[f"{actions} {key}"] = e["metrics"][key]["value"] if e else None
    return out


def digits(key):
    return 0 if key == "steps" else 2


def main():
    table = {label: {s: measures(*dirs(s)) for s in SEEDS} for label, dirs in ARMS}
    print(f"Roundabout, seeds {SEEDS}, 5 M agent-steps (mean ± 95 % t over the seeds with data; "
          f"n = training runs / validation-seed evaluations):\n")
    print("| arm | n | " + " | ".join(c for c, _ in COLUMNS) + " |")
    print("|" + "---|" * (len(COLUMNS) + 2))
    for label, runs in table.items():
        done = [m for m in runs.values() if "success" in m]
        evaluated = sum(m.get("mean scene_success_rate") is not None for m in done)
        cells = [fmt([m[k] for m in done if m.get(k) is not None], digits(k))
                 if any(m.get(k) is not None for m in done) else "–" for _, k in COLUMNS]
        print(f"| {label} | {len(done)} / {evaluated} | " + " | ".join(cells) + " |")
    centred.print_seed_by_seed(table)
    for title, arm_label, base_label in PAIRS:
        arm, base = table[arm_label], table[base_label]
        pairs = [(arm[s], base[s]) for s in SEEDS if "success" in arm[s] and "success" in base[s]]
        print(f"\n{title}, same seed (n = {len(pairs)} in training; evaluations where both have one):\n")
        print("| " + " | ".join(c for c, _ in COLUMNS) + " |")
        print("|" + "---|" * len(COLUMNS))
        cells = []
        for _, k in COLUMNS:
            diffs = [a[k] - b[k] for a, b in pairs if a.get(k) is not None and b.get(k) is not None]
            cells.append(f"{fmt(diffs, digits(k), signed=True)} (n {len(diffs)})" if diffs else "–")
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
