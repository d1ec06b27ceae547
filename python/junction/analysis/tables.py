"""Markdown tables over seeds from `RunRecord`s: Table 1 per scene, every run's figures, each
arm minus a baseline of the same seed, the training curve at agent-step and environment-step
marks (the 20-scene-episode window and CoPO's 100-episode smoothing) beside CoPO's reference,
*Held*, time to success, the learned LCF angle, how evaluation episodes ended, every
evaluation with its own intervals, and the cross-simulator 2 × 2 over training seeds. Standard
library only."""

from __future__ import annotations

from collections import OrderedDict
from typing import Callable, Iterable, Sequence

from . import reference
from .record import MIN_WINDOW_EPISODES, WINDOW_KEYS, RunRecord
from .stats import fmt, format_number, mean_ci

METHOD_ORDER = ["cl", "ippo", "ccppo-mf", "ccppo-concat", "copo", "dynamic-lcf"]
METHOD_LABEL = {"cl": "CL", "ippo": "IPPO", "ccppo-mf": "CCPPO-MF",
                "ccppo-concat": "CCPPO-Concat", "copo": "CoPO", "dynamic-lcf": "dynamic LCF"}
SCENE_AGENTS = {"intersection": 30, "roundabout": 40}
#: The metrics of an evaluation (core/src/evaluation.rs): key, label, unit, higher is better.
METRICS = [
    ("collision_rate", "Collision rate", "1/s", False),
    ("scene_success_rate", "Success rate (MetaDrive)", "", True),
    ("scene_crash_rate", "Crash rate (MetaDrive)", "", False),
    ("scene_out_of_road_rate", "Out-of-road rate (MetaDrive)", "", False),
    ("success_rate", "Success rate", "", True),
    ("crash_rate", "Crash rate", "", False),
    ("out_of_road_rate", "Out-of-road rate", "", False),
    ("timeout_rate", "Timeout rate", "", False),
    ("accel_mean", "Mean acceleration", "m/s²", False),
    ("accel_max", "Mean acceleration (max)", "m/s²", False),
    ("reward_mean", "Env. reward (mean)", "", True),
    ("reward_max", "Env. reward (max)", "", True),
    ("length_mean", "Episode length (mean)", "steps", False),
    ("length_max", "Episode length (max)", "steps", False),
    ("successes_per_300", "Agents succeeding / 300 steps", "", True),
    ("failures_per_300", "Agents failing / 300 steps", "", False),
]
def steps_label(x: float) -> str:
    """"0", "500", "20k", "1.5M": agent-step counts at a glance."""
    a = abs(x)
    scaled, suffix = (x / 1e6, "M") if a >= 1e6 else (x / 1e3, "k") if a >= 1e3 else (x, "")
    text = f"{scaled:.1f}"
    return (text[:-2] if text.endswith(".0") else text) + suffix


def mark_label(x: float) -> str:
    """"5 M", "2.5 M", "150k"."""
    if x >= 1e6:
        return f"{x / 1e6:g} M"
    return f"{x / 1e3:g}k"


def label(group: str, by: str = "method") -> str:
    return METHOD_LABEL.get(group, group) if by == "method" else group


def group_of(record: RunRecord, by: str) -> str:
    return record.arm if by == "arm" else record.method


def ordered(preferred: Iterable[str], found: Iterable[str]) -> list[str]:
    """`preferred` names that occur, in that order, then the others as first found."""
    found = list(OrderedDict.fromkeys(found))
    order = [p for p in preferred if p in found]
    return order + [f for f in found if f not in order]


def groups(records: Sequence[RunRecord], by: str = "method", order: Iterable[str] = ()
           ) -> "OrderedDict[tuple[str, str], list[RunRecord]]":
    """(scene, group) -> its runs sorted by seed; scenes as SCENE_AGENTS orders them, groups
    in `order` (METHOD_ORDER for methods) then as found."""
    training = [r for r in records if r.is_training]
    scenes = ordered(SCENE_AGENTS, (r.scene for r in training))
    names = ordered(list(order) or (METHOD_ORDER if by == "method" else []),
                    (group_of(r, by) for r in training))
    out = OrderedDict()
    for scene in scenes:
        for name in names:
            members = sorted((r for r in training if r.scene == scene and group_of(r, by) == name),
                             key=lambda r: (r.seed is None, r.seed))
            if members:
                out[(scene, name)] = members
    return out


def markdown_table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def budget_label(records: Sequence[RunRecord]) -> str:
    """The budget as RESULTS names it (5 M): runs stop just past it."""
    return f"{min(r.agent_steps for r in records) / 1e6:.1f}".rstrip("0").rstrip(".") + " M"


# ---------------------------------------------------------------- measures of one run

