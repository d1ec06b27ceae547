"""`python -m junction.analysis report` on the fixed runs in tests/fixtures/report-runs (2
methods × 2 scenes × 2 seeds, evaluations for the intersection runs only, one sampled-action
evaluation beside ippo s1's that the tables must leave out, ippo s1 evaluated on a second
evaluation seed (the same numbers), one unreadable run, one run with a line cut short): the
table's numbers, the sources, time to success, and figures that are real SVG pictures: what
the learner's Rust report was tested for (tests/tests/report.rs and its module's unit tests)
before the report moved here; run with the system python3, as the scripts run it."""

import json
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path
from types import SimpleNamespace

import pytest

PYTHON = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(PYTHON))

from junction.analysis import tables, variant_name  # noqa: E402
from junction.analysis.figures import window_band  # noqa: E402
from junction.analysis.record import RunRecord, records_from_dirs  # noqa: E402

FIXTURES = PYTHON.parent / "tests" / "fixtures" / "report-runs"
PYTHON3 = shutil.which("python3") or sys.executable
SVG = "{http://www.w3.org/2000/svg}"


def run_report(out, *extra, check=True):
    """The command as the scripts run it; (report.md, summary.json) when it succeeded."""
    done = subprocess.run(
        [PYTHON3, "-m", "junction.analysis", "report", "--methods", "ippo,cl",
         "--success-threshold", "0.5", *extra, str(FIXTURES), "--out", str(out)],
        capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(PYTHON)})
    if not check:
        return done
    assert done.returncode == 0, f"report failed:\n{done.stderr}"
    return ((out / "report.md").read_text(),
            json.loads((out / "summary.json").read_text()))


def row(markdown, scene, label):
    """The cells of the table row starting with `| {label}` in the section of `scene`: the
    row of exactly that metric ("Success rate ↑", not "Success rate (MetaDrive) ↑"), else the
    first whose label starts with it."""
    section = next((s for s in markdown.split("## ") if s.startswith(f"Table 1 — {scene}")),
                   None)
    assert section is not None, f"no table for {scene}:\n{markdown}"
    lines = section.splitlines()
    line = next((l for l in lines if any(l.startswith(f"| {label}{a}") for a in (" ↑", " ↓"))),
                None) or next((l for l in lines if l.startswith(f"| {label}")), None)
    assert line is not None, f"no row {label!r} for {scene}:\n{section}"
    return [c.strip() for c in line.strip("|").split("|")]


def test_table_numbers_come_from_evaluations_else_the_last_training_window(tmp_path):
    markdown, summary = run_report(tmp_path / "report")

    # Intersection: every seed was evaluated (ippo s1's sampled evaluation, success 0, is not
    # counted). Success 0.6 / 0.8 (ippo) and 0.7 / 0.9 (cl): means 0.7 and 0.8, half-width
    # t(1)·s/√2 = 12.7062 · 0.1 = 1.271; cl is better.
    assert row(markdown, "intersection", "Success rate") == [
        "Success rate ↑", "0.7000 ± 1.271", "**0.8000 ± 1.271**"]
    # Agents succeeding per 300 steps only exist in evaluations: 10 × 0.7 and 10 × 0.8.
    assert row(markdown, "intersection", "Agents succeeding")[1:] == [
        "7.000 ± 12.71", "**8.000 ± 12.71**"]
    assert row(markdown, "intersection", "Source")[1:] == ["eval (seeds 1, 2)", "eval (seed 1)"]
    # Equal values everywhere: nothing is bold.
    assert row(markdown, "intersection", "Episode length (max)")[1:] == ["260.0 ± 0",
                                                                          "260.0 ± 0"]

    # Roundabout: no evaluations, so the last training window: success 0.4 / 0.6 (ippo),
    # 0.3 / 0.5 (cl); collisions per second 0.5 · 0.6 · (1 − success).
    assert row(markdown, "roundabout", "Success rate")[1:] == ["**0.5000 ± 1.271**",
                                                               "0.4000 ± 1.271"]
    assert row(markdown, "roundabout", "Collision rate")[1:] == ["**0.1500 ± 0.3812**",
                                                                 "0.1800 ± 0.3812"]
    assert row(markdown, "roundabout", "Agents succeeding")[1:] == ["—", "—"]
    assert row(markdown, "roundabout", "Source")[1:] == ["training", "training"]
    assert row(markdown, "roundabout", "Seeds")[1:] == ["1, 2", "1, 2"]

    # How the evaluated episodes ended: ippo's evaluations count endings (rear-ends 30 and
    # 10 of 200: 0.1 ± 12.7062 · 0.1/√2), cl's do not; most frequent first, and no section
    # for the roundabout, which has no evaluations.
    parts = markdown.split("## How evaluation episodes ended")
    assert len(parts) > 1, f"no endings section:\n{markdown}"
    endings = parts[1]
    assert "| `crash/entry/rear_end` | 0.1000 ± 0.6353 | — |" in endings, endings
    order = [l[len("| `"):].split("`")[0] for l in endings.splitlines() if l.startswith("| `")]
    assert order == ["success/exit", "crash/entry/rear_end", "out_of_road/junction",
                     "crash/junction/crossing", "timeout/entry"]
    assert "### intersection" in endings and "### roundabout" not in endings

    # The unreadable run is named; the line cut short is counted, the rest of its run kept.
    assert "report-runs/broken`" in markdown, markdown
    assert "1 unreadable progress line" in markdown, markdown
    assert len(summary["runs"]) == 8
    assert len(summary["skipped"]) == 1
    assert summary["methods"] == ["ippo", "cl"]

    # Time to a 0.5 success window (≥ 100 episodes; these runs predate MetaDrive's window, so
    # the agent-episode window): ippo on the intersection ends at 0.5 (seed 1, line 5 at
    # 10,100 agent-steps, 50 s) and 0.7 (seed 2: 0.56 at line 4, 8,200, 40 s): means 9,150
    # agent-steps and 45 s.
    group = next(g for g in summary["groups"]
                 if g["scene"] == "intersection" and g["group"] == "ippo")
    reach = group["reach"]["0.5"]
    assert reach["reached_seeds"] == 2
    assert reach["mean_reach"]["agent_steps"] == 9150
    assert reach["mean_reach"]["elapsed_s"] == 45.0
    assert "| intersection | IPPO | 2/2: 9.2k, 45 s |" in markdown, markdown
    assert "| roundabout | CL | 1/2: 10.2k, 50 s |" in markdown, markdown


