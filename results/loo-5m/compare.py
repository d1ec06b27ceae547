"""Each suspect reverted alone from today's defaults against the defaults beside them, same
seed (run from the repository root):

    python3 results/loo-5m/compare.py

Training at 5 M: MetaDrive's success over the last 20 scene episodes and smoothed over 100 (from
`scene_totals`, as CoPO's curves), crash and timeout of the 20-episode window, and the mean
policy lag of the last updates; evaluation: the final checkpoint on the validation seed 777,
mean and sampled actions. Then each arm − `defaults` (the control run beside them on the same
loaded machine), mean ± 95 % t with each seed's difference in brackets, and the second
control, the grid's IPPO of the same seeds (training only: its checkpoints were evaluated on the
unseen seed, not on 777). Tables are results/dlcf-phi10-roundabout-5m/compare.py's.
"""
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HERE = ROOT / "results" / "loo-5m"
SCENE = "intersection"
SEEDS = [1, 2, 3]
# The last progress lines whose updates' lag is averaged (5 s apart: the run's last ~minute).
LAG_LINES = 12


def _load(name, path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


phi10 = _load("phi10", ROOT / "results" / "dlcf-phi10-roundabout-5m" / "compare.py")
centred, grid_tables = phi10.centred, phi10.centred.grid_tables

COLUMNS = [
    ("training success", "success"), ("100 episodes", "smoothed"), ("crash", "crash"),
    ("timeout", "timeout"), ("lag", "lag"),
    ("eval mean: success", "mean scene_success_rate"), ("crash", "mean scene_crash_rate"),
    ("eval sampled: success", "sample scene_success_rate"), ("crash", "sample scene_crash_rate"),
]


def arm_names():
    with open(HERE / "arms.tsv") as f:
        return [line.split("\t")[0] for line in f if line.strip() and not line.startswith("#")]


def measures(run_dir):
    """centred's measures plus the smoothed success and the lag; {} for a run not finished."""
    out = centred.measures(SCENE, run_dir, run_dir)
    if out.get("mean scene_success_rate") is None and run_dir.parent.parent == HERE:
        return {}  # still training (or stopped): its last window is not the budget's
    if "success" in out:
        lines = grid_tables.read_progress(run_dir)
        smoothed = grid_tables.smoothed_scene_success(lines)
        out["smoothed"] = smoothed[-1][1] if smoothed else None
        lags = [l["update"]["lag_mean"] for l in lines[-LAG_LINES:] if l.get("update")]
        out["lag"] = sum(lags) / len(lags) if lags else None
    return out


def main():
    table = {name: {s: measures(HERE / "runs" / f"{name}-s{s}") for s in SEEDS} for name in arm_names()}
    table["IPPO (grid-5m)"] = {
        s: measures(ROOT / "results" / "grid-5m" / "runs" / f"ippo-{SCENE}-s{s}") for s in SEEDS}
    print(f"{SCENE}, IPPO, seeds {SEEDS}, 5 M agent-steps (mean ± 95 % t over the finished runs):\n")
    phi10.print_means(table, COLUMNS, lambda m: "success" in m)
    for control in ("defaults", "IPPO (grid-5m)"):
        for name in arm_names():
            seeds = [s for s in SEEDS if "success" in table[name][s] and "success" in table[control][s]]
            if name != control and seeds:
                print(f"\n{name} − {control}, same seed (n = {len(seeds)}; seed by seed in brackets):\n")
                phi10.print_paired(table[name], table[control], seeds, COLUMNS)

if __name__ == "__main__":
    main()