def measure(r: RunRecord, key: str, eval_seed: int | None = None) -> float | None:
    """One named measure of a run, as the tables name their columns:

    - `success`, `crash`, `out_of_road`, `timeout`: MetaDrive's rates in the last 20-scene-
      episode training window; `smoothed`: the success smoothed over 100 scene episodes at
      the end; `best`: the best window; `held`, `held_smoothed`: *Held*; `phi`: the LCF angle
      of the last update; `lag`: the mean policy lag of the last updates; `steps`: the last
      training window's mean agent episode length; `env_k`: thousands of environment steps.
    - `<actions> <metric>`: an evaluation metric (`mean scene_success_rate`, `sample
      scene_crash_rate`, `mean scene_timeout_rate`, …) on `eval_seed` (any seed if None).
    - `<column>@<agent-steps>`: a curve column at a mark (`success@5000000`,
      `smoothed_success@2500000`, `best_success@7500000`, `entropy@10000000`).
    """
    if "@" in key:
        column, mark = key.split("@")
        return r.at(int(float(mark)), column)
    if " " in key:
        actions, metric = key.split(" ", 1)
        return r.eval_metric(metric, eval_seed, actions)
    if key in ("success", "crash", "out_of_road", "timeout"):
        return r.last(key)
    return {
        "smoothed": lambda: r.last_smoothed("success"),
        "best": lambda: r.best,
        "held": lambda: r.held(False),
        "held_smoothed": lambda: r.held(True),
        "phi": lambda: r.phi,
        "lag": lambda: (r.data.get("lag") or {}).get("final"),
        "steps": lambda: r.last_window("mean_length"),
        "env_k": lambda: r.env_steps / 1000 if r.env_steps is not None else None,
        "wall_s": lambda: r.wall_s,
    }[key]()


#: Columns of the summary table: (header, measure key, digits).
SUMMARY_COLUMNS = [
    ("training success (20 episodes)", "success", 2),
    ("smoothed (100)", "smoothed", 2),
    ("training crash", "crash", 2),
    ("timeout", "timeout", 2),
    ("eval success (mean action)", "mean scene_success_rate", 2),
    ("crash", "mean scene_crash_rate", 2),
    ("out of road", "mean scene_out_of_road_rate", 2),
    ("eval success (sampled)", "sample scene_success_rate", 2),
    ("crash", "sample scene_crash_rate", 2),
]
PAIRED_COLUMNS = [c for c in SUMMARY_COLUMNS if c[1] != "mean scene_out_of_road_rate"]


def _digits(key: str) -> int:
    return 0 if key in ("steps", "env_k", "wall_s") or key.endswith("length_mean") else 2


def parse_columns(spec: str | None, default):
    """`header=key[:digits],...` or `key,...` into (header, key, digits) columns."""
    if not spec:
        return default
    out = []
    for item in spec.split(","):
        header, _, key = item.rpartition("=")
        key, _, digits = key.partition(":")
        out.append((header or key, key, int(digits) if digits else _digits(key)))
    return out


def summary_table(records, by="method", order=(), columns=SUMMARY_COLUMNS, eval_seed=None,
                  smoothing_note=True) -> str:
    """Per scene and group: the number of seeds, then each column's mean ± 95 % t over the
    seeds that have it. A smoothed value approximated from the 20-episode windows (runs
    written before `scene_totals`) is marked ≈."""
    rows = []
    approximate = False
    for (scene, name), members in groups(records, by, order).items():
        cells = []
        for _, key, digits in columns:
            values = [measure(r, key, eval_seed) for r in members]
            cell = fmt(values, digits)
            present = sum(v is not None for v in values)
            if 0 < present < len(values):
                cell += f" ({present} of {len(values)})"
            if key.startswith("smoothed") and any(r.data.get("smoothing") == "approximate"
                                                  for r in members) and cell != "–":
                cell, approximate = "≈ " + cell, True
            cells.append(cell)
        seeds = ", ".join(str(r.seed) for r in members)
        rows.append([scene, label(name, by), seeds, *cells])
    text = markdown_table(["scene", "method" if by == "method" else "arm", "seeds",
                           *(c[0] for c in columns)], rows)
    if approximate and smoothing_note:
        text += ("\n≈: these runs predate `scene_totals`; CoPO's 100-episode smoothing is "
                 "approximated from five 20-episode windows (within a point of the exact value "
                 "where both exist).\n")
    return text


