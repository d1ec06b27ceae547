//! Runs across hosts: a learner with mutual TLS and a shared token. Certificates are made for
//! this test (a throw-away CA, a server and a client certificate); no key is committed.

use std::path::Path;
use std::time::Duration;

use junction_common::proto::{self, learner_client::LearnerClient};
use junction_core::spec::PROTOCOL_VERSION;
use junction_tests::{
    QUICK_RUN, TempDir, metric_sum, scrape, start_actor, start_learner_with_env, wait_until,
};
use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair,
    KeyUsagePurpose,
};
use tonic::Code;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint, Identity};

const TOKEN: &str = "test-token-0123456789abcdef";

/// Writes `ca.pem`/`ca.key`, `server.pem`/`server.key` (for localhost and 127.0.0.1) and
/// `client.pem`/`client.key` into `dir`.
fn make_certificates(dir: &Path) {
    let mut ca_params = CertificateParams::new(Vec::<String>::new()).expect("CA params");
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca_params
        .distinguished_name
        .push(DnType::CommonName, "junction test CA");
    ca_params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
    let ca_key = KeyPair::generate().expect("CA key");
    let ca_cert = ca_params.self_signed(&ca_key).expect("CA certificate");
    std::fs::write(dir.join("ca.pem"), ca_cert.pem()).expect("write CA");
    std::fs::write(dir.join("ca.key"), ca_key.serialize_pem()).expect("write CA key");
    let issuer = Issuer::new(ca_params, ca_key);
    for (name, names, usage) in [
        (
            "server",
            vec!["localhost".to_string(), "127.0.0.1".to_string()],
            ExtendedKeyUsagePurpose::ServerAuth,
        ),
        (
            "client",
            vec!["actor".to_string()],
            ExtendedKeyUsagePurpose::ClientAuth,
        ),
    ] {
        let mut params = CertificateParams::new(names).expect("params");
        params.distinguished_name.push(DnType::CommonName, name);
        params.extended_key_usages = vec![usage];
        params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        let key = KeyPair::generate().expect("key");
        let cert = params.signed_by(&key, &issuer).expect("sign");
        std::fs::write(dir.join(format!("{name}.pem")), cert.pem()).expect("write cert");
        std::fs::write(dir.join(format!("{name}.key")), key.serialize_pem()).expect("write key");
    }
}

fn read(dir: &Path, name: &str) -> Vec<u8> {
    std::fs::read(dir.join(name)).expect("read PEM")
}

/// A TLS channel to `port` that presents the client certificate.
async fn tls_channel(dir: &Path, port: u16) -> Channel {
    let tls = ClientTlsConfig::new()
        .ca_certificate(Certificate::from_pem(read(dir, "ca.pem")))
        .identity(Identity::from_pem(
            read(dir, "client.pem"),
            read(dir, "client.key"),
        ))
        .domain_name("localhost");
    Endpoint::from_shared(format!("https://127.0.0.1:{port}"))
        .expect("url")
        .tls_config(tls)
        .expect("tls")
        .connect()
        .await
        .expect("TLS connect")
}