def test_time_to_success_takes_its_thresholds_and_window_size(tmp_path):
    # Windows of 200 episodes or more: only the last line of each run counts; ippo seed 2
    # reaches 0.5 there (0.7 at 10,200, 50 s), seed 1 too (0.5 at 10,100).
    markdown, summary = run_report(tmp_path / "min200", "--min-window-episodes", "200")
    assert "| intersection | IPPO | 2/2: 10.2k, 50 s |" in markdown, markdown
    # Several thresholds: a column each; 0.75 is reached by no ippo seed on the intersection.
    markdown, summary = run_report(tmp_path / "several", "--success-threshold", "0.5,0.75")
    assert "| intersection | IPPO | 2/2: 9.2k, 45 s | 0/2 |" in markdown, markdown
    group = next(g for g in summary["groups"]
                 if g["scene"] == "intersection" and g["group"] == "ippo")
    assert group["reach"]["0.75"] == {"reached_seeds": 0, "mean_reach": None}
    assert summary["success_thresholds"] == [0.5, 0.75]

    # From a summary only the kept thresholds answer: another one is refused, not tabled as
    # never reached.
    summary_path = tmp_path / "several" / "summary.json"
    done = subprocess.run(
        [PYTHON3, "-m", "junction.analysis", "report", str(summary_path), "--out",
         str(tmp_path / "again"), "--success-threshold", "0.55"],
        capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(PYTHON)})
    assert done.returncode != 0 and "keeps first reaches" in done.stderr, done.stderr


def test_evaluation_seeds_can_be_picked_and_a_group_short_of_them_falls_back_to_training(
        tmp_path):
    markdown, _ = run_report(tmp_path / "seed-1", "--eval-seeds", "1")
    assert row(markdown, "intersection", "Source")[1:] == ["eval (seed 1)", "eval (seed 1)"]
    assert row(markdown, "intersection", "Success rate")[1:] == ["0.7000 ± 1.271",
                                                                 "**0.8000 ± 1.271**"]
    # Only ippo s1 was evaluated on seed 2: no column has it for every seed.
    markdown, _ = run_report(tmp_path / "seed-2", "--eval-seeds", "2")
    assert row(markdown, "intersection", "Source")[1:] == ["training", "training"]


#: The training-window metrics the fixtures log (they predate MetaDrive's per-scene-episode
#: window, so no scene_success_rate or scene_crash_rate figure), in the report's order.
WINDOW_METRICS = ["success_rate", "collision_rate", "crash_rate", "out_of_road_rate",
                  "accel_mean", "accel_max", "reward_mean", "reward_max", "length_mean",
                  "length_max"]