def paired_table(records, baseline: str, by="method", order=(), columns=PAIRED_COLUMNS,
                 eval_seed=None, each=False) -> str:
    """Each group minus `baseline` of the same scene and seed: mean ± 95 % t over the seeds
    both have (n), each seed's difference in brackets with `each`."""
    table = groups(records, by, order)
    rows = []
    for (scene, name), members in table.items():
        base = {r.seed: r for r in table.get((scene, baseline), [])}
        if name == baseline or not base:
            continue
        arm = {r.seed: r for r in members}
        seeds = [s for s in arm if s in base]
        if not seeds:
            continue
        cells = []
        for _, key, digits in columns:
            diffs = []
            for s in seeds:
                a, b = measure(arm[s], key, eval_seed), measure(base[s], key, eval_seed)
                if a is not None and b is not None:
                    diffs.append(a - b)
            cell = fmt(diffs, digits, signed=True)
            if each and diffs:
                cell += " (" + ", ".join(f"{d:+.{digits}f}" for d in diffs) + ")"
            cells.append(cell)
        rows.append([scene, f"{label(name, by)} − {label(baseline, by)}", len(seeds), *cells])
    return markdown_table(["scene", "difference, same seed", "n", *(c[0] for c in columns)],
                          rows)


def marks_table(records, marks, by="method", order=(), reference_rows=True,
                smoothed=True, held=True) -> str:
    """MetaDrive's training success at agent-step marks, mean ± 95 % t over the seeds that
    reached the mark: per group the 20-episode window's row and the 100-episode smoothed
    row, *Held* last (the lowest value after the best / the best, over the whole run), and
    CoPO's IPPO on MetaDrive's intersection at ≈ 25 agent-steps per environment step."""
    rows, approximate = [], False
    header = ["scene", "method" if by == "method" else "arm",
              *(mark_label(m) for m in marks)] + (["Held"] if held else [])
    scenes_seen = []
    for (scene, name), members in groups(records, by, order).items():
        if scene not in scenes_seen:
            if reference_rows and scenes_seen:
                rows.extend(_reference_row(scenes_seen[-1], marks, held))
            scenes_seen.append(scene)
        variants = [("success", False, "")]
        if smoothed and all(r.data.get("smoothing") for r in members):
            variants.append(("smoothed_success", True, ", 100 episodes"))
            if any(r.data.get("smoothing") == "approximate" for r in members):
                variants[-1] = ("smoothed_success", True, ", 100 episodes ≈")
                approximate = True
        for column, is_smoothed, suffix in variants:
            cells = []
            for m in marks:
                values = [r.at(m, column) for r in members]
                cells.append("–" if None in values else fmt(values))
            if held:
                cells.append(fmt([r.held(is_smoothed) for r in members]))
            rows.append([scene, label(name, by) + suffix, *cells])
    if reference_rows and scenes_seen:
        rows.extend(_reference_row(scenes_seen[-1], marks, held))
    text = markdown_table(header, rows)
    if approximate:
        text += ("\n≈: runs written before `scene_totals`; CoPO's smoothing approximated from "
                 "five 20-episode windows.\n")
    return text


def _reference_row(scene, marks, held):
    points = reference.curve_by_agent_steps(scene)
    if not points:
        return []
    cells = [f"*{points[m]:.2f}*" if m in points else "–" for m in marks]
    return [[scene, "*CoPO's IPPO on MetaDrive (×25)*", *cells] + (["–"] if held else [])]


ENV_MARKS = [50_000, 100_000, 150_000, 200_000]


def env_marks_table(records, marks=ENV_MARKS, by="method", order=(), skip=("cl",)) -> str:
    """Training success at environment-step marks, the unit of CoPO's curves (CL left out:
    its stages change the agents per step), window and smoothed rows, with CoPO's curves."""
    rows, approximate = [], False
    table = groups(records, by, order)
    scenes = list(OrderedDict.fromkeys(s for s, _ in table))
    for scene in scenes:
        for (s, name), members in table.items():
            if s != scene or name in skip:
                continue
            variants = [("success", "")]
            if all(r.data.get("smoothing") for r in members):
                approx = any(r.data.get("smoothing") == "approximate" for r in members)
                approximate |= approx
                variants.append(("smoothed_success", ", 100 episodes" + (" ≈" if approx else "")))
            for column, suffix in variants:
                cells = []
                for m in marks:
                    values = [r.at_env(m, column) for r in members]
                    cells.append("–" if None in values else fmt(values))
                rows.append([scene, label(name, by) + suffix, *cells])
        for method in ("ippo", "copo"):
            points = reference.curve(scene, method)
            if points and any(m in points for m in marks):
                cells = [f"*{points[m]:.2f}*" if m in points else "–" for m in marks]
                name = "CoPO" if method == "copo" else "CoPO's IPPO"
                rows.append([scene, f"*{name} on MetaDrive*", *cells])
    text = markdown_table(["scene", "method" if by == "method" else "arm",
                           *(f"{m // 1000}k env steps" for m in marks)], rows)
    if approximate:
        text += ("\n≈: runs written before `scene_totals`; CoPO's smoothing approximated from "
                 "five 20-episode windows.\n")
    return text


