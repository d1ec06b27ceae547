"""Reading run directories as the learner and `actor eval` write them: the training curve
(`progress.jsonl`, docs/EVALUATION.md), what was trained (`config.toml`) and the evaluations
(`eval/eval-*.json`, format `junction-eval/1`). Standard library only."""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path
from typing import Iterable, Sequence

#: CoPO's smoothing of its curves (RLlib's metrics_smoothing_episodes), in scene episodes.
SMOOTHING = 100
#: MetaDrive's outcomes, as `scene_window` and `scene_totals` name them.
OUTCOMES = ("success", "crash", "out_of_road", "timeout")
EVAL_FORMAT = "junction-eval/1"


def read_progress(path: str | Path) -> list[dict]:
    """The lines of a run's `progress.jsonl` (or of the one in the run directory `path`) as
    one history: see `without_rolled_back`. A line cut short (a crash mid-write) is skipped."""
    return without_rolled_back(_read_lines(path)[0])


def _read_lines(path: str | Path) -> tuple[list[dict], int]:
    path = Path(path)
    if path.is_dir():
        path = path / "progress.jsonl"
    lines, bad = [], 0
    with open(path) as f:
        for line in f:
            line = line.strip()
            if not line:
                continue
            try:
                lines.append(json.loads(line))
            except json.JSONDecodeError:
                bad += 1
    return lines, bad


def without_rolled_back(lines: list[dict]) -> list[dict]:
    """One history whose agent-steps only grow: a resumed learner trains on from its newest
    checkpoint, so each line drops the lines before it that are further on than itself (the
    training the resume rolled back)."""
    kept: list[dict] = []
    for line in lines:
        while kept and kept[-1]["agent_steps"] > line["agent_steps"]:
            kept.pop()
        kept.append(line)
    return kept


def process_starts(lines: Sequence[dict]) -> list[int]:
    """The index where each learner process of a run begins: 0, and one more per resume (a
    process's clock and scene totals only grow; a resumed one starts both from 0 again)."""
    starts = [0]
    for i in range(1, len(lines)):
        before, line = lines[i - 1], lines[i]
        if (line.get("elapsed_s", 0) < before.get("elapsed_s", 0)
                or _scene_episodes(line) < _scene_episodes(before)):
            starts.append(i)
    return starts


def _scene_episodes(line: dict) -> int:
    return (line.get("scene_totals") or {}).get("scene_episodes", 0)


def run_clock(lines: Sequence[dict]) -> list[float]:
    """Wall-clock seconds of training behind each line: its process's clock plus each earlier
    process's up to its last kept line (a resumed run's time is the sum of its processes')."""
    starts = set(process_starts(lines)) - {0}
    clock, offset = [], 0.0
    for i, line in enumerate(lines):
        if i in starts:
            offset += lines[i - 1].get("elapsed_s", 0.0)
        clock.append(offset + line.get("elapsed_s", 0.0))
    return clock


def smoothed_scene_rate(lines: list[dict], episodes: int = SMOOTHING, outcome: str = "success",
                        key: str = "agent_steps", keys: Sequence[str] | None = None) -> list:
    """MetaDrive's training rate of `outcome` smoothed as CoPO smoothed its curves, over the
    last `episodes` scene episodes (at least; whole progress lines apart), from the lines'
    `scene_totals`. Per line with that many episodes of the run behind it: (line[key], rate),
    or with `keys` (line[k] for k in keys) + (rate,). Empty for runs written before
    `scene_totals` existed. A resumed process counts its totals from 0 again; they continue
    the run's."""
    lines = without_rolled_back(lines)
    episodes = max(1, episodes)
    starts = set(process_starts(lines)) - {0}
    out, behind, offset = [], [(0, 0.0)], (0, 0.0)
    for i, line in enumerate(lines):
        totals = line.get("scene_totals")
        if not totals:
            return []
        if i in starts:
            offset = behind[-1]
        here = (offset[0] + totals["scene_episodes"], offset[1] + totals.get(outcome, 0.0))
        base = next((b for b in reversed(behind) if b[0] <= here[0] - episodes), None)
        if base is not None:
            rate = (here[1] - base[1]) / (here[0] - base[0])
            out.append((line[key], rate) if keys is None else (*(line[k] for k in keys), rate))
        behind.append(here)
    return out