def test_figures_are_real_svg_pictures(tmp_path):
    out = tmp_path / "report"
    markdown, summary = run_report(out)
    figures = summary["figures"]
    assert figures == [f"figures/{k}.svg" for k in WINDOW_METRICS], figures
    assert sorted(p.name for p in (out / "figures").iterdir()) == sorted(
        f"{k}.svg" for k in WINDOW_METRICS)
    for name in figures:
        assert f"]({name})" in markdown, f"report.md links {name}"
        text = (out / name).read_text()
        assert text.startswith("<svg"), name
        root = ET.fromstring(text)  # well-formed
        assert root.tag == f"{SVG}svg" and (root.get("width"), root.get("height")) == (
            "960", "400"), name
        for word in ("intersection", "roundabout", "IPPO", "CL", "agent-steps", "<polyline"):
            assert word in text, f"{name} lacks {word}"
        # One line per method and scene, each over the agent-steps every seed covers (2,200
        # to 10,100) at 120 points, its range over seeds shaded; both method colours
        # (Okabe–Ito blue and vermillion).
        lines = root.findall(f"{SVG}polyline")
        assert len(lines) == 4, name
        assert all(len(l.get("points").split()) == 120 for l in lines), name
        assert len(root.findall(f"{SVG}polygon")) == 4, name
        for colour in ("#0072b2", "#d55e00"):
            assert f'stroke="{colour}"' in text, f"{name} lacks {colour}"


def test_an_unreadable_run_alone_is_an_error_that_names_it(tmp_path):
    done = subprocess.run(
        [PYTHON3, "-m", "junction.analysis", "report", str(FIXTURES / "broken"), "--out",
         str(tmp_path / "report")],
        capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(PYTHON)})
    assert done.returncode != 0
    assert "broken" in done.stderr and "no readable training run" in done.stderr, done.stderr


# ------------------------------------------------ what the report module's unit tests checked

def raw_record(seed, lines, method="ippo", scene="intersection"):
    """A run record whose progress lines are `lines` (as made from a run directory)."""
    return RunRecord({"name": f"{method}-s{seed}", "method": method, "scene": scene,
                      "seed": seed, "final": {"agent_steps": lines[-1]["agent_steps"]}},
                     raw=SimpleNamespace(lines=lines, clock=[0.0] * len(lines)))


def window_line(agent_steps, episodes, success_rate, elapsed_s=0.0):
    return {"agent_steps": agent_steps, "elapsed_s": elapsed_s,
            "window": {"episodes": episodes, "success_rate": success_rate}}


def test_a_window_band_spans_where_every_seed_has_data():
    # Seed 1 goes 0.1 → 1 over x = 10..100 (its line at x = 0 has no episodes yet and is
    # left out); seed 2 goes 0 → 0.7 over x = 0..50. Both cover 10..50.
    a = raw_record(1, [window_line(0, 0, 0.7), window_line(10, 5, 0.1),
                       window_line(100, 9, 1.0)])
    b = raw_record(2, [window_line(0, 4, 0.0), window_line(50, 8, 0.7)])
    band = window_band([a, b], "success_rate", 3)
    assert [p[0] for p in band] == [10, 30, 50]
    # x = 30: seed 1 at 0.1 + 0.9·20/90 = 0.3, seed 2 at 0.7·30/50 = 0.42.
    x, mean, low, high = band[1]
    assert abs(mean - 0.36) < 1e-12 and abs(low - 0.3) < 1e-12 and abs(high - 0.42) < 1e-12
    # x = 50: seed 1 at 0.5, seed 2 at 0.7.
    assert abs(band[2][1] - 0.6) < 1e-12
    single = window_band([a], "success_rate", 4)
    assert (single[0][0], single[3][0], single[3][1]) == (10, 100, 1.0)
    assert window_band([a], "successes_per_300", 5) == []  # training does not track it
    disjoint = raw_record(3, [window_line(200, 5, 0.5), window_line(300, 5, 0.5)])
    assert window_band([b, disjoint], "success_rate", 5) == []


def test_time_to_success_needs_a_full_enough_window(tmp_path):
    r = records_from_dirs([write_run(tmp_path / "ippo-s1", 1, [
        window_line(100, 3, 1.0, 1.0),  # too few episodes to count
        window_line(200, 50, 0.6, 2.0), window_line(300, 60, 0.85, 3.0),
        window_line(400, 60, 0.8, 4.0)])])[0]
    assert r.reach(0.8, min_episodes=50) == {"agent_steps": 300, "env_steps": None,
                                             "wall_s": 3.0}
    assert r.reach(0.9, min_episodes=50) is None
    assert r.reach(0.8, min_episodes=1)["agent_steps"] == 100
    # Resumed after 2 s: the second process's clock counts on from the first's.
    resumed = records_from_dirs([write_run(tmp_path / "ippo-s2", 2, [
        window_line(100, 50, 0.6, 1.0), window_line(200, 50, 0.7, 2.0),
        window_line(300, 60, 0.85, 0.5)])])[0]
    assert resumed.reach(0.8, min_episodes=50)["wall_s"] == 2.5
    # The summary keeps the first reaches at 100 episodes: the record read back answers the
    # same for its thresholds, and nothing for another window size.
    kept = RunRecord(resumed.data)
    assert kept.reach(0.8) == resumed.reach(0.8) is None  # 60 episodes < 100
    assert kept.reaches_kept(0.8) and not kept.reaches_kept(0.85)
    assert not kept.reaches_kept(0.8, min_episodes=50) and resumed.reaches_kept(0.85, 50)


