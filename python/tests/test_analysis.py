"""junction.analysis: the smoothing, the intervals, CoPO's reference values, the marks, first
reach, Held, paired differences, and a results folder's summary read back as the raw runs
read. Standard library only: runs from a plain checkout (no native module)."""

import json
import math
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

PYTHON = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(PYTHON))

from junction import analysis  # noqa: E402
from junction.analysis import reference, stats, tables  # noqa: E402
from junction.analysis.record import RunRecord, record_from_run  # noqa: E402
from junction.analysis.runs import RawRun  # noqa: E402


def close(a, b, tol=1e-9):
    return abs(a - b) <= tol


# ---------------------------------------------------------------- intervals

@pytest.mark.parametrize("df,expected", [(1, 12.7062), (2, 4.3027), (3, 3.1824), (4, 2.7764),
                                         (5, 2.5706), (9, 2.2622), (10, 2.2281),
                                         (29, 2.0452), (30, 2.0423), (100, 1.9840),
                                         (1000, 1.9623), (5000, 1.9604)])
def test_t_quantiles_match_the_printed_tables(df, expected):
    assert close(stats.t_quantile_975(df), expected, 5e-4)
    # The printed table kept for readers agrees to its three decimals.
    if df in analysis.T975:
        assert close(analysis.T975[df], expected, 1e-3)


def test_mean_ci_is_the_student_t_half_width_over_seeds():
    # Mean 0.4, s = 0.2, t(2) = 4.3027: half-width 4.3027 · 0.2 / √3 = 0.49683.
    mean, half = analysis.mean_ci([0.2, 0.4, 0.6])
    assert close(mean, 0.4) and close(half, 0.49683, 1e-4)
    # Two seeds: 12.706 · |a − b| / 2.
    mean, half = analysis.mean_ci([0.6, 0.8])
    assert close(mean, 0.7) and close(half, 12.7062 * 0.1, 1e-4)
    assert analysis.mean_ci([0.5]) == (0.5, None)
    assert analysis.mean_ci([None, None]) == (None, None)
    assert analysis.t_interval([0.5]) == (0.5, 0.0)
    assert stats.fmt([0.6, 0.8]) == "0.70 ± 1.27"
    assert stats.fmt([0.1, 0.1, 0.1], signed=True) == "+0.10 ± 0.00"
    assert stats.fmt([]) == "–"


def test_paired_differences_take_the_seeds_both_arms_have():
    arm = {1: 0.7, 2: 0.8, 3: 0.5, 4: None}
    base = {1: 0.6, 2: 0.6, 4: 0.4, 5: 0.1}
    assert [round(d, 9) for d in analysis.paired(arm, base)] == [0.1, 0.2]
    mean, half, n = analysis.paired_difference(arm, base)
    assert n == 2 and close(mean, 0.15) and close(half, 12.7062 * 0.05, 1e-4)


def test_wilson_interval_matches_a_known_value():
    # 772 of 1077 (ippo-intersection-s1's evaluation, whose JSON `actor eval` wrote with
    # core/src/confidence.rs's Wilson interval): 0.7168 [0.68916, 0.74291].
    low, high = analysis.wilson(772, 1077)
    assert close(low, 0.689164, 1e-6) and close(high, 0.742907, 1e-6)
    assert analysis.wilson(0, 10)[0] == 0.0 and close(analysis.wilson(10, 10)[1], 1.0)


# ---------------------------------------------------------------- smoothing and resumes

def totals(steps, elapsed, episodes, success, **extra):
    return {"agent_steps": steps, "elapsed_s": elapsed,
            "scene_totals": {"scene_episodes": episodes, "success": success}, **extra}


def test_smoothing_takes_the_newest_whole_lines_that_hold_enough_episodes():
    # The Rust report's case (learner/src/report/aggregate.rs, since removed): two resumes,
    # the second told apart by its clock.
    lines = [totals(10, 1, 4, 1.0), totals(20, 2, 10, 4.0), totals(30, 3, 12, 6.0),
             totals(40, 4, 16, 10.0), totals(50, 1, 3, 3.0), totals(60, 2, 11, 3.0),
             totals(70, 1, 14, 7.0)]
    assert analysis.process_starts(lines) == [0, 4, 6]
    curve = analysis.smoothed_scene_success(lines, episodes=10)
    expected = [(20, 0.4), (30, 0.5), (40, 0.75), (50, 0.8), (60, 3 / 11), (70, 0.5)]
    assert [x for x, _ in curve] == [x for x, _ in expected]
    assert all(close(r, e) for (_, r), (_, e) in zip(curve, expected)), curve