def smoothed_scene_success(lines: list[dict], episodes: int = SMOOTHING,
                           key: str = "agent_steps", keys: Sequence[str] | None = None) -> list:
    """`smoothed_scene_rate` of arrivals: MetaDrive's training success as CoPO's curves show it."""
    return smoothed_scene_rate(lines, episodes, "success", key, keys)


def first_reach(points: Iterable[tuple], threshold: float) -> tuple | None:
    """The first point whose last value is at least `threshold`, without that value (e.g.
    (seconds, agent_steps) of (seconds, agent_steps, success) points); None if none does."""
    for point in points:
        if point[-1] >= threshold:
            return point[:-1]
    return None


def held_after_best(values: Sequence[float]) -> float | None:
    """The lowest value of a curve from its (first) best on, as a share of the best (issue
    12's "never below 80 % of its best"); None for an empty curve or a best of 0."""
    if not values:
        return None
    best_at = max(range(len(values)), key=lambda i: (values[i], -i))
    best = values[best_at]
    return min(values[best_at:]) / best if best > 0 else None


def interpolate(points: Sequence[tuple[float, float]], x: float) -> float | None:
    """Linear interpolation of a curve sorted by x at x; None outside its range."""
    if not points or x < points[0][0] or x > points[-1][0]:
        return None
    lo, hi = 0, len(points)
    while lo < hi:  # the first point with x' >= x
        mid = (lo + hi) // 2
        if points[mid][0] < x:
            lo = mid + 1
        else:
            hi = mid
    if lo == 0:
        return points[0][1]
    (x0, y0), (x1, y1) = points[lo - 1], points[lo]
    return y0 + (y1 - y0) * (x - x0) / (x1 - x0) if x1 > x0 else y1


def read_config(path: str | Path) -> dict:
    """A run's effective `config.toml` ({} when absent)."""
    path = Path(path)
    if not path.is_file():
        return {}
    with open(path, "rb") as f:
        return tomllib.load(f)


def flatten(table: dict, prefix: str = "") -> dict:
    """{"a.b.c": value} of a nested TOML table."""
    out = {}
    for key, value in table.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, name + "."))
        else:
            out[name] = value
    return out


def variant_name(name: str) -> str:
    """A run directory's name without a trailing `-s<seed>`: `decoupled-s2` -> `decoupled`."""
    match = re.fullmatch(r"(.*)-s\d+", name)
    return match.group(1) if match else name


#: Metrics whose interval a summary keeps (the rates); the others keep their value alone.
INTERVAL_METRICS = {"collision_rate", "scene_success_rate", "scene_crash_rate",
                    "scene_out_of_road_rate", "success_rate", "crash_rate", "out_of_road_rate",
                    "timeout_rate"}
_EVAL_NAME = re.compile(r"eval-(?P<scenario>.+)-seed(?P<seed>\d+)(?P<sample>-sample)?\.json")