/// Calls every RPC with `token` (or none) and returns their status codes.
async fn every_rpc(channel: Channel, token: Option<&str>) -> Vec<(&'static str, Code)> {
    let header = token.map(|t| {
        format!("Bearer {t}")
            .parse::<tonic::metadata::AsciiMetadataValue>()
            .expect("header")
    });
    let mut client =
        LearnerClient::with_interceptor(channel, move |mut request: tonic::Request<()>| {
            if let Some(value) = &header {
                request
                    .metadata_mut()
                    .insert("authorization", value.clone());
            }
            Ok(request)
        });
    let code = |r: Result<tonic::Code, tonic::Status>| r.unwrap_or_else(|s| s.code());
    let register = client
        .register(proto::RegisterRequest {
            protocol_version: PROTOCOL_VERSION,
            actor_name: "probe".into(),
            scenes: 1,
            instance: String::new(),
        })
        .await
        .map(|_| Code::Ok);
    let status = client
        .status(proto::StatusRequest {})
        .await
        .map(|_| Code::Ok);
    let watch = client
        .watch_policy(proto::WatchPolicyRequest {
            protocol_version: PROTOCOL_VERSION,
            actor_id: "probe".into(),
            have_version: 0,
        })
        .await
        .map(|_| Code::Ok);
    let push = client
        .push_rollouts(tokio_stream::iter(Vec::<proto::RolloutFragment>::new()))
        .await
        .map(|_| Code::Ok);
    vec![
        ("Register", code(register)),
        ("Status", code(status)),
        ("WatchPolicy", code(watch)),
        ("PushRollouts", code(push)),
    ]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mutual_tls_and_a_token_guard_every_rpc() {
    let dir = TempDir::new("security");
    make_certificates(dir.path());
    let token_file = dir.path().join("token");
    std::fs::write(&token_file, format!("{TOKEN}\n")).expect("token file");
    let run_dir = dir.path().join("run");
    let port = junction_tests::free_port();
    let addr = format!("127.0.0.1:{port}");
    let pem = |name: &str| dir.path().join(name).display().to_string();
    let sets = [
        format!("server.tls_cert={:?}", pem("server.pem")),
        format!("server.tls_key={:?}", pem("server.key")),
        format!("server.tls_client_ca={:?}", pem("ca.pem")),
        format!(
            "server.auth_token_file={:?}",
            token_file.display().to_string()
        ),
        "server.max_rollout_streams=1".to_string(),
    ];
    let mut args: Vec<&str> = vec!["--addr", &addr, "--max-seconds", "300"];
    args.extend_from_slice(QUICK_RUN);
    for set in &sets {
        args.extend(["--set", set]);
    }
    let (mut learner, endpoints) =
        tokio::task::block_in_place(|| start_learner_with_env(&run_dir, dir.path(), &args, &[]));
    // The token is not part of the recorded configuration.
    let recorded = std::fs::read_to_string(run_dir.join("config.toml")).expect("config.toml");
    assert!(!recorded.contains(TOKEN));

    // Without a token, or with a wrong one: UNAUTHENTICATED on every RPC.
    for token in [None, Some("wrong-token-0123456789abcdef")] {
        for (rpc, code) in every_rpc(tls_channel(dir.path(), port).await, token).await {
            assert_eq!(code, Code::Unauthenticated, "{rpc} with token {token:?}");
        }
    }
    // With it, every RPC goes through.
    for (rpc, code) in every_rpc(tls_channel(dir.path(), port).await, Some(TOKEN)).await {
        assert_eq!(code, Code::Ok, "{rpc} with the right token");
    }
    // Plain TCP, or TLS without a client certificate, does not get that far, even with the
    // right token.
    let plain = async {
        let channel = Endpoint::from_shared(format!("http://{addr}"))
            .ok()?
            .connect()
            .await
            .ok()?;
        Some(every_rpc(channel, Some(TOKEN)).await)
    };
    let served = |codes: Option<Vec<(&str, Code)>>| {
        codes.is_some_and(|codes| codes.iter().any(|(_, code)| *code == Code::Ok))
    };
    assert!(!served(plain.await), "plain TCP was served");
    let no_client_cert = ClientTlsConfig::new()
        .ca_certificate(Certificate::from_pem(read(dir.path(), "ca.pem")))
        .domain_name("localhost");
    let anonymous = async {
        let channel = Endpoint::from_shared(format!("https://{addr}"))
            .ok()?
            .tls_config(no_client_cert)
            .ok()?
            .connect()
            .await
            .ok()?;
        Some(every_rpc(channel, Some(TOKEN)).await)
    };
    assert!(
        !served(anonymous.await),
        "a client without a certificate was served"
    );

    // A real actor with the CA, its certificate and the token trains.
    let url = format!("https://localhost:{port}");
    let token_path = token_file.display().to_string();
    let (ca, client_pem, client_key) = (pem("ca.pem"), pem("client.pem"), pem("client.key"));
    let actor_args = [
        "--learner",
        &url,
        "--tls-ca",
        &ca,
        "--tls-cert",
        &client_pem,
        "--tls-key",
        &client_key,
        "--auth-token-file",
        &token_path,
    ];
    let actor = tokio::task::block_in_place(|| {
        junction_tests::Process::start(
            "actor",
            &junction_tests::bin("actor"),
            &actor_args.iter().map(|s| s.to_string()).collect::<Vec<_>>(),
            dir.path(),
        )
    });
    let trained = tokio::task::block_in_place(|| {
        wait_until(Duration::from_secs(120), || {
            let m = scrape(&endpoints.metrics);
            metric_sum(&m, "junction_learner_policy_version") >= 2.0
                && metric_sum(&m, "junction_learner_connected_actors") == 1.0
        })
    });
    assert!(
        trained,
        "the TLS actor did not train\n{}\n{}",
        actor.log_tail(20),
        learner.log_tail(20)
    );

    // server.max_rollout_streams = 1, and the actor holds it: a second stream is refused.
    let mut client = LearnerClient::with_interceptor(
        tls_channel(dir.path(), port).await,
        |mut r: tonic::Request<()>| {
            r.metadata_mut().insert(
                "authorization",
                format!("Bearer {TOKEN}").parse().expect("header"),
            );
            Ok(r)
        },
    );
    let refused = client
        .push_rollouts(tokio_stream::iter(Vec::<proto::RolloutFragment>::new()))
        .await
        .expect_err("a second rollout stream");
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused:?}");
    assert!(
        refused.message().contains("server.max_rollout_streams"),
        "{refused:?}"
    );

    // An actor with a wrong token stops at once with a clear error instead of retrying.
    let wrong = dir.path().join("wrong-token");
    std::fs::write(&wrong, "not-the-token-0123456789").expect("write");
    let wrong_path = wrong.display().to_string();
    let mut intruder = tokio::task::block_in_place(|| {
        let mut args: Vec<String> = actor_args.iter().map(|s| s.to_string()).collect();
        let last = args.len() - 1;
        args[last] = wrong_path.clone();
        junction_tests::Process::start("intruder", &junction_tests::bin("actor"), &args, dir.path())
    });
    tokio::task::block_in_place(|| {
        intruder.assert_fails_saying(Duration::from_secs(30), &["wrong auth token"])
    });

    let m = tokio::task::block_in_place(|| scrape(&endpoints.metrics));
    assert!(
        m.get("junction_learner_requests_refused_total{reason=\"unauthenticated\"}")
            .copied()
            .unwrap_or(0.0)
            >= 9.0,
        "{m:?}"
    );
    assert!(
        m.get("junction_learner_requests_refused_total{reason=\"stream_limit\"}")
            .copied()
            .unwrap_or(0.0)
            >= 1.0
    );
    tokio::task::block_in_place(|| learner.stop(Duration::from_secs(60)));
    drop(actor);
}