def write_run(directory, seed, lines, method="ippo"):
    """A run directory of `method` on the intersection whose progress lines are `lines`."""
    directory.mkdir()
    (directory / "config.toml").write_text(
        f'[run]\nseed = {seed}\n[scenario]\nname = "intersection"\n[learner]\n'
        f'algo = "{method}"\n')
    (directory / "progress.jsonl").write_text("".join(json.dumps(l) + "\n" for l in lines))
    return directory


def test_the_lcf_table_averages_each_seeds_last_angle_per_bucket(tmp_path):
    # Seed 1's last line has no φ (a restarted learner before its first update): its
    # previous line counts. Seed 2 never saw an agent with 6+ neighbours.
    dirs = []
    for seed, lcfs in ((1, [(1.0, {"0": 1.0}), (20.0, {"0": 10.0, "6+": 60.0}), None]),
                       (2, [(40.0, {"0": 30.0})])):
        lines = [{"agent_steps": 10 * (i + 1), "elapsed_s": float(i)} | (
            {} if l is None else {"lcf": {"mean_deg": l[0], "std_deg": 5.0,
                                          "phi_deg_by_neighbours": l[1]}})
            for i, l in enumerate(lcfs)]
        dirs.append(write_run(tmp_path / f"dynamic-lcf-s{seed}", seed, lines, "dynamic-lcf"))
    records = records_from_dirs(dirs)
    text = tables.lcf_table(records)
    assert "| scene | method | all agents | 0 neighbours | 6+ neighbours |" in text, text
    # All agents: 20 and 40 → 30; bucket 0: 10 and 30 → 20; 6+: seed 1's 60 alone.
    cells = [c.strip() for c in text.splitlines()[2].strip("|").split("|")]
    assert cells[:3] == ["intersection", "dynamic LCF", tables.fmt([20.0, 40.0], 1)]
    assert cells[2].startswith("30.0 ± ") and cells[3].startswith("20.0 ± "), cells
    assert cells[3] == tables.fmt([10.0, 30.0], 1) and cells[4] == "60.0", cells
    # An angle of 0 throughout is not a learned one: no table.
    for record in records:
        record.data["final"]["lcf"] = {"mean_deg": 0.0, "std_deg": 0.0,
                                       "by_neighbours": {"0": 0.0, "1-2": 0.0}}
    assert tables.lcf_table(records) == ""


def test_order_cells_and_variant_names():
    # The preferred order first (names not found dropped), then the others as found.
    assert tables.ordered(["cl", "copo", "ippo"], ["ippo", "cl", "zeta", "ccppo-mf"]) == [
        "cl", "ippo", "zeta", "ccppo-mf"]
    assert tables.estimate_cell([0.2]) == "0.2000 (1 seed)"
    assert tables.estimate_cell([None]) == "—"
    assert variant_name("no-grad-clip-s12") == "no-grad-clip"
    assert variant_name("tyres-s") == "tyres-s" and variant_name("plain") == "plain"


@pytest.mark.parametrize("higher,expected", [(True, [False, True]), (False, [True, False])])
def test_the_best_mean_of_a_row_is_bold_in_its_direction(higher, expected):
    # Success (higher is better) and crash (lower is better) from the last training window.
    def run(seed, method, success):
        return RunRecord({"name": f"{method}-s{seed}", "method": method, "scene": "x",
                          "seed": seed, "final": {"agent_steps": 1, "wall_s": 1.0,
                                                  "window": {"success_rate": success,
                                                             "crash_rate": success}}})
    text = tables.table1([run(1, "ippo", 0.2), run(1, "cl", 0.5)], "x", order=["ippo", "cl"])
    label = "Success rate ↑" if higher else "Crash rate ↓"
    cells = next(l for l in text.splitlines() if l.startswith(f"| {label}")).split("|")[2:4]
    assert [c.strip().startswith("**") for c in cells] == expected, text