def run_marks_table(records, marks, columns=("success", "smoothed_success"), by="method",
                    order=()) -> str:
    """Each run's curve at the marks (a dash past its end), one row per run and column: the
    curves one seed at a time, where the marks table averages seeds that all reached a mark."""
    rows = []
    for (scene, name), members in groups(records, by, order).items():
        for r in members:
            for column in columns:
                values = [r.at(m, column) for m in marks]
                if all(v is None for v in values):
                    continue
                where = r.experiment.rstrip("/").split("/")[-1] + "/" + r.name
                smoothed = column.startswith("smoothed") and r.data.get("smoothing")
                rows.append([scene, f"{label(name, by)}, seed {r.seed} ({where})",
                             column.replace("_", " ") + (" ≈" if smoothed == "approximate"
                                                          else ""),
                             *("–" if v is None else f"{v:.2f}" for v in values)])
    return markdown_table(["scene", "run", "curve", *(mark_label(m) for m in marks)], rows)


def runs_table(records, eval_seed=None, by="method") -> str:
    """Every training run: MetaDrive's success / crash / timeout in the last window, smoothed
    success, best window, Held, and its evaluations' success / crash / timeout."""
    rows = []
    for (_, _), members in groups(records, by).items():
        for r in members:
            training = "–" if r.last() is None else (
                f"{r.last('success'):.2f} / {r.last('crash'):.2f} / {r.last('timeout'):.2f}")
            if r.phi:
                training += f" ({'μ' if r.method == 'copo' else 'φ'} {r.phi:.0f}°)"
            smoothed = r.last_smoothed("success")
            cells = [r.experiment.rstrip("/").split("/")[-1] + "/" + r.name, steps_label(r.agent_steps),
                     training, "–" if smoothed is None else f"{smoothed:.2f}",
                     "–" if r.best is None else f"{r.best:.2f}",
                     "–" if r.held() is None else f"{r.held():.0%}"]
            for actions in ("mean", "sample"):
                e = r.evaluation(eval_seed, actions)
                if e is None:
                    cells.append("–")
                    continue
                s = r.eval_metric("scene_success_rate", e["seed"], actions)
                c = r.eval_metric("scene_crash_rate", e["seed"], actions)
                t = r.eval_metric("scene_timeout_rate", e["seed"], actions)
                cells.append("–" if None in (s, c, t) else
                             f"{s:.3f} / {c:.3f} / {t:.3f} (seed {e['seed']})")
            rows.append(cells)
    return markdown_table(["run", "agent-steps", "training: success / crash / timeout",
                           "smoothed (100)", "best window", "Held",
                           "eval, mean action: success / crash / timeout",
                           "eval, sampled"], rows)


def evals_table(records) -> str:
    """Every evaluation, each with its own intervals: success, crash and out of road over
    agent episodes (Wilson) and MetaDrive's success per scene episode (Student's t over
    scene episodes). Agents of one scene episode are not independent (crashes come in
    pairs), so the Wilson intervals are too narrow; the scene-episode interval is the
    honest one."""
    rows = []

    def wilson_cell(e, key):
        m = e["metrics"].get(key)
        return "–" if m is None else f"{m[0]:.3f} [{m[1]:.3f}, {m[2]:.3f}]"

    for r in records:
        # An evaluation made elsewhere and attached to its run is listed where it was made.
        for e in (e for e in r.evals if "evaluated_in" not in e):
            scene = e["metrics"].get("scene_success_rate")
            rows.append([r.experiment.rstrip("/").split("/")[-1] + "/" + r.name,
                         e["scenario"], e["seed"], e["actions"], e["episodes"],
                         e.get("scene_episodes") or "–",
                         wilson_cell(e, "success_rate"), wilson_cell(e, "crash_rate"),
                         wilson_cell(e, "out_of_road_rate"),
                         "–" if scene is None else
                         f"{scene[0]:.3f} ± {(scene[2] - scene[0]) if scene[2] is not None else 0:.3f}"])
    return markdown_table(["run / checkpoint", "evaluated on", "seed", "actions",
                           "agent episodes", "scene episodes", "success [Wilson 95 %]",
                           "crash", "out of road", "MetaDrive's success ± t over scene episodes"],
                          rows)


CROSS_SIM_RATES = ("success", "crash", "out_of_road")


def cross_sim_cells(records, eval_seed=None, actions="mean") -> "OrderedDict":
    """(scene trained on, scenario evaluated on) -> [(run, its evaluation there)] in seed
    order: every training run's evaluation (on `eval_seed`, any seed if None) in each scenario
    it was evaluated on, its own included."""
    cells: OrderedDict = OrderedDict()
    for r in sorted((r for r in records if r.is_training), key=lambda r: (r.scene, r.seed or 0)):
        for scenario in dict.fromkeys(e["scenario"] for e in r.evals):
            e = r.evaluation(eval_seed, actions, scenario)
            if e is not None:
                cells.setdefault((r.scene, scenario), []).append((r, e))
    return cells


