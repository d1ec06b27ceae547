//! The deployment files under deploy/: Prometheus configurations and alert rules (promtool,
//! including the rules' unit tests), Kubernetes manifests (kubernetes-validate against the
//! strict schemas), the compose file, the run configuration shipped in the ConfigMap, and the
//! learner's resume-or-start wrappers. The Dockerfile is not built here (no Docker daemon).
//!
//! Tools: `promtool` (Debian's `prometheus` package) and `.venv/bin/kubernetes-validate`, both
//! installed by scripts/setup.sh --test; YAML is read with the venv's Python (PyYAML comes with
//! kubernetes-validate).

use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::Command;

use junction_tests::{TempDir, bin, workspace_root};
use serde_json::Value;

/// Kubernetes versions the manifests are validated against: an old and the newest schema set
/// kubernetes-validate ships.
const KUBERNETES_VERSIONS: [&str; 2] = ["1.30.0", "1.37.0"];

/// The manifests `kubectl apply -k deploy/k8s` applies (kustomization.yaml lists them).
const K8S_MANIFESTS: [&str; 5] = [
    "namespace.yaml",
    "configmap.yaml",
    "learner-service.yaml",
    "learner-statefulset.yaml",
    "actor-deployment.yaml",
];

fn deploy(relative: &str) -> PathBuf {
    workspace_root().join("deploy").join(relative)
}

fn venv_tool(name: &str) -> PathBuf {
    let path = workspace_root().join(".venv/bin").join(name);
    assert!(
        path.exists(),
        "{} is missing: run scripts/setup.sh --test",
        path.display()
    );
    path
}