def test_smoothing_windows_the_run_as_one_across_a_resume():
    # A process to 40, killed; the next resumed from its checkpoint at 30 and counts from 0.
    lines = [totals(10, 1, 40, 20.0), totals(20, 2, 100, 50.0), totals(30, 3, 150, 100.0),
             totals(40, 4, 210, 160.0), totals(35, 1, 30, 30.0), totals(45, 2, 120, 60.0)]
    smoothed = analysis.smoothed_scene_success(lines, episodes=100)
    # The line at 40 was rolled back; the resumed totals continue the line at 30's (150, 100).
    assert [s for s, _ in smoothed] == [20, 30, 35, 45]
    expected = [50 / 100, (100 - 20) / (150 - 40), (130 - 20) / (180 - 40),
                (160 - 100) / (270 - 150)]
    assert all(close(r, e) for (_, r), e in zip(smoothed, expected)), smoothed
    # Runs written before scene_totals existed have no smoothed curve.
    assert analysis.smoothed_scene_success([{"agent_steps": 1, "scene_window": {}}]) == []
    # The other outcomes smooth the same way.
    lines = [dict(l, scene_totals=dict(l["scene_totals"], crash=l["scene_totals"]["success"] / 2))
             for l in lines]
    crash = analysis.smoothed_scene_rate(lines, 100, "crash")
    assert all(close(c, s / 2) for (_, c), (_, s) in zip(crash, smoothed))


def test_a_resumed_runs_clock_adds_its_processes_up():
    lines = analysis.without_rolled_back(
        [{"agent_steps": x, "elapsed_s": t} for x, t in
         [(10, 1.0), (20, 2.0), (30, 3.0), (40, 4.0), (25, 0.5), (35, 1.5)]])
    assert [l["agent_steps"] for l in lines] == [10, 20, 25, 35]
    assert analysis.run_clock(lines) == [1.0, 2.0, 2.5, 3.5]


def test_the_approximate_smoothing_averages_five_windows_twenty_episodes_apart():
    # Scene episodes of 100 env steps: a line every 2000 env steps is 20 scene episodes on.
    lines = [{"agent_steps": 1000 * i, "env_steps": 2000 * i,
              "scene_window": {"scene_episodes": 20, "success_rate": 0.1 * i,
                               "mean_steps": 100.0}} for i in range(1, 8)]
    curve = analysis.approximately_smoothed(lines)
    # From the fifth line on: the mean of that line's window and the four before.
    assert [x for x, _ in curve] == [5000, 6000, 7000]
    assert all(close(v, e) for (_, v), e in zip(curve, [0.3, 0.4, 0.5]))


# ---------------------------------------------------------------- reaching, holding, marks

def test_first_reach_held_and_interpolation():
    points = [(1.0, 100, 0.2), (2.0, 200, 0.85), (3.0, 300, 0.9)]
    assert analysis.first_reach(points, 0.8) == (2.0, 200)
    assert analysis.first_reach(points, 0.95) is None
    assert analysis.held_after_best([0.9, 0.2, 1.0, 0.6, 0.8, 1.0]) == 0.6
    assert analysis.held_after_best([0.2, 0.4]) == 1.0
    assert analysis.held_after_best([]) is None and analysis.held_after_best([0.0]) is None
    curve = [(0.0, 0.0), (10.0, 1.0), (20.0, 3.0)]
    assert analysis.interpolate(curve, 5.0) == 0.5 and analysis.interpolate(curve, 15.0) == 2.0
    assert analysis.interpolate(curve, 21.0) is None and analysis.interpolate([], 1.0) is None


