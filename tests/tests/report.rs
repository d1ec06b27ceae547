//! `learner report` on the fixed runs in tests/fixtures/report-runs (2 methods × 2 scenes × 2
//! seeds, evaluations for the intersection runs only, one sampled-action evaluation beside
//! ippo s1's that the tables must leave out, ippo s1 evaluated on a second evaluation seed
//! (the same numbers), one unreadable run, one run with a line cut short): the table's
//! numbers, the sources, and figures that are real pictures.

use std::path::Path;
use std::process::Command;

use junction_tests::{TempDir, bin, workspace_root};

fn report(out: &Path, extra_args: &[&str]) -> (String, serde_json::Value) {
    let fixtures = workspace_root().join("tests/fixtures/report-runs");
    let output = Command::new(bin("learner"))
        .args([
            "report",
            "--methods",
            "ippo,cl",
            "--success-threshold",
            "0.5",
        ])
        .args(extra_args)
        .arg(&fixtures)
        .arg("--out")
        .arg(out)
        .output()
        .expect("run learner report");
    assert!(
        output.status.success(),
        "learner report failed:\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let markdown = std::fs::read_to_string(out.join("report.md")).expect("report.md");
    let summary = std::fs::read_to_string(out.join("summary.json")).expect("summary.json");
    (
        markdown,
        serde_json::from_str(&summary).expect("summary.json is JSON"),
    )
}

/// The table row starting with `| {label}` in the section of `scene`.
fn row<'a>(markdown: &'a str, scene: &str, label: &str) -> Vec<&'a str> {
    let section = markdown
        .split("## ")
        .find(|s| s.starts_with(&format!("Table 1 — {scene}")))
        .unwrap_or_else(|| panic!("no table for {scene}:\n{markdown}"));
    // The row of exactly that metric ("Success rate ↑", not "Success rate (MetaDrive) ↑"),
    // else the first whose label starts with it.
    let exact = |l: &&str| {
        [" ↑", " ↓"]
            .iter()
            .any(|a| l.starts_with(&format!("| {label}{a}")))
    };
    let line = section
        .lines()
        .find(exact)
        .or_else(|| {
            section
                .lines()
                .find(|l| l.starts_with(&format!("| {label}")))
        })
        .unwrap_or_else(|| panic!("no row {label:?} for {scene}:\n{section}"));
    line.trim_matches('|').split('|').map(str::trim).collect()
}

#[test]
fn table_numbers_come_from_evaluations_else_the_last_training_window() {
    let dir = TempDir::new("report");
    let (markdown, summary) = report(dir.path(), &[]);

    // Intersection: every seed was evaluated (ippo s1's sampled evaluation, success 0, is not
    // counted). Success 0.6 / 0.8 (ippo) and 0.7 / 0.9 (cl):
    // means 0.7 and 0.8, half-width t(1)·s/√2 = 12.7062 · 0.1 = 1.271; cl is better.
    assert_eq!(
        row(&markdown, "intersection", "Success rate"),
        ["Success rate ↑", "0.7000 ± 1.271", "**0.8000 ± 1.271**"]
    );
    // Agents succeeding per 300 steps only exist in evaluations: 10 × 0.7 and 10 × 0.8.
    assert_eq!(
        row(&markdown, "intersection", "Agents succeeding")[1..],
        ["7.000 ± 12.71", "**8.000 ± 12.71**"]
    );
    assert_eq!(
        row(&markdown, "intersection", "Source")[1..],
        ["eval (seeds 1, 2)", "eval (seed 1)"]
    );
    // Equal values everywhere: nothing is bold.
    assert_eq!(
        row(&markdown, "intersection", "Episode length (max)")[1..],
        ["260.0 ± 0", "260.0 ± 0"]
    );

    // Roundabout: no evaluations, so the last training window: success 0.4 / 0.6 (ippo),
    // 0.3 / 0.5 (cl); collisions per second 0.5 · 0.6 · (1 − success).
    assert_eq!(
        row(&markdown, "roundabout", "Success rate")[1..],
        ["**0.5000 ± 1.271**", "0.4000 ± 1.271"]
    );
    assert_eq!(
        row(&markdown, "roundabout", "Collision rate")[1..],
        ["**0.1500 ± 0.3812**", "0.1800 ± 0.3812"]
    );
    assert_eq!(
        row(&markdown, "roundabout", "Agents succeeding")[1..],
        ["—", "—"]
    );
    assert_eq!(
        row(&markdown, "roundabout", "Source")[1..],
        ["training", "training"]
    );
    assert_eq!(row(&markdown, "roundabout", "Seeds")[1..], ["1, 2", "1, 2"]);

    // How the evaluated episodes ended: ippo's evaluations count endings (rear-ends 30 and
    // 10 of 200: 0.1 ± 12.7062 · 0.1/√2), cl's do not; most frequent first, and no section
    // for the roundabout, which has no evaluations.
    let endings = markdown
        .split("## How evaluation episodes ended")
        .nth(1)
        .unwrap_or_else(|| panic!("no endings section:\n{markdown}"));
    assert!(
        endings.contains("| `crash/entry/rear_end` | 0.1000 ± 0.6353 | — |"),
        "{endings}"
    );
    let order: Vec<&str> = endings
        .lines()
        .filter_map(|l| l.strip_prefix("| `")?.split('`').next())
        .collect();
    assert_eq!(
        order,
        [
            "success/exit",
            "crash/entry/rear_end",
            "out_of_road/junction",
            "crash/junction/crossing",
            "timeout/entry"
        ]
    );
    assert!(endings.contains("### intersection") && !endings.contains("### roundabout"));

    // The unreadable run is named; the line cut short is counted, the rest of its run kept.
    assert!(markdown.contains("report-runs/broken`"), "{markdown}");
    assert!(
        markdown.contains("1 unreadable progress line"),
        "{markdown}"
    );
    assert_eq!(summary["runs"].as_array().unwrap().len(), 8);
    assert_eq!(summary["skipped"].as_array().unwrap().len(), 1);
    assert_eq!(summary["methods"], serde_json::json!(["ippo", "cl"]));

    // Time to a 0.5 success window (≥ 100 episodes): ippo on the intersection ends at 0.5
    // (seed 1, line 5 at 10,100 agent-steps, 50 s) and 0.7 (seed 2: 0.56 at line 4, 8,200,
    // 40 s): means 9,150 agent-steps and 45 s.
    let group = summary["groups"]
        .as_array()
        .unwrap()
        .iter()
        .find(|g| g["scene"] == "intersection" && g["method"] == "ippo")
        .unwrap();
    assert_eq!(group["reached_seeds"], 2);
    assert_eq!(group["mean_reach"]["agent_steps"], 9150);
    assert_eq!(group["mean_reach"]["elapsed_s"], 45.0);
    assert!(
        markdown.contains("| intersection | ippo | 2/2 | 9.2k | 45 |"),
        "{markdown}"
    );
    assert!(
        markdown.contains("| roundabout | cl | 1/2 | 10.2k | 50 |"),
        "{markdown}"
    );
}

