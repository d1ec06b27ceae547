"""The 30-minute criterion ("never below 80 % of its best") under CoPO's smoothing of the
training success, 100 scene episodes, next to the 20 of `run.stats_window_scene_episodes`
(from the repository root):

    python3 results/metadrive-smoothing/analysis.py

Per run: the best window and the lowest after it with the 20-episode window of progress.jsonl,
then with 100 episodes. Runs with `scene_totals` are smoothed exactly
(scripts/grid-tables.py's smoothed_scene_success), and approximately as well, to check the
approximation; older runs only approximately: the mean of five 20-episode windows 20 scene
episodes apart, the scene episodes counted as env_steps over the window's mean scene-episode
length. Then the mean ± 95 % t of the share per arm (each run exact where it can be).
Last, issue #12's success marks, both ways: the grid's 5 M runs at today's defaults (IPPO's
and the replaced CoPO and dynamic-LCF runs) and the 15 M runs.
"""
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("grid_tables", ROOT / "scripts" / "grid-tables.py")
grid_tables = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(grid_tables)

WINDOW = 20  # run.stats_window_scene_episodes of every run below
SMOOTHING = grid_tables.SMOOTHING  # CoPO's: RLlib's metrics_smoothing_episodes
ARMS = [
    ("dynamic LCF, φ ≤ 10° (defaults), 12 M", "results/dlcf-phi10-12m/runs/phi10-s{}"),
    ("the same again, with scene_totals", "results/dlcf-12m-smoothed/runs/dlcf-s{}"),
    ("dynamic LCF, φ ≤ 10°, entropy 0.002, 12 M", "results/dlcf-phi10-entropy002-12m/runs/phi10-ent002-s{}"),
    ("dynamic LCF, φ ≤ 10°, entropy 0.005, 12 M", "results/dlcf-phi10-entropy-12m/runs/phi10-ent005-s{}"),
    ("dynamic LCF, φ ≤ 20°, 12 M", "results/dlcf-scene-phi20-linear-12m/runs/scene-phi20-linear-s{}"),
    ("IPPO, 12 M", "results/lcf20-linear-12m/runs/ippo-s{}"),
    ("IPPO, entropy 0.005, 12 M", "results/ippo-entropy-12m/runs/ippo-ent005-s{}"),
    ("IPPO (defaults), 15 M", "results/ippo-15m-unseen/runs/linear-s{}"),
    ("IPPO, entropy 0.005, 15 M", "results/ippo-entropy-15m/runs/ippo-ent005-s{}"),
]
SEEDS = [1, 2, 3]


def windowed(lines):
    """The progress lines' own full windows: (agent_steps, success)."""
    return [(p["agent_steps"], p["scene_window"]["success_rate"]) for p in lines
            if p["scene_window"]["scene_episodes"] >= WINDOW]


