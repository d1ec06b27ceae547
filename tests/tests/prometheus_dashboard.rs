//! The metrics and the Grafana dashboard against a real Prometheus server (Debian's
//! `prometheus` package, installed by scripts/setup.sh --test): a real learner and actor train
//! briefly, Prometheus scrapes both, every metric family passes `promtool check metrics`, and
//! every query of every dashboard panel returns data through Prometheus' HTTP API.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use junction_tests::{
    Process, QUICK_RUN, TempDir, free_port, http_get, metric_sum, scrape, start_actor_with_metrics,
    start_learner, wait_until, workspace_root,
};

/// What Grafana would put in for the dashboard's variables.
const RATE_INTERVAL: &str = "20s";
const ALL_SCENARIOS: &str = ".+";

/// Percent-encodes a query-string value (RFC 3986 unreserved characters pass).
fn url_encode(value: &str) -> String {
    value
        .bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => {
                (b as char).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}

/// GET over HTTP/1.0, so the body comes unchunked; returns the body of any status.
fn http10_get(addr: &str, path: &str) -> std::io::Result<String> {
    let mut stream = TcpStream::connect(addr)?;
    stream.set_read_timeout(Some(Duration::from_secs(10)))?;
    write!(stream, "GET {path} HTTP/1.0\r\nHost: {addr}\r\n\r\n")?;
    let mut response = String::new();
    stream.read_to_string(&mut response)?;
    Ok(response
        .split_once("\r\n\r\n")
        .map(|(_, body)| body.to_string())
        .unwrap_or_default())
}

/// Evaluates an instant query; the number of series it returned, or Prometheus' error.
fn query(prometheus: &str, expr: &str) -> Result<usize, String> {
    let body = http10_get(
        prometheus,
        &format!("/api/v1/query?query={}", url_encode(expr)),
    )
    .map_err(|e| format!("request failed: {e}"))?;
    let reply: serde_json::Value =
        serde_json::from_str(&body).map_err(|e| format!("not JSON ({e}): {body}"))?;
    if reply["status"] != "success" {
        return Err(format!("{}: {}", reply["errorType"], reply["error"]));
    }
    Ok(reply["data"]["result"].as_array().map_or(0, Vec::len))
}

/// Every (panel title, PromQL) of the dashboard, with its variables filled in.
fn dashboard_queries(dashboard: &serde_json::Value) -> Vec<(String, String)> {
    let panels = dashboard["panels"].as_array().expect("dashboard panels");
    panels
        .iter()
        .flat_map(|panel| {
            let title = panel["title"].as_str().unwrap_or("?").to_string();
            panel["targets"]
                .as_array()
                .into_iter()
                .flatten()
                .filter_map(move |t| {
                    let expr = t["expr"]
                        .as_str()?
                        .replace("$__rate_interval", RATE_INTERVAL)
                        .replace("$scenario", ALL_SCENARIOS);
                    Some((title.clone(), expr))
                })
        })
        .collect()
}

fn promtool_check_metrics(exposition: &str) -> Result<(), String> {
    let mut child = Command::new("promtool")
        .args(["check", "metrics"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| format!("promtool not runnable (scripts/setup.sh --test installs it): {e}"))?;
    child
        .stdin
        .take()
        .expect("promtool stdin")
        .write_all(exposition.as_bytes())
        .map_err(|e| e.to_string())?;
    let out = child.wait_with_output().map_err(|e| e.to_string())?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ))
    }
}

