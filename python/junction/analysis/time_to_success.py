"""The time-to-success table: `scripts/time-to-success.py`'s JSON lines (one file per setting,
one line per training seed and a summary line) as one Markdown row per setting, the mean and
95 % t half-width over its seeds. The evaluation columns are the mean action's (issue 40's bar)
and, beside them, sampled actions' (CoPO's evaluation samples)."""

from __future__ import annotations

import json
from pathlib import Path

from .stats import fmt, mean_ci

HEADER = ("| setting | seeds | agent-steps/s | agent-steps | training window ≥ {t:g} at "
          "(s; 100 episodes) | ≥ {threshold:g} | final window | evaluated success | crash "
          "| out of road | timeout | sampled success | sampled crash |")


def seed_lines(path: Path) -> list[dict]:
    """The per-seed lines of one file (its summary line left out), in seed order."""
    lines = [json.loads(l) for l in path.read_text().splitlines() if l.strip()]
    seeds = [l for l in lines if l.get("bench") == "time_to_success"]
    if not seeds:
        raise ValueError(f"{path}: no time_to_success line")
    return sorted(seeds, key=lambda l: l["seed"])


def _reach(line: dict, window: str, threshold: float) -> float | None:
    """Seconds to the first reach of `threshold` over the `window` ("20" or "100") episodes."""
    if abs(threshold - line["threshold"]) < 1e-9:
        return line[f"seconds_to_threshold_{window}"]
    reached = line.get(f"reach_{window}", {}).get(f"{threshold:g}")
    return reached[0] if reached else None


def _seconds(values: list[float | None]) -> str:
    """Each seed's seconds, `never` for a seed that did not get there."""
    return " / ".join("never" if v is None else f"{v:.0f}" for v in values)


def _later_rate(seeds: list[dict], key: str) -> str:
    """Mean ± t over the seeds of an evaluation rate the script reports since 2026-12-07 (the
    timeout and the sampled evaluation): a dash in files written before."""
    return fmt([l.get(key, {}).get("value") for l in seeds], 3)


def row(label: str, seeds: list[dict], also: float) -> str:
    threshold = seeds[0]["threshold"]
    steps = [l["agent_steps"] for l in seeds]
    rate = mean_ci(l["agent_steps_per_s"] for l in seeds)
    reached = [_reach(l, "20", threshold) for l in seeds]
    cells = [
        label,
        ", ".join(str(l["seed"]) for l in seeds),
        f"{rate[0]:,.0f}" + ("" if rate[1] is None else f" ± {rate[1]:,.0f}"),
        f"{min(steps) / 1e6:.1f}–{max(steps) / 1e6:.1f} M",
        f"{_seconds([_reach(l, '20', also) for l in seeds])} "
        f"({_seconds([_reach(l, '100', also) for l in seeds])})",
        f"{sum(r is not None for r in reached)}/{len(seeds)} seeds"
        + ("" if not any(r is not None for r in reached) else f": {_seconds(reached)} s"),
        fmt([l["final_success_20"] for l in seeds]),
        fmt([l["eval_success"]["value"] for l in seeds], 3),
        fmt([l["eval_crash"]["value"] for l in seeds], 3),
        fmt([l["eval_out_of_road"]["value"] for l in seeds], 3),
        _later_rate(seeds, "eval_timeout"),
        _later_rate(seeds, "eval_sampled_success"),
        _later_rate(seeds, "eval_sampled_crash"),
    ]
    return "| " + " | ".join(cells) + " |"


def table(files: list[str], also: float = 0.7) -> str:
    """One row per file, labelled by its name without `.jsonl`."""
    rows = [(Path(f).stem, seed_lines(Path(f))) for f in files]
    threshold = rows[0][1][0]["threshold"]
    columns = HEADER.count("|") - 1
    lines = [HEADER.format(t=also, threshold=threshold), "|" + "---|" * columns]
    lines += [row(label, seeds, also) for label, seeds in rows]
    return "\n".join(lines) + "\n"
