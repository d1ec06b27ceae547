"""The 30-minute checks of the dynamic LCF at φ ≤ 10° (run from the repository root):

    python3 results/dlcf-phi10-12m/curves.py

Per seed: the training window (MetaDrive's success / crash / timeout) at marks of agent-steps,
the best window and the lowest one after it (the issue's "never below 80 % of its best"),
φ by live-neighbour count at the end, and the final checkpoint on the unseen seed 1000 (mean
action and sampled). Then the same seeds of the dynamic LCF at 20° and IPPO at the same budget
and schedule (results/dlcf-scene-phi20-linear-12m, results/lcf20-linear-12m), and φ ≤ 10° with
an entropy bonus (results/dlcf-phi10-entropy-12m) and IPPO with the same bonus
(results/ippo-entropy-12m), and φ ≤ 10° with a smaller bonus (results/dlcf-phi10-entropy002-12m),
paired.
"""
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("grid_tables", ROOT / "scripts" / "grid-tables.py")
grid_tables = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(grid_tables)
fmt = grid_tables.fmt

SCENE = "intersection"
SEEDS = [1, 2, 3]
MARKS = [2e6, 3e6, 5e6, 7e6, 8e6, 10e6, 12e6]
UNSEEN_SEED = 1000
# The ablations' own evaluation (scripts/ablation.sh), paired as well: not the unseen seed.
VALIDATION_SEED = 777
ARMS = [
    ("φ ≤ 10°", lambda s: ROOT / f"results/dlcf-phi10-12m/runs/phi10-s{s}"),
    ("φ ≤ 20°", lambda s: ROOT / f"results/dlcf-scene-phi20-linear-12m/runs/scene-phi20-linear-s{s}"),
    ("IPPO", lambda s: ROOT / f"results/lcf20-linear-12m/runs/ippo-s{s}"),
    ("φ ≤ 10°, entropy 0.005", lambda s: ROOT / f"results/dlcf-phi10-entropy-12m/runs/phi10-ent005-s{s}"),
    ("IPPO, entropy 0.005", lambda s: ROOT / f"results/ippo-entropy-12m/runs/ippo-ent005-s{s}"),
    ("φ ≤ 10°, entropy 0.002", lambda s: ROOT / f"results/dlcf-phi10-entropy002-12m/runs/phi10-ent002-s{s}"),
]
# (arm, baseline) pairs of the paired differences.
PAIRS = [("φ ≤ 10°", "IPPO"), ("φ ≤ 10°", "φ ≤ 20°"),
         ("φ ≤ 10°, entropy 0.005", "φ ≤ 10°"), ("IPPO, entropy 0.005", "IPPO"),
         ("φ ≤ 10°, entropy 0.005", "IPPO, entropy 0.005"), ("φ ≤ 10°, entropy 0.005", "IPPO"),
         ("φ ≤ 10°, entropy 0.002", "φ ≤ 10°"), ("φ ≤ 10°, entropy 0.002", "IPPO")]


def run_measures(run_dir, marks=MARKS):
    """None while a run has no progress; else its curve, best window and evaluations."""
    if not (run_dir / "progress.jsonl").exists():
        return None
    lines = [p for p in grid_tables.read_progress(run_dir) if p["scene_window"]["scene_episodes"] > 0]
    rates = [p["scene_window"]["success_rate"] for p in lines]
    best = max(range(len(lines)), key=rates.__getitem__)
    last = lines[-1]
    out = {
        "steps": last["agent_steps"],
        "best": rates[best],
        "best_at": lines[best]["agent_steps"],
        "lowest_after": min(rates[best:]),
        "marks": {},
        "phi": (last.get("lcf") or {}).get("phi_deg_by_neighbours"),
    }
    for mark in marks:
        before = [p for p in lines if p["agent_steps"] <= mark]
        if before and last["agent_steps"] >= mark:
            w = before[-1]["scene_window"]
            out["marks"][mark] = (w["success_rate"], w["crash_rate"], w["timeout_rate"])
    updates = [p["update"] for p in lines if p.get("update")]
    out["entropy"] = updates[-1]["entropy"] if updates else None
    for key, seed in (("", UNSEEN_SEED), ("validation ", VALIDATION_SEED)):
        for actions in ("mean", "sample"):
            e = grid_tables.read_eval(run_dir, SCENE, seed, actions)
            out[key + actions] = None if e is None else (
                e["metrics"]["scene_success_rate"]["value"], e["metrics"]["scene_crash_rate"]["value"])
    return out


