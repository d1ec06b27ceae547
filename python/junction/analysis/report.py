"""`python -m junction.analysis report`: an experiment's report from run directories or
summaries: report.md (Table 1 per scene, every run, the training success at agent-step marks
beside CoPO's curve with *Held*, time to success, the learned LCF angle, how evaluation
episodes ended), summary.json (every run as `summary.json` keeps it, the groups' numbers,
the runs left out) and figures/*.svg (the training curves; from run directories also one per
training-window metric)."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from . import tables
from .figures import write_figures, write_window_figures
from .record import MIN_WINDOW_EPISODES, RunRecord
from .summary import FORMAT, dumps

DEFAULT_MARKS = [1_000_000, 2_500_000, 5_000_000, 7_500_000, 10_000_000, 15_000_000]
#: Training success rates of the time-to-success table.
DEFAULT_THRESHOLDS = [0.5, 0.6, 0.7]


def _names(records, by, order):
    training = [r for r in records if r.is_training]
    table = tables.groups(training, by, order)
    return (list(dict.fromkeys(n for _, n in table)), list(dict.fromkeys(s for s, _ in table)))


def report_markdown(records: Sequence[RunRecord], by: str = "method", order: Sequence[str] = (),
                    eval_seeds: Sequence[int] = (), marks: Sequence[int] = DEFAULT_MARKS,
                    figures: Sequence[str] = (), thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
                    min_episodes: int = MIN_WINDOW_EPISODES, skipped: Sequence[dict] = ()
                    ) -> str:
    training = [r for r in records if r.is_training]
    names, scenes = _names(records, by, order)
    eval_seed = eval_seeds[0] if len(eval_seeds) == 1 else None
    kind = "methods" if by == "method" else "arms"
    md = ["# Junction experiment report\n",
          f"{len(training)} runs ({len(names)} {kind} × {len(scenes)} scenes); made by "
          "`python -m junction.analysis report`.\n"]
    bad = sum(r.data.get("unreadable_progress_lines", 0) for r in training)
    if bad:
        md.append(f"{bad} unreadable progress line(s) skipped (see `summary.json`).\n")
    if skipped:
        md.append("Runs left out (unreadable):\n\n"
                  + "".join(f"- `{s['dir']}`: {s['reason']}\n" for s in skipped))
    for scene in scenes:
        md.append(f"## Table 1 — {scene}\n")
        md.append("Mean ± 95 % confidence half-width over seeds (Student's t on the per-seed "
                  "values). Source per column (row *Source*): `eval` = `actor eval` of the "
                  "final checkpoint (the policy's mean action on held-out seeds; the "
                  "evaluation seeds follow, and a run evaluated on several counts their mean "
                  "unless `--eval-seeds` picks them), `training` = the last training window of "
                  "`progress.jsonl` (the stochastic policy; no per-300-step counts). ↑ higher "
                  "is better, ↓ lower is better; the best mean of a row in bold.\n")
        md.append(tables.table1(training, scene, by, order, list(eval_seeds) or None))
    md.append("## Every run\n")
    md.append(tables.runs_table(training, eval_seed, by))
    reached_marks = [m for m in marks if any(r.agent_steps >= m for r in training)]
    md.append("## Training success at agent-step marks (MetaDrive's definition)\n")
    md.append("Per scene episode the share of its agents that arrived (the stochastic training "
              "policy), read off each seed's curve at the mark; mean ± 95 % over the seeds "
              "(a dash where a seed did not reach it). Per group two rows: the runs' live "
              "window (the last 20 scene episodes) and the same smoothed over 100 scene "
              "episodes as CoPO smoothed its curves. The reference row is CoPO's IPPO on "
              "MetaDrive's intersection (8 seeds; environment steps × ≈ 25 agent-steps). "
              "*Held*: the lowest value after the curve's best, as a share of the best.\n")
    md.append(tables.marks_table(training, reached_marks, by, order))
    md.append("## Time to success\n")
    md.append("First progress line whose training success reached the threshold: MetaDrive's "
              "success in the training window (runs written before that window: the "
              f"agent-episode window once it holds at least {min_episodes} episodes), and the "
              "same smoothed over 100 scene episodes; the run's wall clock, continued over "
              "resumes; means over the seeds that reached it.\n")
    md.append(tables.reach_table(training, thresholds, by, order, min_episodes))
    lcf = tables.lcf_table(training, by, order)
    if lcf:
        md.append("## Learned LCF angle φ by neighbour count\n")
        md.append("φ of each seed's final update (degrees; 0° = own reward, 90° = the "
                  "neighbours' only), mean ± 95 % over seeds, by live-neighbour count.\n")
        md.append(lcf)
    endings = tables.endings_table(training, eval_seed, by, order, report=True)
    if endings:
        md.append("## How evaluation episodes ended\n")
        md.append("Share of the evaluated agent episodes (mean action) by outcome, route stage "
                  "(`entry`: the approach lane, `junction`: inside the junction or on the "
                  "ring, `exit`: the exit lane) and, for crashes, what the car hit "
                  "(docs/EVALUATION.md), mean ± 95 % over the seeds whose evaluations count "
                  "endings, most frequent first.\n")
        md.append(endings)
    others = [r for r in records if r.evals and not r.is_training]
    if others:
        md.append("## Evaluations of checkpoints trained elsewhere\n")
        md.append(tables.evals_table(others))
    if figures:
        md.append("## Figures\n")
        md.append("Lines: mean over seeds against agent-steps; shading: range over seeds.\n")
        md.extend(f"![{Path(f).stem}]({f})\n" for f in figures)
    return "\n".join(md)


def group_summaries(records: Sequence[RunRecord], by: str = "method", order: Sequence[str] = (),
                    eval_seeds: Sequence[int] = (),
                    thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
                    min_episodes: int = MIN_WINDOW_EPISODES) -> list[dict]:
    """Per scene and group, what the report's tables show: the seeds, Table 1's source and
    its metrics as [mean, half-width] over seeds, and per threshold the seeds that reached
    it and the mean agent-steps and seconds they took (`reach`; `smoothed_reach` where every
    seed has the smoothed curve)."""
    training = [r for r in records if r.is_training]
    _, scenes = _names(records, by, order)
    out = []
    for scene in scenes:
        for g in tables.table1_values(training, scene, by, order, list(eval_seeds) or None):
            members = g["members"]
            entry = {"scene": scene, "group": g["group"], "seeds": g["seeds"],
                     "source": g["source"], "eval_seeds": g["eval_seeds"],
                     "metrics": {k: list(v) for k, v in g["metrics"].items()}}
            curves = [("reach", False)]
            if all(r.data.get("smoothing") == "exact" for r in members):
                curves.append(("smoothed_reach", True))
            for name, smoothed in curves:
                entry[name] = {}
                for t in thresholds:
                    hits = tables.reached(members, t, smoothed, min_episodes)
                    entry[name][f"{t:g}"] = {
                        "reached_seeds": len(hits),
                        "mean_reach": {
                            "agent_steps": sum(h["agent_steps"] for h in hits) / len(hits),
                            "elapsed_s": sum(h["wall_s"] for h in hits) / len(hits),
                        } if hits else None}
            out.append(entry)
    return out


def write_report(records: Sequence[RunRecord], out: str | Path, by: str = "method",
                 order: Sequence[str] = (), eval_seeds: Sequence[int] = (),
                 marks: Sequence[int] = DEFAULT_MARKS,
                 thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
                 min_episodes: int = MIN_WINDOW_EPISODES,
                 skipped: Sequence[dict] = ()) -> Path:
    """Writes out/report.md, out/summary.json and out/figures/*.svg; returns report.md's
    path. `eval_seeds`: the evaluation seeds that count (default every one found);
    `skipped`: the run directories left out as unreadable ({dir, reason})."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if eval_seeds:
        for r in records:
            r.evals = [e for e in r.evals if e["seed"] in eval_seeds]
            r.data = dict(r.data, evals=r.evals)
    figures = write_figures(records, out / "figures", by, order)
    figures += write_window_figures(records, out / "figures", by, order, figures)
    names, scenes = _names(records, by, order)
    relative = [f"figures/{p.name}" for p in figures]
    (out / "summary.json").write_text(dumps({
        "format": FORMAT, "experiment": out.name,
        "made_by": "python -m junction.analysis report",
        "groups_by": by, "groups": group_summaries(records, by, order, eval_seeds, thresholds,
                                                   min_episodes),
        "scenes": scenes, "methods" if by == "method" else "arms": names,
        "success_thresholds": list(thresholds), "min_window_episodes": min_episodes,
        "figures": relative, "skipped": list(skipped),
        "runs": [r.data for r in records]}))
    (out / "report.md").write_text(report_markdown(
        records, by, order, eval_seeds, marks, relative, thresholds, min_episodes, skipped))
    return out / "report.md"
