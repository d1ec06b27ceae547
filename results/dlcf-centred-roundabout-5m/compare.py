"""The centred neighbourhood reward against the same seeds' IPPO and dynamic LCF (run from the
repository root):

    python3 results/dlcf-centred-roundabout-5m/compare.py roundabout
    python3 results/dlcf-centred-roundabout-5m/compare.py intersection

Training: the last window of each run (MetaDrive's success, crash, timeout, steps per agent
episode, φ). Evaluation: the final checkpoints on the validation seed 777, mean and sampled
actions: this directory's arm from its own runs, IPPO and the dynamic LCF from
results/dlcf-centred-<scene>-5m/baselines (results/seeds456-5m's checkpoints evaluated again on
the validation seed; that grid itself was evaluated on the unseen seed 1000).
"""
import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("grid_tables", ROOT / "scripts" / "grid-tables.py")
grid_tables = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(grid_tables)
fmt = grid_tables.fmt
SEEDS = [4, 5, 6]
EVAL_SEED = 777


def arms(scene):
    """(label, training run directory, evaluation run directory) per seed."""
    here = ROOT / "results" / f"dlcf-centred-{scene}-5m"
    grid = ROOT / "results" / "seeds456-5m"
    return [
        ("IPPO", lambda s: (grid / f"{scene}-s{s}/runs/ippo-{scene}-s{s}", here / f"baselines/ippo-s{s}")),
        ("dynamic LCF, r_N mean", lambda s: (grid / f"{scene}-s{s}/runs/dynamic-lcf-{scene}-s{s}",
                                             here / f"baselines/dynamic-lcf-s{s}")),
        ("dynamic LCF, r_N centred", lambda s: (here / f"runs/dlcf-centred-s{s}",) * 2),
    ]


def measures(scene, train_dir, eval_dir):
    """Every measure of one run by name; None where it is missing."""
    out = {}
    if (train_dir / "progress.jsonl").exists():
        last = grid_tables.read_progress(train_dir)[-1]
        out |= {
            "success": last["scene_window"]["success_rate"],
            "crash": last["scene_window"]["crash_rate"],
            "timeout": last["scene_window"]["timeout_rate"],
            "steps": last["window"]["mean_length"],
            "phi": (last.get("lcf") or {}).get("mean_deg"),
        }
    for actions in ("mean", "sample"):
        e = grid_tables.read_eval(eval_dir, scene, EVAL_SEED, actions)
        for key in ("scene_success_rate", "scene_crash_rate", "timeout_rate"):
            out[f"{actions} {key}"] = e["metrics"][key]["value"] if e else None
    return out


COLUMNS = [
    ("training success", "success"), ("crash", "crash"), ("timeout", "timeout"),
    ("steps per agent", "steps"), ("φ (°)", "phi"),
    ("eval mean: success", "mean scene_success_rate"), ("crash", "mean scene_crash_rate"),
    ("timeout", "mean timeout_rate"),
    ("eval sampled: success", "sample scene_success_rate"), ("crash", "sample scene_crash_rate"),
]


def print_seed_by_seed(table):
    """One line per arm of `table` ({arm: {seed: measures}}), each run's training and mean-action
    evaluation."""
    print("\nSeed by seed (training success / crash / timeout; eval mean success / crash):\n")
    for label, runs in table.items():
        line = []
        for s, m in runs.items():
            if "success" in m:
                ev = m["mean scene_success_rate"], m["mean scene_crash_rate"]
                ev_text = "–" if None in ev else f"{ev[0]:.2f}/{ev[1]:.2f}"
                line.append(f"s{s} {m['success']:.2f}/{m['crash']:.2f}/{m['timeout']:.2f}; {ev_text}")
        print(f"- {label}: " + ", ".join(line))


def main():
    scene = sys.argv[1] if len(sys.argv) > 1 else "roundabout"
    table = {label: {s: measures(scene, *dirs(s)) for s in SEEDS} for label, dirs in arms(scene)}
    print(f"{scene}, seeds {SEEDS}, 5 M agent-steps (mean ± 95 % t over the seeds with data):\n")
    print("| arm | n | " + " | ".join(c for c, _ in COLUMNS) + " |")
    print("|" + "---|" * (len(COLUMNS) + 2))
    for label, runs in table.items():
        done = [m for m in runs.values() if "success" in m]
        cells = [fmt([m[k] for m in done if m.get(k) is not None], 0 if k == "steps" else 2)
                 for _, k in COLUMNS]
        print(f"| {label} | {len(done)} | " + " | ".join(cells) + " |")
    print_seed_by_seed(table)
    arm = table["dynamic LCF, r_N centred"]
    for base_label in ("IPPO", "dynamic LCF, r_N mean"):
        base = table[base_label]
        pairs = [(arm[s], base[s]) for s in SEEDS if "success" in arm[s] and "success" in base[s]]
        print(f"\nCentred − {base_label}, same seed (n = {len(pairs)}):\n")
        print("| " + " | ".join(c for c, _ in COLUMNS) + " |")
        print("|" + "---|" * len(COLUMNS))
        cells = []
        for _, k in COLUMNS:
            diffs = [a[k] - b[k] for a, b in pairs if a.get(k) is not None and b.get(k) is not None]
            cells.append(fmt(diffs, 0 if k == "steps" else 2, signed=True))
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