def progress_line(steps, elapsed, success, crash=0.1, episodes=None, env_per_agent=0.04):
    return {"agent_steps": steps, "env_steps": int(steps * env_per_agent), "elapsed_s": elapsed,
            "algorithm": "ippo", "scenario": "intersection", "seed": 1,
            "scene_window": {"scene_episodes": 20, "success_rate": success,
                             "crash_rate": crash, "out_of_road_rate": 0.0,
                             "timeout_rate": 1 - success - crash, "mean_steps": 100.0},
            "window": {"episodes": 200, "success_rate": success, "mean_length": 400.0},
            "update": {"entropy": 2.0, "approx_kl": 0.01, "lag_mean": 2.0, "lag_max": 3},
            **({"scene_totals": {"scene_episodes": episodes, "success": success * episodes}}
               if episodes is not None else {})}


def write_run(root, name, seed, successes, method="ippo", scene="intersection", resume_at=None,
              evals=()):
    """A run with a progress line every 250k agent-steps (10 s apart), optionally resumed:
    the first process's lines after `resume_at` are rolled back and the clock restarts."""
    run = root / "runs" / name
    (run / "eval").mkdir(parents=True)
    (run / "config.toml").write_text(
        f'[run]\nseed = {seed}\nmax_agent_steps = {len(successes) * 250_000}\n'
        f'[scenario]\nname = "{scene}"\n[learner]\nalgo = "{method}"\n')
    lines, episodes = [], 0
    for i, s in enumerate(successes, 1):
        episodes += 30
        # A first process that dies later ran a little past the marks it is rolled back from.
        past = 10_000 if resume_at is not None and i > resume_at else 0
        lines.append(progress_line(i * 250_000 + past, 10.0 * i, s, episodes=episodes))
    if resume_at is not None:
        # The learner died after the last line and resumed from its checkpoint at resume_at:
        # lines from there are written again by a process whose clock and totals start at 0.
        k = resume_at
        lines += [progress_line(j * 250_000, 10.0 * (j - k), successes[j - 1],
                                episodes=30 * (j - k)) for j in range(k + 1, len(successes) + 1)]
    (run / "progress.jsonl").write_text("".join(json.dumps(l) + "\n" for l in lines))
    for seed_e, actions, success, crash in evals:
        write_eval(run / "eval", scene, seed_e, actions, success, crash)
    return run


def write_eval(directory, scenario, seed, actions, success, crash):
    """An evaluation JSON: MetaDrive's rates with t intervals over 12 scene episodes (success
    ± 0.1), the agent-episode success with a Wilson interval (± 0.03)."""
    suffix = "-sample" if actions == "sample" else ""
    metrics = {"scene_success_rate": {"value": success, "low": success - 0.1,
                                      "high": success + 0.1, "ci": "student_t", "n": 12},
               "scene_crash_rate": {"value": crash, "low": 0, "high": 1, "ci": "student_t",
                                    "n": 12},
               "scene_out_of_road_rate": {"value": 0.01, "low": 0, "high": 1,
                                          "ci": "student_t", "n": 12},
               "success_rate": {"value": success, "low": success - 0.03,
                                "high": success + 0.03, "ci": "wilson", "n": 1000}}
    (directory / f"eval-{scenario}-seed{seed}{suffix}.json").write_text(json.dumps({
        "format": "junction-eval/1", "scenario": scenario, "seed": seed, "actions": actions,
        "episodes": 1000, "scene_episodes": 12, "outcomes": {}, "metrics": metrics,
        "endings": {"success/exit": 700, "crash/junction/crossing": 300}}))


def test_a_resumed_run_is_one_history_with_its_clock_continued(tmp_path):
    run = write_run(tmp_path, "ippo-s1", 1, [0.1, 0.2, 0.5, 0.6, 0.7, 0.8], resume_at=2)
    record = RunRecord(record_from_run(RawRun(run), "runs/ippo-s1"))
    # 20 s to the checkpoint at 500k, then 40 s more: 60 s, not the last process's 40.
    assert record.wall_s == 60.0
    assert record.data["processes"] == 2
    reach = record.reach(0.7)
    assert reach["agent_steps"] == 1_250_000 and reach["wall_s"] == 50.0
    # The curve at every 250k agent-steps; between marks a run's value is interpolated.
    assert record.at(1_000_000) == 0.6 and close(record.at(1_125_000), 0.65)
    assert record.at(2_000_000) is None
    # Smoothed over 100 scene episodes (30 per line): the totals continue over the resume.
    smoothed = record.curve("smoothed_success")
    assert smoothed[0][0] == 1_000_000
    # Each line's totals: 30 scene episodes a line, arrivals = its rate × its process's
    # episodes. At 1M the run has 120 episodes behind it: the first process's 60 to the
    # checkpoint (0.2 · 60 arrivals) and the resumed one's 60 (0.6 · 60): 48 / 120.
    assert close(smoothed[0][1], 0.4)
    # Not the resumed process's own 60 episodes (0.6), which are too few for 100 anyway.