def approximately_smoothed(lines):
    """(agent_steps, mean of SMOOTHING / WINDOW full windows WINDOW scene episodes apart)."""
    counted, episodes, previous = [], 0.0, None
    for p in lines:
        w = p["scene_window"]
        if previous is not None and w["mean_steps"] > 0:
            episodes += (p["env_steps"] - previous["env_steps"]) / w["mean_steps"]
        previous = p
        counted.append(episodes)
    out = []
    for i, p in enumerate(lines):
        picks = []
        for k in range(SMOOTHING // WINDOW):
            target = counted[i] - k * WINDOW
            at = [j for j in range(i + 1) if counted[j] <= target + 1e-9]
            if not at or lines[at[-1]]["scene_window"]["scene_episodes"] < WINDOW:
                break
            picks.append(lines[at[-1]]["scene_window"]["success_rate"])
        if len(picks) == SMOOTHING // WINDOW:
            out.append((p["agent_steps"], sum(picks) / len(picks)))
    return out


def held(curve):
    """(best, where, lowest after it, lowest / best)."""
    rates = [r for _, r in curve]
    best = max(range(len(rates)), key=rates.__getitem__)
    lowest = min(rates[best:])
    return rates[best], curve[best][0], lowest, lowest / rates[best]


def main():
    print(f"| run | {WINDOW} episodes: best / lowest after (share) | {SMOOTHING} episodes: best at / "
          "lowest after (share) | the same, approximated |")
    print("|---|---|---|---|")
    shares = {}
    for label, pattern in ARMS:
        for seed in SEEDS:
            run = ROOT / pattern.format(seed)
            if not (run / "progress.jsonl").exists():
                continue
            lines = [p for p in grid_tables.read_progress(run) if p["scene_window"]["scene_episodes"] > 0]
            exact, approximate = grid_tables.smoothed_scene_success(lines, SMOOTHING), approximately_smoothed(lines)
            if not approximate:
                continue
            short, rough = held(windowed(lines)), held(approximate)
            long = held(exact) if exact else None
            shares.setdefault(label, []).append((short[3], (long or rough)[3]))
            cell = lambda h: f"{h[0]:.3f} at {h[1] / 1e6:.1f} M / {h[2]:.3f} ({h[3]:.0%})"
            print(f"| {label} s{seed} | {short[0]:.3f} / {short[2]:.3f} ({short[3]:.0%}) "
                  f"| {cell(long) if long else '–'} | {cell(rough)} |")
    print(f"\n| arm | n | lowest after the best / best, {WINDOW} episodes | {SMOOTHING} episodes |")
    print("|---|---|---|---|")
    for label, pairs in shares.items():
        print(f"| {label} | {len(pairs)} | {grid_tables.fmt([a for a, _ in pairs])} "
              f"| {grid_tables.fmt([b for _, b in pairs])} |")


# (label, run pattern, marks): the runs behind issue #12's success marks.
MARK_RUNS = [
    ("IPPO, intersection (grid-5m)", "results/grid-5m/runs/ippo-intersection-s{}", [2.5e6, 5e6]),
    ("CoPO, intersection (copo-metalr-5m)", "results/copo-metalr-5m/runs/metalr-s{}", [5e6]),
    ("dynamic LCF, intersection (dlcf-phi10-intersection-5m)",
     "results/dlcf-phi10-intersection-5m/runs/phi10-s{}", [5e6]),
    ("IPPO, roundabout (grid-5m)", "results/grid-5m/runs/ippo-roundabout-s{}", [5e6]),
    ("CoPO, roundabout (copo-default-roundabout-5m)",
     "results/copo-default-roundabout-5m/runs/copo-roundabout-s{}", [5e6]),
    ("dynamic LCF, roundabout (dlcf-phi10-roundabout-5m)",
     "results/dlcf-phi10-roundabout-5m/runs/phi10-s{}", [5e6]),
    ("IPPO, intersection, 15 M (ippo-15m-unseen)", "results/ippo-15m-unseen/runs/linear-s{}", [5e6, 7.5e6, 15e6]),
    ("IPPO, roundabout, 15 M (roundabout-15m)", "results/roundabout-15m/runs/linear-s{}", [5e6, 15e6])]


def at(curve, mark):
    before = [r for steps, r in curve if steps <= mark]
    return before[-1] if before else None


def print_marks():
    print(f"\nTraining success at the marks, mean ± 95 % t over seeds {SEEDS}: "
          f"{WINDOW} episodes → {SMOOTHING} episodes (approximated where the runs have no "
          "scene_totals)\n")
    print("| runs | mark | " + " | ".join(f"s{s}" for s in SEEDS) + " | mean |")
    print("|---|---|" + "---|" * (len(SEEDS) + 1))
    for label, pattern, marks in MARK_RUNS:
        curves = []
        for seed in SEEDS:
            lines = [p for p in grid_tables.read_progress(ROOT / pattern.format(seed))
                     if p["scene_window"]["scene_episodes"] > 0]
            smooth = grid_tables.smoothed_scene_success(lines, SMOOTHING) or approximately_smoothed(lines)
            curves.append((windowed(lines), smooth))
        for mark in marks:
            pairs = [(at(short, mark), at(long, mark)) for short, long in curves]
            cells = [" | ".join("–" if v is None else f"{v:.2f}" for v in pair) for pair in pairs]
            means = [grid_tables.fmt([p[i] for p in pairs if p[i] is not None]) for i in (0, 1)]
            print(f"| {label} | {mark / 1e6:g} M | " + " | ".join(c.replace(" | ", " → ") for c in cells)
                  + f" | {means[0]} → {means[1]} |")


if __name__ == "__main__":
    main()
    print_marks()