def has_cross_sim(records) -> bool:
    """Whether some training run was evaluated on a scenario other than its own."""
    return any(trained != evaluated for trained, evaluated in cross_sim_cells(records))


def cross_sim_table(records, eval_seed=None, actions="mean") -> str:
    """The cross-simulator 2 × 2 (trained on one scene × evaluated on each): MetaDrive's
    success, crash and out-of-road rates per scene episode, as mean ± 95 % t over the training
    seeds (one policy per seed: the level training varies at), then each seed's success with
    its t interval over that evaluation's scene episodes. Neither interval counts agent
    episodes, which share their scene episode (crashes come in pairs)."""
    rows = []
    for (trained, evaluated), members in cross_sim_cells(records, eval_seed, actions).items():
        def rates(key):
            return [(e["metrics"].get(f"scene_{key}_rate") or [None])[0] for _, e in members]

        def each(r, e):
            m = e["metrics"].get("scene_success_rate")
            if m is None:
                return f"{r.seed}: –"
            low, high = m[1], m[2]
            interval = "" if low is None or high is None else f" [{low:.2f}, {high:.2f}]"
            return f"{r.seed}: {m[0]:.2f}{interval}"

        rows.append([trained, evaluated, len(members),
                     sum(e.get("scene_episodes") or 0 for _, e in members),
                     *(fmt(rates(k), 2) for k in CROSS_SIM_RATES),
                     "; ".join(each(r, e) for r, e in members)])
    return markdown_table(["trained on", "evaluated on", "seeds", "scene episodes",
                           "success ± t over seeds", "crash", "out of road",
                           "seed: success [t over its scene episodes]"], rows)


def reach_table(records, thresholds=(0.5, 0.6, 0.7), by="method", order=(),
                min_episodes=MIN_WINDOW_EPISODES) -> str:
    """Time to a training success: per group and threshold, the seeds whose curve reached it
    and the mean agent-steps and wall seconds (the run's clock, continued over resumes) they
    took; MetaDrive's 20-scene-episode window (runs written before it: the agent-episode
    window once it holds `min_episodes` episodes) and the 100-episode smoothing."""
    rows = []
    for (scene, name), members in groups(records, by, order).items():
        for smoothed in (False, True):
            if smoothed and not all(r.data.get("smoothing") == "exact" for r in members):
                continue
            cells = []
            for t in thresholds:
                hits = reached(members, t, smoothed, min_episodes)
                if not hits:
                    cells.append(f"0/{len(members)}")
                    continue
                steps = sum(h["agent_steps"] for h in hits) / len(hits)
                wall = sum(h["wall_s"] for h in hits) / len(hits)
                cells.append(f"{len(hits)}/{len(members)}: {steps_label(steps)}, {wall:.0f} s")
            rows.append([scene, label(name, by) + (", 100 episodes" if smoothed else ""),
                         *cells])
    return markdown_table(["scene", "method" if by == "method" else "arm",
                           *(f"≥ {t:g}: seeds, agent-steps, wall time" for t in thresholds)],
                          rows)


def reached(members, threshold, smoothed=False, min_episodes=MIN_WINDOW_EPISODES) -> list:
    """The first reaches ({agent_steps, env_steps, wall_s}) of the runs that reached a
    training success of `threshold` (see `RunRecord.reach`)."""
    hits = [r.reach(threshold, smoothed, min_episodes) for r in members]
    return [h for h in hits if h]


def lcf_table(records, by="method", order=()) -> str:
    """The LCF angle of each seed's final update by live-neighbour count, mean ± 95 % over
    seeds, for the groups whose angle is not 0 throughout."""
    rows, buckets = [], []
    for (scene, name), members in groups(records, by, order).items():
        finals = [r.final.get("lcf") for r in members if r.final.get("lcf")]
        if not any(l.get("mean_deg") or l.get("std_deg") or any((l.get("by_neighbours") or {})
                                                                 .values()) for l in finals):
            continue
        for l in finals:
            # Every bucket some seed saw, in the order first seen.
            buckets += [b for b in l.get("by_neighbours") or {} if b not in buckets]
        rows.append((scene, name, finals))
    if not rows:
        return ""
    out = []
    for scene, name, finals in rows:
        cells = [fmt([l.get("mean_deg") for l in finals], 1)]
        cells += [fmt([(l.get("by_neighbours") or {}).get(b) for l in finals], 1) for b in buckets]
        out.append([scene, label(name, by), *cells])
    return markdown_table(["scene", "method" if by == "method" else "arm", "all agents",
                           *(f"{b} neighbours" for b in buckets)], out)