def test_marks_best_held_and_first_reach_of_a_run(tmp_path):
    run = write_run(tmp_path, "ippo-s1", 1, [0.1, 0.4, 0.8, 0.5, 0.7, 0.6])
    record = RunRecord(record_from_run(RawRun(run), "runs/ippo-s1"))
    assert record.best == 0.8 and record.data["best"]["agent_steps"] == 750_000
    assert record.held() == 0.5 / 0.8
    assert record.at(500_000) == 0.4 and record.at(1_500_000, "best_success") == 0.8
    assert record.last("success") == 0.6 and record.agent_steps == 1_500_000
    assert record.reach(0.5)["agent_steps"] == 750_000 and record.reach(0.9) is None
    assert record.at_env(50_000) == 0.7  # 0.04 env steps per agent-step: 1.25M
    assert record.data["lag"]["final"] == 2.0


# ---------------------------------------------------------------- reference

def test_copo_reference_values():
    ippo = reference.curve("intersection")
    assert ippo == {100_000: 0.19, 150_000: 0.33, 200_000: 0.50, 250_000: 0.58,
                    300_000: 0.63, 500_000: 0.65, 600_000: 0.70, 1_000_000: 0.63}
    assert reference.curve("intersection", "copo") == {200_000: 0.54, 300_000: 0.67,
                                                        1_000_000: 0.75}
    assert reference.curve("roundabout") == {100_000: 0.13, 200_000: 0.32, 400_000: 0.51,
                                             1_000_000: 0.61}
    # ≈ 25 agent-steps per environment step of the 30-agent intersection; unknown elsewhere.
    assert reference.curve_by_agent_steps("intersection")[5_000_000] == 0.50
    assert reference.curve_by_agent_steps("roundabout") == {}
    # MetaDrive's own intersection and Junction's twin of it are read against CoPO's curve.
    for scene in ("intersection-on-metadrive", "intersection-metadrive"):
        assert reference.curve_by_agent_steps(scene)[5_000_000] == 0.50
    assert reference.curve("roundabout-large") == {}
    assert reference.table("intersection") == {"ippo": 0.719, "ccppo-concat": 0.757,
                                               "ccppo-mf": 0.708, "cl": 0.757, "copo": 0.795}
    assert reference.table("roundabout")["copo"] == 0.728
    assert "arXiv:2111.00680" in reference.reference()["source"]


# ---------------------------------------------------------------- a results folder

def make_experiment(root):
    """Two arms × two seeds, evaluated on 777 (mean and sampled actions)."""
    for seed, base, arm in ((1, 0.5, 0.6), (2, 0.7, 0.9)):
        write_run(root, f"defaults-s{seed}", seed, [0.1, 0.3, base],
                  evals=[(777, "mean", base, 0.2), (777, "sample", base + 0.05, 0.1)])
        write_run(root, f"arm-s{seed}", seed, [0.2, 0.4, arm],
                  evals=[(777, "mean", arm, 0.1), (777, "sample", arm, 0.1)])
    (root / "arms.tsv").write_text("defaults\t\narm\t--set x=1\n")


