"""The analysis of finished runs: one implementation for every table and figure of RESULTS.md
and the results folders, importable without the native module, libtorch or anything beyond
the standard library (`sys.path` holding `python/` is enough).

- Reading: `read_progress` (a run's `progress.jsonl` as one history, a resume's rolled-back
  lines dropped), `run_clock` (a resumed run's wall time continued), `read_config`,
  `read_eval`; `RawRun` for a run directory.
- Curves: `smoothed_scene_success` / `smoothed_scene_rate` (CoPO's smoothing over 100 scene
  episodes, from `scene_totals`), `approximately_smoothed` (for runs written before the
  totals), `interpolate`, `first_reach`, `held_after_best`.
- Intervals: `mean_ci` / `t_interval` (mean ± 95 % Student's t over seeds, exact quantiles),
  `paired_difference` (an arm minus a baseline of the same seed), `wilson`.
- Runs as kept: `record_from_run` / `RunRecord`, a results folder's `summary.json`
  (`summarize`, `write_summary`, `load`); tables (`junction.analysis.tables`), SVG figures
  (`junction.analysis.figures`), an experiment's report (`junction.analysis.report`).
- CoPO's reference curves and table: `junction.analysis.reference` (`copo_reference.json`).
- The command line: `python -m junction.analysis --help`.
"""

from .record import RunRecord, record_from_run
from .runs import (OUTCOMES, SMOOTHING, RawRun, approximately_smoothed, first_reach,
                   held_after_best, interpolate, process_starts, read_config, read_eval,
                   read_evals, read_progress, run_clock, smoothed_scene_rate,
                   smoothed_scene_success, variant_name, without_rolled_back)
from .stats import (T975, fmt, mean_ci, paired, paired_difference, t_interval, t_quantile,
                    t_quantile_975, wilson)
from .summary import load, read_summary, summarize, write_summary

__all__ = [
    "OUTCOMES", "SMOOTHING", "T975", "RawRun", "RunRecord", "approximately_smoothed",
    "first_reach", "fmt", "held_after_best", "interpolate", "load", "mean_ci", "paired",
    "paired_difference", "process_starts", "read_config", "read_eval", "read_evals",
    "read_progress", "read_summary", "record_from_run", "run_clock", "smoothed_scene_rate",
    "smoothed_scene_success", "summarize", "t_interval", "t_quantile", "t_quantile_975",
    "variant_name", "wilson", "without_rolled_back", "write_summary",
]