#[test]
fn an_actor_without_the_token_is_refused_and_says_why() {
    let dir = TempDir::new("token-only");
    let run_dir = dir.path().join("run");
    // The token from the environment (as from a Kubernetes Secret), plain TCP.
    let (mut learner, endpoints) = start_learner_with_env(
        &run_dir,
        dir.path(),
        &["--max-seconds", "120"],
        &[("JUNCTION_AUTH_TOKEN", TOKEN)],
    );
    let mut actor = start_actor(&endpoints, dir.path(), "actor", &[]);
    actor.assert_fails_saying(
        Duration::from_secs(30),
        &["Unauthenticated", "missing auth token"],
    );
    learner.stop(Duration::from_secs(30));
}

/// Starts a learner with `files`: `[server]` keys set to files in `dir` (none: plain text).
fn start_learner_with_files(
    dir: &Path,
    label: &str,
    files: &[(&str, &str)],
) -> (junction_tests::Process, junction_tests::Endpoints) {
    let sets: Vec<String> = files
        .iter()
        .map(|(key, file)| format!("server.{key}={:?}", dir.join(file).display().to_string()))
        .collect();
    let mut args = vec!["--max-seconds", "120"];
    for set in &sets {
        args.extend(["--set", set]);
    }
    start_learner_with_env(&dir.join(label), dir, &args, &[])
}