def read_eval(path: str | Path) -> dict:
    """One `actor eval` (or `metadrive_eval`) result, compacted: what it evaluated and every
    metric to 5 significant digits, the rates of INTERVAL_METRICS as [value, low, high] (the
    interval's n: `scene_episodes` for the `scene_*` rates, `episodes` for the others), the
    rest as [value]. What the file leaves out is read from
    its name (`eval-<scenario>-seed<S>[-sample].json`)."""
    path = Path(path)
    raw = json.loads(path.read_text())
    if raw.get("format", EVAL_FORMAT) != EVAL_FORMAT:
        raise ValueError(f"{path}: format {raw.get('format')!r}, not {EVAL_FORMAT}")
    named = _EVAL_NAME.fullmatch(path.name)
    actions = raw.get("actions") or ("sample" if named and named["sample"] else "mean")
    metrics = {}
    for key, m in raw["metrics"].items():
        if m is None:
            continue
        metrics[key] = ([_round(m["value"]), _round(m.get("low")), _round(m.get("high"))]
                        if key in INTERVAL_METRICS else [_round(m["value"])])
    training = raw.get("training") or {}
    return {
        "scenario": raw.get("scenario") or (named and named["scenario"]),
        "seed": raw.get("seed", int(named["seed"]) if named else None),
        "actions": actions,
        "after_horizon": raw.get("after_horizon"),
        "episodes": raw.get("episodes"),
        "scene_episodes": raw.get("scene_episodes"),
        "scenes": raw.get("scenes"),
        "scene_steps": raw.get("scene_steps"),
        "policy_version": raw.get("policy_version"),
        # What was evaluated: learner.algo, scenario, run.seed and agent-steps of the run.
        "trained": [training.get("algorithm"), training.get("scenario"), training.get("seed"),
                    training.get("agent_steps")],
        "outcomes": raw.get("outcomes", {}),
        # How agent episodes ended (outcome / route stage / what a crash hit): mean actions.
        "endings": raw.get("endings", {}) if actions == "mean" else {},
        "metrics": metrics,
    }


def _round(value, digits: int = 5):
    if value is None or not isinstance(value, float):
        return value
    return float(f"{value:.{digits}g}")


def read_evals(directory: str | Path) -> list[dict]:
    """Every evaluation JSON in `directory` (a run's `eval/`), sorted by file name."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    return [read_eval(p) for p in sorted(directory.glob("eval-*.json"))]


class RawRun:
    """One run directory as the learner left it."""

    def __init__(self, directory: str | Path):
        self.dir = Path(directory)
        lines, self.bad_lines = _read_lines(self.dir)
        self.lines = without_rolled_back(lines)
        if not self.lines:
            raise ValueError(f"{self.dir}/progress.jsonl holds no readable progress line")
        self.config = read_config(self.dir / "config.toml")
        last = self.lines[-1]
        self.method = (self.config.get("learner", {}).get("algo") or last.get("algorithm")
                       or "?")
        self.scene = (self.config.get("scenario", {}).get("name") or last.get("scenario")
                      or "?")
        seed = self.config.get("run", {}).get("seed", last.get("seed"))
        self.seed = int(seed) if seed is not None else None
        self.clock = run_clock(self.lines)
        self.evals = read_evals(self.dir / "eval")


def approximately_smoothed(lines: Sequence[dict], window: int = 20,
                           episodes: int = SMOOTHING, key: str = "agent_steps"
                           ) -> list[tuple[int, float]]:
    """CoPO's smoothing approximated for runs written before `scene_totals`: at each line,
    the mean of episodes / window full 20-scene-episode windows, `window` scene episodes
    apart, the scene episodes counted as env_steps over the window's mean scene-episode
    length (within a point of the exact share where both exist: results/metadrive-smoothing).
    (line[key], success) per line that has them all."""
    import bisect
    lines = [l for l in lines if (l.get("scene_window") or {}).get("scene_episodes", 0) > 0]
    counted, total, previous = [], 0.0, None
    for line in lines:
        w = line["scene_window"]
        if previous is not None and w.get("mean_steps", 0) > 0:
            total += (line["env_steps"] - previous["env_steps"]) / w["mean_steps"]
        previous = line
        counted.append(total)
    out = []
    for i, line in enumerate(lines):
        picks = []
        for k in range(episodes // window):
            j = bisect.bisect_right(counted, counted[i] - k * window + 1e-9, 0, i + 1) - 1
            if j < 0 or lines[j]["scene_window"]["scene_episodes"] < window:
                break
            picks.append(lines[j]["scene_window"]["success_rate"])
        if len(picks) == episodes // window:
            out.append((line[key], sum(picks) / len(picks)))
    return out