#[test]
fn every_dashboard_panel_returns_data_from_a_real_prometheus() {
    let root = workspace_root();
    let dashboard: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(root.join("deploy/grafana/dashboards/junction.json"))
            .expect("dashboard file"),
    )
    .expect("dashboard JSON");
    let queries = dashboard_queries(&dashboard);
    assert!(queries.len() >= 20, "only {} queries", queries.len());
    // Grafana keys panels by id: a repeated one makes it drop or mix panels.
    let mut ids = std::collections::BTreeSet::new();
    for panel in dashboard["panels"].as_array().expect("dashboard panels") {
        let id = panel["id"].as_u64().expect("every panel has a numeric id");
        assert!(ids.insert(id), "panel id {id} is used twice");
    }

    let dir = TempDir::new("prometheus");
    let run_dir = dir.path().join("run");
    let (mut learner, endpoints) = start_learner(
        &run_dir,
        dir.path(),
        &[&["--max-seconds", "240"], QUICK_RUN].concat(),
    );
    let (actor, actor_metrics) = start_actor_with_metrics(&endpoints, dir.path());

    let prometheus_addr = format!("127.0.0.1:{}", free_port());
    let config = dir.path().join("prometheus.yml");
    std::fs::write(
        &config,
        format!(
            "global:\n  scrape_interval: 1s\n  evaluation_interval: 1s\n\
             rule_files:\n  - {rules}\n\
             scrape_configs:\n\
             \x20 - job_name: junction-learner\n    static_configs:\n      - targets: ['{learner}']\n\
             \x20 - job_name: junction-actor\n    static_configs:\n      - targets: ['{actor}']\n",
            rules = root.join("deploy/prometheus/alerts.yml").display(),
            learner = endpoints.metrics,
            actor = actor_metrics,
        ),
    )
    .expect("write prometheus.yml");
    let prometheus = Process::start(
        "prometheus",
        Path::new("prometheus"),
        &[
            format!("--config.file={}", config.display()),
            format!("--storage.tsdb.path={}", dir.path().join("tsdb").display()),
            format!("--web.listen-address={prometheus_addr}"),
        ],
        dir.path(),
    );
    let ready = wait_until(Duration::from_secs(60), || {
        http_get(&prometheus_addr, "/-/ready").is_ok()
    });
    assert!(ready, "prometheus not ready\n{}", prometheus.log_tail(30));

    // Training has published versions and finished episodes...
    let trained = wait_until(Duration::from_secs(150), || {
        let m = scrape(&endpoints.metrics);
        metric_sum(&m, "junction_learner_policy_version") >= 3.0
            && metric_sum(&m, "junction_learner_episodes_total") > 0.0
    });
    assert!(
        trained,
        "no training progress\n{}\n{}",
        learner.log_tail(30),
        actor.log_tail(30)
    );
    // ...and Prometheus has scraped enough of it for every rate() window.
    let scraped = wait_until(Duration::from_secs(60), || {
        query(
            &prometheus_addr,
            &format!("count_over_time(junction_learner_policy_version[{RATE_INTERVAL}]) >= 10"),
        ) == Ok(1)
    });
    assert!(
        scraped,
        "prometheus did not scrape the learner\n{}",
        prometheus.log_tail(30)
    );

    for (who, addr) in [("learner", &endpoints.metrics), ("actor", &actor_metrics)] {
        let exposition = http_get(addr, "/metrics").expect("scrape");
        if let Err(problems) = promtool_check_metrics(&exposition) {
            panic!("promtool check metrics on the {who}'s /metrics:\n{problems}");
        }
    }

    // Every panel, while the run is still going (a finished run has no rates).
    let empty: Vec<String> = queries
        .iter()
        .filter_map(|(title, expr)| match query(&prometheus_addr, expr) {
            Ok(series) if series > 0 => None,
            Ok(_) => Some(format!("{title}: no data for {expr}")),
            Err(e) => Some(format!("{title}: {expr} failed: {e}")),
        })
        .collect();
    assert!(
        empty.is_empty(),
        "{} of {} panel queries returned nothing:\n{}",
        empty.len(),
        queries.len(),
        empty.join("\n")
    );
    // The alert rules loaded and evaluate (none of them should fire on a healthy run).
    let rules = http10_get(&prometheus_addr, "/api/v1/rules").expect("rules");
    let rules: serde_json::Value = serde_json::from_str(&rules).expect("rules JSON");
    let groups = rules["data"]["groups"]
        .as_array()
        .cloned()
        .unwrap_or_default();
    let alerts: Vec<&serde_json::Value> = groups
        .iter()
        .flat_map(|g| g["rules"].as_array().into_iter().flatten())
        .collect();
    assert!(alerts.len() >= 5, "alert rules not loaded: {rules}");
    for alert in alerts {
        assert_eq!(alert["health"], "ok", "rule does not evaluate: {alert}");
        assert_ne!(
            alert["state"], "firing",
            "alert fires on a healthy run: {alert}"
        );
    }

    learner.signal(libc::SIGTERM);
    let status = learner.wait_exit(Duration::from_secs(60));
    assert!(
        status.is_some_and(|s| s.success()),
        "learner did not stop cleanly: {status:?}\n{}",
        learner.log_tail(20)
    );
}