def _ending_shares(r, eval_seed, pool):
    """A run's share of evaluated agent episodes per ending (mean action): of its evaluation
    on `eval_seed` (any seed: the first), or with `pool` of all its evaluations on its scene
    together; None when they count no endings."""
    if pool and eval_seed is None:
        evals = [e for e in r.evals if e["actions"] == "mean" and e["scenario"] == r.scene]
    else:
        evals = [e for e in [r.evaluation(eval_seed, "mean")] if e]
    counts: dict[str, float] = {}
    for e in evals:
        for k, v in (e.get("endings") or {}).items():
            counts[k] = counts.get(k, 0) + v
    total = sum(counts.values())
    return {k: v / total for k, v in counts.items()} if total else None


def estimate_cell(values) -> str:
    """A cell of the report's tables: `mean ± half-width` in about four significant digits,
    the value with "(1 seed)" alone, a dash for none."""
    mean, half = mean_ci(values)
    if mean is None:
        return "—"
    return (f"{format_number(mean)} ± {format_number(half)}" if half is not None
            else f"{format_number(mean)} (1 seed)")


def endings_table(records, eval_seed=None, by="method", order=(), report=False) -> str:
    """Share of the evaluated agent episodes (mean action) per ending (outcome / route stage
    / what a crash hit), mean ± 95 % over the seeds whose evaluations count endings, most
    frequent first, per scene that has them. `report`: as the report prints it (a heading per
    scene, Table 1's cells, every evaluation of a run pooled when no seed is picked)."""
    out = []
    for scene in ordered(SCENE_AGENTS, (r.scene for r in records if r.is_training)):
        table = [(name, members) for (s, name), members in groups(records, by, order).items()
                 if s == scene]
        per_group = []
        endings = {}
        for name, members in table:
            shares = [x for x in (_ending_shares(r, eval_seed, report) for r in members) if x]
            for s in shares:
                for k, v in s.items():
                    endings[k] = max(endings.get(k, 0), v)
            per_group.append((name, shares))
        if not endings:
            continue
        keys = sorted(endings, key=lambda k: (-endings[k], k))
        if report:
            rows = [[f"`{k}`", *(estimate_cell([s.get(k, 0.0) for s in shares])
                                 for _, shares in per_group)] for k in keys]
            out.append(f"### {scene}\n\n" + markdown_table(
                ["Ending", *(label(n, by) for n, _ in per_group)], rows))
            continue
        rows = [[f"`{k}`", *(fmt([s.get(k, 0.0) for s in shares], 3) if shares else "–"
                             for _, shares in per_group)] for k in keys]
        out.append(f"{scene}:\n\n" + markdown_table(
            ["ending", *(label(n, by) for n, _ in per_group)], rows))
    return "\n".join(out)


def table1_values(records, scene, by="method", order=(), eval_seeds=None) -> list[dict]:
    """Table 1's numbers for one scene, a dict per group: `group`, `seeds`, `source` ("eval"
    when every seed of the group has a mean-action evaluation of its scene, on one of
    `eval_seeds` if given, else "training"), `eval_seeds` behind an eval source, and
    `metrics` {key: (mean, half-width)} over seeds (a run evaluated on several seeds counts
    their mean; from training, the last window's value; (None, None) where no seed has it)."""
    out = []
    for (s, name), members in groups(records, by, order).items():
        if s != scene:
            continue

        def evals(r):
            return [e for e in r.evals if e["actions"] == "mean" and e["scenario"] == r.scene
                    and (not eval_seeds or e["seed"] in eval_seeds)]
        from_eval = all(evals(r) for r in members)
        metrics = {}
        for key, *_ in METRICS:
            per_run = []
            for r in members:
                if from_eval:
                    got = [e["metrics"][key][0] for e in evals(r) if key in e["metrics"]]
                    per_run.append(sum(got) / len(got) if got else None)
                elif key.startswith("scene_"):
                    per_run.append(r.last(key[len("scene_"):-len("_rate")]))
                else:
                    per_run.append(r.last_window(WINDOW_KEYS[key]) if key in WINDOW_KEYS
                                   else None)
            metrics[key] = mean_ci(per_run)
        out.append({
            "group": name, "members": members, "seeds": [r.seed for r in members],
            "source": "eval" if from_eval else "training",
            "eval_seeds": sorted({e["seed"] for r in members for e in evals(r)})
            if from_eval else [],
            "metrics": metrics,
        })
    return out