/// Runs an actor against `url` with `extra` flags and asserts that it fails within seconds,
/// long before `--connect-timeout` (120 s), saying each of `reasons`. `at_first_attempt`: the
/// failure is certain on every attempt, so the actor must not take it for an outage even once.
fn assert_actor_stops_at_once(
    dir: &Path,
    name: &str,
    url: &str,
    extra: &[&str],
    reasons: &[&str],
    at_first_attempt: bool,
) {
    let mut args = vec![
        "--learner".to_string(),
        url.to_string(),
        "--connect-timeout".to_string(),
        "120".to_string(),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    let mut actor = junction_tests::Process::start(name, &junction_tests::bin("actor"), &args, dir);
    // Generous for a loaded machine; retrying would take the full 120 s.
    actor.assert_fails_saying(Duration::from_secs(20), reasons);
    assert!(
        !(at_first_attempt && actor.log().contains("unreachable")),
        "{name} took a configuration error for an outage\n{}",
        actor.log_tail(20)
    );
}

#[test]
fn an_actor_with_a_tls_misconfiguration_stops_at_once() {
    let dir = TempDir::new("tls-misconfigured");
    make_certificates(dir.path());
    let other = dir.path().join("other");
    std::fs::create_dir(&other).expect("mkdir");
    make_certificates(&other);
    let pem = |name: &str| dir.path().join(name).display().to_string();
    let (ca, other_ca) = (pem("ca.pem"), other.join("ca.pem").display().to_string());

    let (mut learner, endpoints) = start_learner_with_files(
        dir.path(),
        "run",
        &[("tls_cert", "server.pem"), ("tls_key", "server.key")],
    );
    let port = endpoints.grpc.rsplit(':').next().expect("port");
    let url = format!("https://localhost:{port}");
    // Another CA than the one that signed the learner's certificate.
    assert_actor_stops_at_once(
        dir.path(),
        "wrong-ca",
        &url,
        &["--tls-ca", &other_ca],
        &["TLS certificate was rejected", "--tls-ca"],
        true,
    );
    // The right CA, but a name the certificate is not issued for.
    assert_actor_stops_at_once(
        dir.path(),
        "wrong-domain",
        &url,
        &["--tls-ca", &ca, "--tls-domain", "learner.example"],
        &[
            "TLS certificate was rejected",
            "learner.example",
            "--tls-domain",
        ],
        true,
    );
    // Plain text to a TLS learner. Its alert may be lost to a reset connection, which is
    // retried; the next attempt usually reads it.
    assert_actor_stops_at_once(
        dir.path(),
        "http-to-tls",
        &format!("http://{}", endpoints.grpc),
        &[],
        &["does not speak plain-text gRPC", "https://"],
        false,
    );
    learner.stop(Duration::from_secs(30));

    // A learner that serves its CA's certificate as its own.
    let (mut learner, endpoints) = start_learner_with_files(
        dir.path(),
        "run-ca",
        &[("tls_cert", "ca.pem"), ("tls_key", "ca.key")],
    );
    let port = endpoints.grpc.rsplit(':').next().expect("port");
    assert_actor_stops_at_once(
        dir.path(),
        "ca-as-server",
        &format!("https://localhost:{port}"),
        &["--tls-ca", &ca],
        &[
            "TLS certificate was rejected",
            "CaUsedAsEndEntity",
            "tls_cert",
        ],
        true,
    );
    learner.stop(Duration::from_secs(30));
}

#[test]
fn an_actor_that_speaks_tls_to_a_plain_text_learner_stops_at_once() {
    let dir = TempDir::new("tls-plain");
    make_certificates(dir.path());
    let ca = dir.path().join("ca.pem").display().to_string();
    let (mut learner, endpoints) = start_learner_with_files(dir.path(), "run", &[]);
    assert_actor_stops_at_once(
        dir.path(),
        "https-to-plain",
        &format!("https://{}", endpoints.grpc),
        &["--tls-ca", &ca],
        &["does not speak TLS", "http://"],
        true,
    );
    learner.stop(Duration::from_secs(30));
}
