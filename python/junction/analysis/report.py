"""`python -m junction.analysis report`: what `learner report` wrote, from run directories or
summaries: report.md (Table 1 per scene, time to success, the training success at agent-step
marks beside CoPO's curve with *Held*, the learned LCF angle, how evaluation episodes ended),
summary.json (every run as `summary.json` keeps it) and figures/*.svg."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from . import tables
from .figures import write_figures
from .record import RunRecord
from .summary import FORMAT, dumps

DEFAULT_MARKS = [1_000_000, 2_500_000, 5_000_000, 7_500_000, 10_000_000, 15_000_000]


def report_markdown(records: Sequence[RunRecord], by: str = "method", order: Sequence[str] = (),
                    eval_seeds: Sequence[int] = (), marks: Sequence[int] = DEFAULT_MARKS,
                    figures: Sequence[str] = ()) -> str:
    training = [r for r in records if r.is_training]
    scenes = list(dict.fromkeys(s for s, _ in tables.groups(training, by, order)))
    eval_seed = eval_seeds[0] if len(eval_seeds) == 1 else None
    md = ["# Junction experiment report\n",
          f"{len(training)} runs; made by `python -m junction.analysis report`.\n"]
    bad = sum(r.data.get("unreadable_progress_lines", 0) for r in training)
    if bad:
        md.append(f"{bad} unreadable progress line(s) skipped.\n")
    for scene in scenes:
        md.append(f"## Table 1 — {scene}\n")
        md.append("Mean ± 95 % confidence half-width over seeds (Student's t on the per-seed "
                  "values). Source per column: `eval` = `actor eval` of the final checkpoint "
                  "(the policy's mean action on held-out seeds; several evaluation seeds of a "
                  "run count their mean), `training` = the last training window of "
                  "`progress.jsonl` (the stochastic policy). ↑ higher is better, ↓ lower is "
                  "better; the best mean of a row in bold.\n")
        md.append(tables.table1(training, scene, by, order, list(eval_seeds) or None))
    md.append("## Every run\n")
    md.append(tables.runs_table(training, eval_seed, by))
    reached = [m for m in marks if any(r.agent_steps >= m for r in training)]
    md.append("## Training success at agent-step marks (MetaDrive's definition)\n")
    md.append("Per scene episode the share of its agents that arrived (the stochastic training "
              "policy), read off each seed's curve at the mark; mean ± 95 % over the seeds "
              "(a dash where a seed did not reach it). Per group two rows: the runs' live "
              "window (the last 20 scene episodes) and the same smoothed over 100 scene "
              "episodes as CoPO smoothed its curves. The reference row is CoPO's IPPO on "
              "MetaDrive's intersection (8 seeds; environment steps × ≈ 25 agent-steps). "
              "*Held*: the lowest value after the curve's best, as a share of the best.\n")
    md.append(tables.marks_table(training, reached, by, order))
    md.append("## Time to success\n")
    md.append("First progress line whose training success reached the threshold (the run's "
              "wall clock, continued over resumes); means over the seeds that reached it.\n")
    md.append(tables.reach_table(training, by=by, order=order))
    lcf = tables.lcf_table(training, by, order)
    if lcf:
        md.append("## Learned LCF angle φ by neighbour count\n")
        md.append("φ of each seed's final update (degrees; 0° = own reward, 90° = the "
                  "neighbours' only), mean ± 95 % over seeds, by live-neighbour count.\n")
        md.append(lcf)
    endings = tables.endings_table(training, eval_seed, by, order)
    if endings:
        md.append("## How evaluation episodes ended\n")
        md.append("Share of the evaluated agent episodes (mean action) by outcome, route stage "
                  "and, for crashes, what the car hit (docs/EVALUATION.md), mean ± 95 % over "
                  "seeds.\n")
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


def write_report(records: Sequence[RunRecord], out: str | Path, by: str = "method",
                 order: Sequence[str] = (), eval_seeds: Sequence[int] = (),
                 marks: Sequence[int] = DEFAULT_MARKS) -> Path:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if eval_seeds:
        for r in records:
            r.evals = [e for e in r.evals if e["seed"] in eval_seeds]
            r.data = dict(r.data, evals=r.evals)
    figures = write_figures(records, out / "figures", by, order)
    (out / "summary.json").write_text(dumps({
        "format": FORMAT, "experiment": out.name,
        "made_by": "python -m junction.analysis report",
        "runs": [r.data for r in records]}))
    (out / "report.md").write_text(report_markdown(
        records, by, order, eval_seeds, marks,
        [f"figures/{p.name}" for p in figures]))
    return out / "report.md"