def table1(records, scene, by="method", order=(), eval_seeds=None) -> str:
    """The report's Table 1: groups as columns, every metric as a row, mean ± 95 %
    half-width over seeds; from the mean-action evaluations when every seed of a column has
    one (several evaluation seeds: their mean), else the last training window. The best mean
    of a row is bold (every one tied for it), none where all columns tie."""
    table = table1_values(records, scene, by, order, eval_seeds)
    rows = []
    for key, text, unit, higher in METRICS:
        present = [g["metrics"][key][0] for g in table if g["metrics"][key][0] is not None]
        best = (max if higher else min)(present) if present else None
        bold = len(present) > 1 and any(v != best for v in present)
        cells = []
        for g in table:
            mean, half = g["metrics"][key]
            cell = "—" if mean is None else (
                f"{format_number(mean)} ± {format_number(half)}" if half is not None
                else f"{format_number(mean)} (1 seed)")
            cells.append(f"**{cell}**" if bold and mean is not None and mean == best else cell)
        rows.append([f"{text}{f' ({unit})' if unit else ''} {'↑' if higher else '↓'}", *cells])
    rows.append(["Seeds", *(", ".join(str(s) for s in g["seeds"]) for g in table)])
    rows.append(["Source", *(
        f"eval (seed{'s' if len(g['eval_seeds']) > 1 else ''} "
        f"{', '.join(map(str, g['eval_seeds']))})" if g["source"] == "eval" else "training"
        for g in table)])
    rows.append(["Agent-steps trained (mean)",
                 *(steps_label(sum(r.agent_steps for r in g["members"]) / len(g["members"]))
                   for g in table)])
    rows.append(["Wall time per run (s, mean)",
                 *(f"{sum(r.wall_s for r in g['members']) / len(g['members']):.0f}"
                   for g in table)])
    return markdown_table(["Metric", *(label(g["group"], by) for g in table)], rows)


# ---------------------------------------------------------------- the grid's tables

def grid_tables(records, eval_seed: int = 1000) -> str:
    """RESULTS.md's grid tables (what scripts/grid-tables.py prints): every run, Table 1 per
    scene, each method against IPPO of the same seed, and the curves at CoPO's environment-
    step marks."""
    out = []
    scenes = [s for s in SCENE_AGENTS if any(r.scene == s for r in records)]
    out.append(_grid_runs(records, eval_seed))
    for scene in scenes:
        out.append(_grid_table1(records, scene, eval_seed))
    out.append(_grid_paired(records, scenes, eval_seed))
    out.append(_grid_curves(records, scenes))
    return "".join(out)


def _ev(r, actions, key, eval_seed):
    return r.eval_metric(key, eval_seed, actions)


def _sw(r, outcome):
    """The last progress line's scene-window rate as written (0 while its window is empty),
    as the grid's tables always read it."""
    return (r.final.get("scene_window") or {}).get(f"{outcome}_rate")


def _f2(value):
    return "–" if value is None else f"{value:.2f}"


def _grid_runs(records, eval_seed):
    at = budget_label(records)
    lines = ["### Runs (MetaDrive's success / crash / timeout)\n",
             f"| run | training at {at} | unseen seed {eval_seed}, mean action "
             f"| unseen seed {eval_seed}, sampled |", "|---|---|---|---|"]
    order = {m: i for i, m in enumerate(METHOD_ORDER)}
    scenes = list(SCENE_AGENTS)
    for r in sorted(records, key=lambda r: (order.get(r.method, 99),
                                            scenes.index(r.scene) if r.scene in scenes else 99,
                                            r.seed)):
        training = f"{_f2(_sw(r, 'success'))} / {_f2(_sw(r, 'crash'))} / {_f2(_sw(r, 'timeout'))}"
        if r.method in ("copo", "dynamic-lcf") and r.phi is not None:
            training += f" ({'μ' if r.method == 'copo' else 'φ'} {r.phi:.0f}°)"
        evaluated = []
        for actions in ("mean", "sample"):
            success = _ev(r, actions, "scene_success_rate", eval_seed)
            evaluated.append("–" if success is None else
                             f"{success:.3f} / {_ev(r, actions, 'scene_crash_rate', eval_seed):.3f}"
                             f" / {_ev(r, actions, 'scene_timeout_rate', eval_seed):.3f}")
        name = f"{r.method}-{r.scene}-s{r.seed}"
        run_name = r.name.split("/")[-1]
        where = r.experiment.rstrip("/").split("/")[-1]
        shown = name if run_name == name else f"{name} ({where}/{run_name})"
        lines.append(f"| {shown} | {training} | " + " | ".join(evaluated) + " |")
    return "\n".join(lines) + "\n\n"