def main(arms=ARMS, pairs=PAIRS, marks=MARKS):
    """The tables of some arms (label, seed → run directory) and paired differences, at marks."""
    table = {label: {s: run_measures(dirs(s), marks) for s in SEEDS} for label, dirs in arms}
    end = f"{marks[-1] / 1e6:g} M"
    header = " | ".join(f"{m / 1e6:g} M" for m in marks)
    print(f"| run | {header} | best window | lowest after it | φ at the end: 0 / 1-2 / 3-5 / 6+ "
          f"| unseen {UNSEEN_SEED}, mean action | sampled | entropy at the end |")
    print("|---" * (len(marks) + 7) + "|")
    for label, runs in table.items():
        for s, m in runs.items():
            if m is None:
                continue
            cells = ["/".join(f"{v:.2f}" for v in m["marks"][k]) if k in m["marks"] else "–"
                     for k in marks]
            phi = " / ".join(f"{m['phi'][k]:.0f}°" for k in ("0", "1-2", "3-5", "6+")) if m["phi"] else "–"
            evals = ["–" if m[a] is None else f"{m[a][0]:.2f} / {m[a][1]:.2f}" for a in ("mean", "sample")]
            share = f"{m['lowest_after'] / m['best']:.0%}" if m["best"] > 0 else "–"
            print(f"| {label} s{s} | " + " | ".join(cells)
                  + f" | {m['best']:.3f} at {m['best_at'] / 1e6:.1f} M"
                  + f" | {m['lowest_after']:.3f} ({share})"
                  + f" | {phi} | " + " | ".join(evals)
                  + f" | {'–' if m['entropy'] is None else format(m['entropy'], '.2f')} |")
    print(f"\nOver seeds (mean ± 95 % t), runs that reached {end}:\n")
    print(f"| arm | n | success at {end} | crash | timeout | lowest after the best / best "
          "| unseen mean action: success | crash | sampled: success | crash |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    done = {label: {s: m for s, m in runs.items() if m and m["steps"] >= marks[-1]} for label, runs in table.items()}
    for label, runs in done.items():
        ms = list(runs.values())
        col = lambda f: fmt([f(m) for m in ms if f(m) is not None])
        at_end = lambda i: col(lambda m: m["marks"][marks[-1]][i])
        print(f"| {label} | {len(ms)} | {at_end(0)} | {at_end(1)} | {at_end(2)} | {col(lambda m: m['lowest_after'] / m['best'])} "
              f"| {col(lambda m: m['mean'] and m['mean'][0])} | {col(lambda m: m['mean'] and m['mean'][1])} "
              f"| {col(lambda m: m['sample'] and m['sample'][0])} | {col(lambda m: m['sample'] and m['sample'][1])} |")
    for arm_label, base_label in pairs:
        arm, base = done[arm_label], done[base_label]
        seeds = [s for s in arm if s in base]
        if not seeds:
            continue
        print(f"\n{arm_label} − {base_label}, same seed (n = {len(seeds)}): ", end="")
        parts = []
        for name, f in ((f"success at {end}", lambda m: m["marks"][marks[-1]][0]),
                        ("crash", lambda m: m["marks"][marks[-1]][1]),
                        ("timeout", lambda m: m["marks"][marks[-1]][2]),
                        ("lowest after the best / best", lambda m: m["lowest_after"] / m["best"]),
                        ("unseen mean action", lambda m: m["mean"] and m["mean"][0]),
                        ("crash", lambda m: m["mean"] and m["mean"][1]),
                        ("sampled", lambda m: m["sample"] and m["sample"][0]),
                        ("crash", lambda m: m["sample"] and m["sample"][1]),
                        ("validation seed mean action", lambda m: m["validation mean"] and m["validation mean"][0]),
                        ("crash", lambda m: m["validation mean"] and m["validation mean"][1]),
                        ("sampled", lambda m: m["validation sample"] and m["validation sample"][0]),
                        ("crash", lambda m: m["validation sample"] and m["validation sample"][1])):
            diffs = [f(arm[s]) - f(base[s]) for s in seeds if f(arm[s]) is not None and f(base[s]) is not None]
            parts.append(f"{name} {fmt(diffs, signed=True)}")
        print("; ".join(parts))


if __name__ == "__main__":
    main()