def test_summary_reads_back_as_the_raw_runs_read(tmp_path):
    make_experiment(tmp_path)
    raw = analysis.load([str(tmp_path)])
    summary = analysis.write_summary(tmp_path)
    assert (tmp_path / "summary.json").exists() and (tmp_path / "config.toml").exists()
    assert len(summary["runs"]) == 4
    # Every run's config keys that differ from the base run's are kept.
    assert summary["runs"][0]["config"] == {}
    assert {r["name"]: r["config"].get("run.seed") for r in summary["runs"]}[
        "runs/arm-s2"] == 2
    for d in (tmp_path / "runs").iterdir():
        for f in list(d.rglob("*"))[::-1]:
            f.unlink() if f.is_file() else f.rmdir()
        d.rmdir()
    from_summary = analysis.load([str(tmp_path)])
    assert [r.data for r in from_summary] == [json.loads(json.dumps(r.data)) for r in raw]
    text = tables.summary_table(from_summary, by="arm", eval_seed=777)
    assert "| intersection | defaults | 1, 2 | 0.60 ± 1.27 |" in text
    paired = tables.paired_table(from_summary, "defaults", by="arm", eval_seed=777, each=True)
    # arm − defaults, same seed: +0.1 and +0.2 in training and with the mean action.
    row = next(l for l in paired.splitlines() if "arm − defaults" in l)
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2] == "2" and cells[3] == f"+0.15 ± {12.7062 * 0.05:.2f} (+0.10, +0.20)"
    marks = tables.marks_table(from_summary, [500_000, 750_000], by="arm")
    assert "| intersection | arm | 0.40 ± 0.00 | 0.75 ± 1.91 |" in marks


def test_the_command_line_tables_report_and_figures(tmp_path):
    make_experiment(tmp_path / "exp")
    env = {"PYTHONPATH": str(PYTHON)}
    run = lambda *args: subprocess.run([sys.executable, "-m", "junction.analysis", *args],
                                       check=True, capture_output=True, text=True, env=env)
    out = run("tables", str(tmp_path / "exp"), "--group-by-dir", "--baseline", "defaults",
              "--eval-seed", "777").stdout
    assert "arm − defaults" in out and "### Every run" in out
    run("report", str(tmp_path / "exp"), "--group-by-dir", "--out", str(tmp_path / "report"))
    report = (tmp_path / "report" / "report.md").read_text()
    assert "## Table 1 — intersection" in report and "Success rate (MetaDrive)" in report
    figures = sorted((tmp_path / "report" / "figures").glob("*.svg"))
    # The stored curves' figures, and from the run directories one per training-window
    # metric they log (success.svg and crash.svg already show MetaDrive's window).
    assert {f.stem for f in figures} == {"crash", "success", "success-smoothed",
                                         "success_rate", "length_mean"}
    for f in figures:
        root = ET.fromstring(f.read_text())  # well-formed SVG
        assert root.tag.endswith("svg") and len(f.read_bytes()) < 30_000
    run("summarize", str(tmp_path / "exp"), "--group-by-dir")
    assert (tmp_path / "exp" / "figures" / "success.svg").exists()
    summary = json.loads((tmp_path / "exp" / "summary.json").read_text())
    assert summary["format"] == "junction-summary/1" and not math.isnan(
        summary["runs"][0]["final"]["wall_s"])


def test_the_cross_simulator_table_takes_its_interval_over_training_seeds(tmp_path):
    twin, metadrive = "intersection-metadrive", "intersection-on-metadrive"
    # Three twin-trained seeds, each evaluated at home and in MetaDrive on seed 1000, plus a
    # validation evaluation (seed 777) and a sampled one the table must leave out.
    for seed, home, away in [(1, 0.5, 0.3), (2, 0.6, 0.4), (3, 0.7, 0.5)]:
        run = write_run(tmp_path, f"twin-s{seed}", seed, [0.2, 0.4], scene=twin,
                        evals=[(777, "mean", 0.9, 0.05), (1000, "mean", home, 0.2),
                               (1000, "sample", 0.95, 0.0)])
        write_eval(run / "eval", metadrive, 1000, "mean", away, 0.3 + 0.1 * seed)
    records = analysis.load([str(tmp_path)])
    assert tables.has_cross_sim(records)
    rows = {tuple(c.strip() for c in line.strip("|").split("|"))[:2]:
            [c.strip() for c in line.strip("|").split("|")]
            for line in tables.cross_sim_table(records, 1000).splitlines()[2:]}
    assert set(rows) == {(twin, twin), (twin, metadrive)}
    half = 4.3027 * 0.1 / math.sqrt(3)  # t(0.975, 2 df) × sd 0.1 / sqrt(3 seeds)
    home = rows[(twin, twin)]
    assert home[2:5] == ["3", "36", f"0.60 ± {half:.2f}"]
    assert home[7] == "1: 0.50 [0.40, 0.60]; 2: 0.60 [0.50, 0.70]; 3: 0.70 [0.60, 0.80]"
    away = rows[(twin, metadrive)]
    assert away[4:6] == [f"0.40 ± {half:.2f}", f"0.50 ± {half:.2f}"]
    # A run evaluated only at home has no cross-simulator cell to show.
    alone = tmp_path / "alone"
    write_run(alone, "twin-s1", 1, [0.2], scene=twin, evals=[(1000, "mean", 0.5, 0.2)])
    assert not tables.has_cross_sim(analysis.load([str(alone)]))