def _grid_table1(records, scene, seed):
    at = budget_label(records)
    lines = [f"### Table 1 — {scene} ({SCENE_AGENTS.get(scene, '?')} agents)\n",
             f"| method | seeds | env steps (k) | training success at {at} | best window by {at} "
             "| training crash | unseen, mean action: success | crash | timeout | steps per agent "
             "| arrivals per 300 steps | unseen, sampled: success | crash |",
             "|" + "---|" * 13]
    phis = []
    for method in METHOD_ORDER:
        rs = [r for r in records if r.scene == scene and r.method == method]
        if not rs:
            lines.append(f"| {METHOD_LABEL[method]} | 0 | not run yet |" + " |" * 10)
            continue
        env_k = sum(r.env_steps or 0 for r in rs) / len(rs) / 1000
        cells = [
            fmt([_sw(r, "success") for r in rs]), fmt([r.best for r in rs]),
            fmt([_sw(r, "crash") for r in rs]),
            fmt([_ev(r, "mean", "scene_success_rate", seed) for r in rs]),
            fmt([_ev(r, "mean", "scene_crash_rate", seed) for r in rs]),
            fmt([_ev(r, "mean", "scene_timeout_rate", seed) for r in rs]),
            fmt([_ev(r, "mean", "length_mean", seed) for r in rs], 0),
            fmt([_ev(r, "mean", "successes_per_300", seed) for r in rs], 1),
            fmt([_ev(r, "sample", "scene_success_rate", seed) for r in rs]),
            fmt([_ev(r, "sample", "scene_crash_rate", seed) for r in rs]),
        ]
        lines.append(f"| {METHOD_LABEL[method]} | {len(rs)} | {env_k:.0f} | "
                     + " | ".join(cells) + " |")
        if method in ("copo", "dynamic-lcf"):
            phis.append((METHOD_LABEL[method], [r.phi for r in sorted(rs, key=lambda r: r.seed)]))
    text = "\n".join(lines) + "\n\n"
    for name, values in phis:
        angle = "μ" if name == "CoPO" else "φ"
        text += (f"{angle} at {at}, {name}: "
                 + ", ".join("–" if v is None else f"{v:.0f}°" for v in values) + "\n\n")
    return text


def _grid_paired(records, scenes, eval_seed):
    lines = ["### Against IPPO, seed by seed\n",
             "Each method minus IPPO of the same seed and scene (mean ± 95 % t over the paired "
             "seeds):\n",
             "| scene | method − ippo | n | training success | training crash | unseen mean "
             "success | crash | unseen sampled success | crash |", "|" + "---|" * 9]
    getters: list[Callable] = [
        lambda r: _sw(r, "success"), lambda r: _sw(r, "crash"),
        lambda r: _ev(r, "mean", "scene_success_rate", eval_seed),
        lambda r: _ev(r, "mean", "scene_crash_rate", eval_seed),
        lambda r: _ev(r, "sample", "scene_success_rate", eval_seed),
        lambda r: _ev(r, "sample", "scene_crash_rate", eval_seed),
    ]
    for scene in scenes:
        base = {r.seed: r for r in records if r.scene == scene and r.method == "ippo"}
        for method in sorted({r.method for r in records if r.scene == scene} - {"ippo"}):
            pairs = [(r, base[r.seed]) for r in records
                     if r.scene == scene and r.method == method and r.seed in base]
            if not pairs:
                continue
            cells = []
            for get in getters:
                values = [(get(a), get(b)) for a, b in pairs]
                cells.append(fmt([x - y for x, y in values if x is not None and y is not None],
                                 signed=True))
            lines.append(f"| {scene} | {method} | {len(pairs)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n\n"


def _grid_curves(records, scenes):
    lines = ["### Against CoPO's reference curves\n"]
    header = " | ".join(f"{m // 1000}k env steps" for m in ENV_MARKS)
    lines += [f"| scene | method | {header} |", "|" + "---|" * (2 + len(ENV_MARKS))]
    for scene in scenes:
        for method in sorted({r.method for r in records if r.scene == scene} - {"cl"}):
            rs = [r for r in records if r.scene == scene and r.method == method]
            for smoothed in (False, True):
                # Runs written before scene_totals have no (exactly) smoothed row.
                if smoothed and not all(r.data.get("smoothing") == "exact" for r in rs):
                    continue
                column = "smoothed_success" if smoothed else "success"
                cells = []
                for mark in ENV_MARKS:
                    values = [r.at_env(mark, column) for r in rs]
                    # A mark some seed did not reach is left out rather than averaged over fewer.
                    cells.append("–" if None in values else fmt(values))
                name = f"{method}, 100 scene episodes" if smoothed else method
                lines.append(f"| {scene} | {name} | " + " | ".join(cells) + " |")
    for scene in scenes:
        for method in ("ippo", "copo"):
            points = reference.curve(scene, method)
            if any(m in points for m in ENV_MARKS):
                cells = [f"{points[m]:.2f}" if m in points else "–" for m in ENV_MARKS]
                name = "CoPO" if method == "copo" else "CoPO's IPPO"
                lines.append(f"| {scene} | *{name} on MetaDrive (reference)* | "
                             + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n\n"