#[test]
fn evaluation_seeds_can_be_picked_and_a_group_short_of_them_falls_back_to_training() {
    let picked = TempDir::new("report-eval-seed-1");
    let (markdown, _) = report(picked.path(), &["--eval-seeds", "1"]);
    assert_eq!(
        row(&markdown, "intersection", "Source")[1..],
        ["eval (seed 1)", "eval (seed 1)"]
    );
    assert_eq!(
        row(&markdown, "intersection", "Success rate")[1..],
        ["0.7000 ± 1.271", "**0.8000 ± 1.271**"]
    );
    // Only ippo s1 was evaluated on seed 2: no column has it for every seed.
    let short = TempDir::new("report-eval-seed-2");
    let (markdown, _) = report(short.path(), &["--eval-seeds", "2"]);
    assert_eq!(
        row(&markdown, "intersection", "Source")[1..],
        ["training", "training"]
    );
}

#[test]
fn figures_are_real_pictures_in_png_and_svg() {
    let dir = TempDir::new("report-figures");
    let (markdown, summary) = report(dir.path(), &[]);
    let figures = summary["figures"].as_array().unwrap();
    assert_eq!(figures.len(), 24, "12 metrics × PNG and SVG");
    for figure in figures {
        let name = figure.as_str().unwrap();
        assert!(markdown.contains(name), "report.md links {name}");
        let path = dir.path().join(name);
        if name.ends_with(".png") {
            let decoder =
                png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
            let mut reader = decoder.read_info().expect("a PNG");
            let mut pixels = vec![0; reader.output_buffer_size().unwrap()];
            let info = reader.next_frame(&mut pixels).expect("PNG pixels");
            assert_eq!((info.width, info.height), (1200, 500), "{name}");
            let colours: std::collections::HashSet<&[u8]> =
                pixels[..info.buffer_size()].chunks(3).collect();
            // Background, grid, text, two method colours and their bands at least.
            assert!(colours.len() > 20, "{name} has {} colours", colours.len());
            // Both method colours appear (Okabe–Ito blue and vermillion).
            for colour in [[0u8, 114, 178], [213, 94, 0]] {
                assert!(colours.contains(&colour[..]), "{name} lacks {colour:?}");
            }
        } else {
            let svg = std::fs::read_to_string(&path).unwrap();
            assert!(svg.starts_with("<svg"), "{name}");
            for text in [
                "intersection",
                "roundabout",
                "ippo",
                "agent-steps",
                "<polyline",
            ] {
                assert!(svg.contains(text), "{name} lacks {text}");
            }
        }
    }
}