/// Runs `command`; returns whether it succeeded and its stdout + stderr.
fn output(command: &mut Command) -> (bool, String) {
    let out = command
        .output()
        .unwrap_or_else(|e| panic!("cannot run {command:?} ({e}); run scripts/setup.sh --test"));
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

/// Runs `command`, failing the test with its output unless it succeeds.
fn run_ok(command: &mut Command) -> String {
    let (ok, text) = output(command);
    assert!(ok, "{command:?} failed:\n{text}");
    text
}

/// Every YAML document of `path`, as JSON (PyYAML; it also resolves `<<` merge keys).
fn yaml_documents(path: &Path) -> Vec<Value> {
    let mut command = Command::new(venv_tool("python"));
    command
        .arg("-c")
        .arg(
            "import json, sys, yaml\n\
             with open(sys.argv[1]) as f:\n    docs = list(yaml.safe_load_all(f))\n\
             sys.stdout.write(json.dumps(docs))",
        )
        .arg(path);
    let out = command
        .output()
        .unwrap_or_else(|e| panic!("cannot run {command:?} ({e}); run scripts/setup.sh --test"));
    assert!(
        out.status.success(),
        "{} is not valid YAML:\n{}",
        path.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice::<Vec<Value>>(&out.stdout)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .into_iter()
        .filter(|d| !d.is_null())
        .collect()
}

fn yaml(path: &Path) -> Value {
    let mut docs = yaml_documents(path);
    assert_eq!(
        docs.len(),
        1,
        "{}: expected one YAML document",
        path.display()
    );
    docs.remove(0)
}

fn strings(value: &Value) -> Vec<String> {
    value
        .as_array()
        .unwrap_or_else(|| panic!("expected a list, got {value}"))
        .iter()
        .map(|v| match v {
            Value::String(s) => s.clone(),
            other => other.to_string(),
        })
        .collect()
}

// --- Prometheus --------------------------------------------------------------------------------

#[test]
fn compose_prometheus_config_is_valid() {
    let out = run_ok(
        Command::new("promtool")
            .args(["check", "config"])
            .arg(deploy("prometheus/prometheus.yml")),
    );
    // check config also checks the rule files it names.
    assert!(out.contains("alerts.yml"), "alerts.yml not loaded:\n{out}");
}

#[test]
fn kubernetes_prometheus_config_is_valid() {
    let config = deploy("prometheus/prometheus-k8s.yml");
    let (ok, out) = output(
        Command::new("promtool")
            .args(["check", "config"])
            .arg(&config),
    );
    if ok {
        return;
    }
    // Debian builds Prometheus without Kubernetes service discovery (its client libraries are
    // not packaged), so its promtool rejects the key itself. Check everything else: the same
    // file without kubernetes_sd_configs (relabelling rules, rule files, globals).
    assert!(
        out.contains("field kubernetes_sd_configs not found"),
        "promtool check config {} failed:\n{out}",
        config.display()
    );
    eprintln!("this promtool has no Kubernetes SD (Debian build): checking the rest of the file");
    let dir = TempDir::new("deploy-prometheus-k8s");
    std::fs::copy(
        deploy("prometheus/alerts.yml"),
        dir.path().join("alerts.yml"),
    )
    .expect("copy alerts.yml");
    let stripped = dir.path().join("prometheus-k8s.yml");
    run_ok(
        Command::new(venv_tool("python"))
            .arg("-c")
            .arg(
                "import sys, yaml\n\
                 config = yaml.safe_load(open(sys.argv[1]))\n\
                 for job in config['scrape_configs']:\n    \
                     assert 'kubernetes_sd_configs' in job, job['job_name']\n    \
                     del job['kubernetes_sd_configs']\n\
                 yaml.safe_dump(config, open(sys.argv[2], 'w'))",
            )
            .arg(&config)
            .arg(&stripped),
    );
    let out = run_ok(
        Command::new("promtool")
            .args(["check", "config"])
            .arg(&stripped),
    );
    assert!(out.contains("alerts.yml"), "alerts.yml not loaded:\n{out}");
}

#[test]
fn alert_rules_are_valid() {
    run_ok(
        Command::new("promtool")
            .args(["check", "rules"])
            .arg(deploy("prometheus/alerts.yml")),
    );
}

#[test]
fn alert_rules_pass_their_unit_tests() {
    run_ok(
        Command::new("promtool")
            .args(["test", "rules"])
            .arg(deploy("prometheus/alerts_test.yml")),
    );
}

#[test]
fn every_alert_has_a_severity_a_summary_a_description_and_unit_tests() {
    let rules = yaml(&deploy("prometheus/alerts.yml"));
    let tests = std::fs::read_to_string(deploy("prometheus/alerts_test.yml")).expect("read tests");
    let mut alerts = Vec::new();
    for group in rules["groups"].as_array().expect("groups") {
        for rule in group["rules"].as_array().expect("rules") {
            let Some(alert) = rule["alert"].as_str() else {
                continue;
            };
            alerts.push(alert.to_string());
            let severity = rule["labels"]["severity"].as_str().unwrap_or_default();
            assert!(
                ["critical", "warning"].contains(&severity),
                "{alert}: severity {severity:?}"
            );
            for annotation in ["summary", "description"] {
                assert!(
                    rule["annotations"][annotation]
                        .as_str()
                        .is_some_and(|s| !s.trim().is_empty()),
                    "{alert}: no {annotation}"
                );
            }
            // Firing and not firing (`exp_alerts: []`) are both asserted in the unit tests
            // (promtool checks the expectations; this checks that they exist).
            let cases: Vec<&str> = tests
                .split("alertname:")
                .skip(1)
                .filter(|case| case.split_whitespace().next() == Some(alert))
                .collect();
            assert!(
                cases.iter().any(|c| c.contains("exp_alerts: []")),
                "{alert}: no not-firing case in alerts_test.yml"
            );
            assert!(
                cases.iter().any(|c| c.contains("exp_labels")),
                "{alert}: no firing case in alerts_test.yml"
            );
        }
    }
    for expected in [
        "LearnerDown",
        "NoActors",
        "LearnerStalled",
        "NaNLoss",
        "HighDropRate",
    ] {
        assert!(alerts.iter().any(|a| a == expected), "{expected} missing");
    }
}

/// Metric names in the rules must be ones the binaries export (common/src/telemetry.rs), or
/// an alert silently never fires after a rename.
#[test]
fn alerts_use_only_exported_metric_names() {
    let rules = std::fs::read_to_string(deploy("prometheus/alerts.yml")).expect("read rules");
    let telemetry = std::fs::read_to_string(workspace_root().join("common/src/telemetry.rs"))
        .expect("read common/src/telemetry.rs");
    let mut names = Vec::new();
    for (start, _) in rules.match_indices("junction_") {
        let name: String = rules[start..]
            .chars()
            .take_while(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || *c == '_')
            .collect();
        if !names.contains(&name) {
            names.push(name);
        }
    }
    assert!(names.len() >= 5, "found only {names:?}");
    for name in &names {
        let base = ["_bucket", "_count", "_sum"]
            .iter()
            .find_map(|suffix| name.strip_suffix(suffix))
            .filter(|base| telemetry.contains(&format!("\"{base}\"")))
            .unwrap_or(name);
        assert!(
            telemetry.contains(&format!("\"{base}\"")),
            "alerts.yml uses {name}, which common/src/telemetry.rs does not define"
        );
    }
}

// --- Kubernetes --------------------------------------------------------------------------------

#[test]
fn kubernetes_manifests_pass_strict_schema_validation() {
    let dir = deploy("k8s");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("list deploy/k8s")
        .map(|e| e.expect("dir entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "yaml" || e == "yml"))
        // kustomize's own file and patches are not Kubernetes objects.
        .filter(|p| {
            let name = p.file_name().unwrap().to_string_lossy();
            name != "kustomization.yaml" && !name.contains("patch")
        })
        .collect();
    files.sort();
    let names: Vec<String> = files
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    for expected in K8S_MANIFESTS {
        assert!(
            names.iter().any(|n| n == expected),
            "{expected} missing in {names:?}"
        );
    }
    for version in KUBERNETES_VERSIONS {
        run_ok(
            Command::new(venv_tool("kubernetes-validate"))
                .args(["--strict", "--kubernetes-version", version])
                .args(&files),
        );
    }
}

/// `kubectl apply -k` renders both kustomizations; their output must validate too (this is
/// where the GPU patch is checked). Needs kubectl, which set-up does not install: skipped
/// with a note without it.
#[test]
fn kustomizations_render_valid_manifests() {
    let kubectl = Command::new("kubectl")
        .args(["version", "--client"])
        .output();
    if !kubectl.is_ok_and(|o| o.status.success()) {
        eprintln!("kubectl not found: kustomize rendering not checked");
        return;
    }
    let dir = TempDir::new("deploy-kustomize");
    for (overlay, gpu) in [("k8s", false), ("k8s-gpu", true)] {
        let rendered = run_ok(
            Command::new("kubectl")
                .arg("kustomize")
                .arg(deploy(overlay)),
        );
        let file = dir.path().join(format!("{overlay}.yaml"));
        std::fs::write(&file, &rendered).expect("write rendered manifests");
        for version in KUBERNETES_VERSIONS {
            run_ok(
                Command::new(venv_tool("kubernetes-validate"))
                    .args(["--strict", "--kubernetes-version", version])
                    .arg(&file),
            );
        }
        let docs = yaml_documents(&file);
        assert_eq!(docs.len(), 6, "{overlay}: {} objects", docs.len());
        let learner = docs
            .iter()
            .find(|d| d["kind"] == "StatefulSet")
            .expect("learner StatefulSet");
        let container = &learner["spec"]["template"]["spec"]["containers"][0];
        let device = container["env"]
            .as_array()
            .expect("env")
            .iter()
            .find(|e| e["name"] == "JUNCTION_DEVICE")
            .expect("JUNCTION_DEVICE")["value"]
            .clone();
        let gpus = &container["resources"]["limits"]["nvidia.com/gpu"];
        if gpu {
            assert_eq!(device, "cuda");
            assert_eq!(gpus, 1);
            // The patch adds to the base's resources; it must not replace them.
            assert_eq!(container["resources"]["limits"]["cpu"], "4");
        } else {
            assert_eq!(device, "cpu");
            assert!(gpus.is_null());
        }
    }
}

/// Names, ports and labels that must agree across manifests, Prometheus and alerts.
#[test]
fn kubernetes_manifests_agree_with_each_other_and_with_prometheus() {
    let services = yaml_documents(&deploy("k8s/learner-service.yaml"));
    let learner = yaml(&deploy("k8s/learner-statefulset.yaml"));
    let actor = yaml(&deploy("k8s/actor-deployment.yaml"));
    let configmap = yaml(&deploy("k8s/configmap.yaml"));
    let kustomization = yaml(&deploy("k8s/kustomization.yaml"));

    let listed = strings(&kustomization["resources"]);
    assert_eq!(listed.len(), K8S_MANIFESTS.len());
    for manifest in K8S_MANIFESTS {
        assert!(
            listed.iter().any(|r| r == manifest),
            "kustomization lacks {manifest}"
        );
    }

    let service = services
        .iter()
        .find(|s| s["metadata"]["name"] == "junction-learner")
        .expect("Service junction-learner");
    let headless = services
        .iter()
        .find(|s| s["spec"]["clusterIP"] == "None")
        .expect("headless Service");
    assert_eq!(learner["spec"]["serviceName"], headless["metadata"]["name"]);
    assert_eq!(learner["spec"]["replicas"], 1, "one learner per run");
    let pod_labels = &learner["spec"]["template"]["metadata"]["labels"];
    for s in [service, headless] {
        for (key, value) in s["spec"]["selector"].as_object().expect("selector") {
            assert_eq!(
                &pod_labels[key], value,
                "selector {key} of {}",
                s["metadata"]["name"]
            );
        }
    }
    // The API server rejects a workload whose selector does not match its pod template.
    for workload in [&learner, &actor] {
        let labels = &workload["spec"]["template"]["metadata"]["labels"];
        let selector = workload["spec"]["selector"]["matchLabels"]
            .as_object()
            .expect("matchLabels");
        for (key, value) in selector {
            assert_eq!(&labels[key], value, "{}", workload["metadata"]["name"]);
        }
    }
    let port = |s: &Value, name: &str| {
        s["spec"]["ports"]
            .as_array()
            .expect("ports")
            .iter()
            .find(|p| p["name"] == name)
            .unwrap_or_else(|| panic!("port {name}"))["port"]
            .as_u64()
            .unwrap()
    };
    assert_eq!(port(service, "grpc"), 50051);
    assert_eq!(port(service, "metrics"), 9100);

    // Actors dial the Service.
    let actor_args = strings(&actor["spec"]["template"]["spec"]["containers"][0]["args"]);
    let url = &actor_args[actor_args.iter().position(|a| a == "--learner").unwrap() + 1];
    assert_eq!(
        url,
        &format!(
            "http://{}:{}",
            service["metadata"]["name"].as_str().unwrap(),
            50051
        )
    );
    assert_eq!(actor["spec"]["replicas"], 4);

    // Scrape annotations name the declared metrics port, which --metrics-addr binds, and the
    // component label gives the job names alerts.yml and the dashboard use.
    let alerts = std::fs::read_to_string(deploy("prometheus/alerts.yml")).unwrap();
    for (workload, metrics_port) in [(&learner, 9100), (&actor, 9101)] {
        let template = &workload["spec"]["template"];
        let annotations = &template["metadata"]["annotations"];
        assert_eq!(annotations["prometheus.io/scrape"], "true");
        assert_eq!(annotations["prometheus.io/port"], metrics_port.to_string());
        let container = &template["spec"]["containers"][0];
        let declared = container["ports"]
            .as_array()
            .expect("container ports")
            .iter()
            .find(|p| p["name"] == "metrics")
            .expect("a port named metrics")["containerPort"]
            .clone();
        assert_eq!(declared, metrics_port);
        let command = strings(&container["args"]).join(" ");
        assert!(
            command.contains(&format!("--metrics-addr 0.0.0.0:{metrics_port}")),
            "{command}"
        );
        let component = template["metadata"]["labels"]["app.kubernetes.io/component"]
            .as_str()
            .expect("component label");
        if component == "learner" {
            assert!(alerts.contains(&format!("job=\"junction-{component}\"")));
        }
    }

    // The learner mounts the ConfigMap and keeps its run directory on the claim.
    let spec = &learner["spec"]["template"]["spec"];
    let volume = spec["volumes"]
        .as_array()
        .unwrap()
        .iter()
        .find(|v| v["configMap"].is_object())
        .expect("ConfigMap volume");
    assert_eq!(volume["configMap"]["name"], configmap["metadata"]["name"]);
    let mounts = &spec["containers"][0]["volumeMounts"];
    let mount_of = |name: &Value| {
        mounts
            .as_array()
            .unwrap()
            .iter()
            .find(|m| &m["name"] == name)
            .unwrap_or_else(|| panic!("no mount of {name}"))["mountPath"]
            .clone()
    };
    assert_eq!(mount_of(&volume["name"]), "/config");
    assert_eq!(
        mount_of(&learner["spec"]["volumeClaimTemplates"][0]["metadata"]["name"]),
        "/runs"
    );
}

#[test]
fn configmap_run_configuration_is_accepted_by_the_learner() {
    let configmap = yaml(&deploy("k8s/configmap.yaml"));
    let toml = configmap["data"]["run.toml"]
        .as_str()
        .expect("data.run.toml");
    let dir = TempDir::new("deploy-run-config");
    let file = dir.path().join("run.toml");
    std::fs::write(&file, toml).expect("write run.toml");
    // Unknown keys and invalid values are errors in `learner config`.
    let effective = run_ok(
        Command::new(bin("learner"))
            .arg("config")
            .arg("--config")
            .arg(&file),
    );
    assert!(
        effective
            .lines()
            .any(|l| l.trim() == "max_seconds = 0.0" || l.trim() == "max_seconds = 0"),
        "a deployed learner must train until stopped:\n{effective}"
    );
}

// --- The learner's resume-or-start wrapper (compose and Kubernetes) ----------------------------

/// Runs a wrapper script with a stub `learner` first on PATH; returns the stub's arguments.
fn wrapper_args(script: &str, env: &[(&str, &str)], dir: &Path) -> Vec<String> {
    let stub_dir = dir.join("bin");
    std::fs::create_dir_all(&stub_dir).unwrap();
    let stub = stub_dir.join("learner");
    let args_file = dir.join("args");
    std::fs::write(
        &stub,
        format!(
            "#!/bin/sh\nprintf '%s\\n' \"$@\" > '{}'\n",
            args_file.display()
        ),
    )
    .unwrap();
    std::fs::set_permissions(&stub, std::fs::Permissions::from_mode(0o755)).unwrap();
    let _ = std::fs::remove_file(&args_file);
    let path = format!(
        "{}:{}",
        stub_dir.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    run_ok(
        Command::new("sh")
            .arg("-c")
            .arg(script)
            .env("PATH", path)
            .env_remove("JUNCTION_DEVICE")
            .envs(env.iter().copied()),
    );
    std::fs::read_to_string(&args_file)
        .expect("the wrapper did not run learner")
        .lines()
        .map(str::to_string)
        .collect()
}

fn flag_value<'a>(args: &'a [String], flag: &str) -> Option<&'a str> {
    args.iter()
        .position(|a| a == flag)
        .map(|i| args[i + 1].as_str())
}

/// Runs `script` (whose run directory is `run_dir`, e.g. /runs/current) against the three
/// states of a run directory it must tell apart, on a temporary directory instead; returns the
/// learner arguments of a fresh start and of a resume.
fn check_resume_or_start(
    script: &str,
    run_dir: &str,
    env: &[(&str, &str)],
    label: &str,
) -> [Vec<String>; 2] {
    let assignment = format!("run={run_dir}\n");
    assert!(
        script.contains(&assignment),
        "no `{assignment}` in\n{script}"
    );
    let dir = TempDir::new(label);
    let run = dir.path().join("run");
    let run_str = run.display().to_string();
    let script = script.replace(&assignment, &format!("run={run_str}\n"));
    let script = script.as_str();
    let mut seen = Vec::new();

    // A new run: nothing there yet.
    let args = wrapper_args(script, env, dir.path());
    assert_eq!(args.first().map(String::as_str), Some("serve"), "{args:?}");
    assert_eq!(
        flag_value(&args, "--run-dir"),
        Some(run_str.as_str()),
        "{args:?}"
    );
    assert!(!args.contains(&"--resume".to_string()), "{args:?}");
    seen.push(args);

    // A checkpoint whose write was interrupted (no meta.json) does not count: the learner
    // ignores it too, so this is still a fresh start.
    std::fs::create_dir_all(run.join("checkpoints/ckpt-0000000003")).unwrap();
    std::fs::create_dir_all(run.join("checkpoints/.tmp-0000000004-1")).unwrap();
    let args = wrapper_args(script, env, dir.path());
    assert_eq!(
        flag_value(&args, "--run-dir"),
        Some(run_str.as_str()),
        "{args:?}"
    );
    assert!(!args.contains(&"--resume".to_string()), "{args:?}");

    // A complete checkpoint: resume (and never pass --run-dir, which conflicts).
    std::fs::write(run.join("checkpoints/ckpt-0000000003/meta.json"), "{}").unwrap();
    let args = wrapper_args(script, env, dir.path());
    assert_eq!(
        flag_value(&args, "--resume"),
        Some(run_str.as_str()),
        "{args:?}"
    );
    assert!(!args.contains(&"--run-dir".to_string()), "{args:?}");
    seen.push(args);
    seen.try_into().unwrap()
}

#[test]
fn compose_file_defines_the_stack_and_its_learner_resumes_or_starts() {
    let compose = yaml(&deploy("compose.yaml"));
    let services = &compose["services"];
    for name in ["learner", "actor", "prometheus", "grafana"] {
        assert!(services[name].is_object(), "service {name} missing");
    }
    // Both run the one image (through the shared `x-junction` block).
    for name in ["learner", "actor"] {
        assert_eq!(services[name]["image"], "junction:latest", "{name}");
        assert_eq!(
            services[name]["build"]["dockerfile"], "deploy/Dockerfile",
            "{name}"
        );
    }

    // Actors: reach the learner by its service name, serve metrics where Prometheus' DNS
    // discovery looks, and can be scaled (no fixed name, no published port).
    let actor = &services["actor"];
    let args = strings(&actor["command"]);
    assert_eq!(args[0], "actor");
    assert_eq!(flag_value(&args, "--learner"), Some("http://learner:50051"));
    assert_eq!(flag_value(&args, "--metrics-addr"), Some("0.0.0.0:9101"));
    assert!(actor["container_name"].is_null() && actor["ports"].is_null());
    assert!(actor["deploy"]["replicas"].as_u64().is_some());
    let prometheus_config = yaml(&deploy("prometheus/prometheus.yml"));
    let jobs = prometheus_config["scrape_configs"].as_array().unwrap();
    let job = |name: &str| jobs.iter().find(|j| j["job_name"] == name).expect(name);
    assert_eq!(
        job("junction-actor")["dns_sd_configs"][0]["names"][0],
        "actor"
    );
    assert_eq!(job("junction-actor")["dns_sd_configs"][0]["port"], 9101);
    assert_eq!(
        job("junction-learner")["static_configs"][0]["targets"][0],
        "learner:9100"
    );

    // Files and directories mounted into Prometheus and Grafana exist (relative to deploy/).
    for service in ["prometheus", "grafana"] {
        for volume in strings(&services[service]["volumes"]) {
            if let Some(source) = volume.strip_prefix("./") {
                let source = source.split(':').next().unwrap();
                assert!(deploy(source).exists(), "{service} mounts missing {source}");
            }
        }
    }

    // The learner's wrapper, after compose's `$$` -> `$` unescaping.
    let command = strings(&services["learner"]["command"]);
    assert_eq!(command[..2], ["sh", "-c"]);
    let script = command[2].replace("$$", "$");
    for args in check_resume_or_start(&script, "/runs/compose", &[], "deploy-compose-wrapper") {
        assert_eq!(flag_value(&args, "--max-seconds"), Some("0"), "{args:?}");
        assert_eq!(
            flag_value(&args, "--addr"),
            Some("0.0.0.0:50051"),
            "{args:?}"
        );
        assert_eq!(
            flag_value(&args, "--metrics-addr"),
            Some("0.0.0.0:9100"),
            "{args:?}"
        );
    }
}

#[test]
fn kubernetes_learner_resumes_or_starts_with_the_configmap() {
    let learner = yaml(&deploy("k8s/learner-statefulset.yaml"));
    let args = strings(&learner["spec"]["template"]["spec"]["containers"][0]["args"]);
    assert_eq!(args[..2], ["sh", "-c"]);
    for (env, device) in [
        (&[][..], "cpu"),
        (&[("JUNCTION_DEVICE", "cuda")][..], "cuda"),
    ] {
        let label = format!("deploy-k8s-wrapper-{device}");
        let [fresh, resumed] = check_resume_or_start(&args[2], "/runs/current", env, &label);
        // A new run takes the ConfigMap's configuration; a resumed one keeps its recorded one.
        assert_eq!(flag_value(&fresh, "--config"), Some("/config/run.toml"));
        assert_eq!(flag_value(&resumed, "--config"), None);
        for args in [&fresh, &resumed] {
            assert_eq!(
                flag_value(args, "--addr"),
                Some("0.0.0.0:50051"),
                "{args:?}"
            );
            assert_eq!(
                flag_value(args, "--metrics-addr"),
                Some("0.0.0.0:9100"),
                "{args:?}"
            );
            assert_eq!(flag_value(args, "--device"), Some(device), "{args:?}");
        }
    }
}