# ---------------------------------------------------------------- RESULTS.md

def test_every_table_of_results_md_is_what_its_command_prints():
    """Each table RESULTS.md prints below a `python -m junction.analysis` command is that
    command's output from the summaries in results/ (results-md prints them all)."""
    from junction.analysis import cli, results_md
    page = PYTHON.parent / "RESULTS.md"
    found = results_md.commands(page.read_text())
    assert len(found) >= 5, "RESULTS.md names the commands of its tables"
    for command, argv, rows in found:
        assert rows, f"no table follows {command}"
        printed = results_md.run(argv, cli.main).splitlines()
        missing = [row for row in rows if row not in printed]
        assert not missing, f"{command}\nprints other rows than RESULTS.md's:\n" + "\n".join(
            missing[:5])


# ---------------------------------------------------------------- time to success

def tts_line(seed, reach_07, reach_08, steps, success, crash, sampled=None):
    line = {"bench": "time_to_success", "seed": seed, "threshold": 0.8,
            "seconds_to_threshold_20": reach_08, "seconds_to_threshold_100": None,
            "reach_20": {"0.7": [reach_07, 1] if reach_07 else None},
            "reach_100": {"0.7": None}, "agent_steps": steps,
            "agent_steps_per_s": steps / 300, "final_success_20": success,
            "eval_success": {"value": success}, "eval_crash": {"value": crash},
            "eval_out_of_road": {"value": 0.0}}
    if sampled is not None:
        line |= {"eval_timeout": {"value": 1 - success - crash},
                 "eval_sampled_success": {"value": sampled}, "eval_sampled_crash": {"value": crash}}
    return line


def test_the_time_to_success_table_rows_a_file_per_setting_over_its_seeds(tmp_path):
    from junction.analysis import time_to_success
    f = tmp_path / "fast-300s.jsonl"
    lines = [tts_line(2, 90.0, None, 9_000_000, 0.8, 0.1),
             tts_line(1, 80.4, 250.0, 6_000_000, 0.7, 0.2),
             {"bench": "time_to_success_summary"}]
    f.write_text("\n".join(json.dumps(l) for l in lines) + "\n")
    header, rule, row = time_to_success.table([str(f)]).splitlines()
    assert "≥ 0.7 at" in header and "≥ 0.8" in header and rule.count("---") == 13
    cells = [c.strip() for c in row.strip("|").split("|")]
    # Seeds in order; 25,000 ± t(1)·5,000/√2·√2 agent-steps/s; seed 2 never reached 0.8.
    assert cells[:4] == ["fast-300s", "1, 2", "25,000 ± 63,531", "6.0–9.0 M"]
    assert cells[4] == "80 / 90 (never / never)"
    assert cells[5] == "1/2 seeds: 250 / never s"
    assert cells[7] == "0.750 ± 0.635" and cells[8] == "0.150 ± 0.635"
    # Files written before the timeout and the sampled evaluation were measured: dashes.
    assert cells[10:] == ["–", "–", "–"]
    f.write_text("\n".join(json.dumps(l) for l in [tts_line(1, 80.0, None, 6e6, 0.7, 0.1, 0.84),
                                                   tts_line(2, 90.0, None, 9e6, 0.7, 0.1, 0.86)]))
    cells = [c.strip() for c in time_to_success.table([str(f)]).splitlines()[2].strip("|").split("|")]
    assert cells[10:] == ["0.200 ± 0.000", "0.850 ± 0.127", "0.100 ± 0.000"]
    with pytest.raises(ValueError, match="no time_to_success line"):
        (tmp_path / "empty.jsonl").write_text(json.dumps(lines[2]) + "\n")
        time_to_success.table([str(tmp_path / "empty.jsonl")])
