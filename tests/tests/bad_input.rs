//! Hostile or broken actors: malformed fragments (and bytes that are no protobuf at all) get a
//! clear gRPC error, are counted by reason in /metrics, and the learner keeps serving.

use std::time::Duration;

use junction_common::proto::{self, learner_client::LearnerClient};
use junction_core::lcf_inputs;
use junction_core::spec::PROTOCOL_VERSION;
use junction_tests::{TempDir, metric_sum, scrape, start_learner};
use prost::bytes::{Buf, BufMut};
use tonic::Code;
use tonic::codec::{Codec, DecodeBuf, Decoder, EncodeBuf, Encoder};
use tonic::codegen::http::uri::PathAndQuery;

const OBS_DIM: usize = 91;

/// A valid fragment: 2 steps of one agent on the default scenario.
fn valid_fragment() -> proto::RolloutFragment {
    let (steps, agents) = (2usize, 1usize);
    proto::RolloutFragment {
        protocol_version: PROTOCOL_VERSION,
        actor_id: "test".into(),
        sequence: 0,
        behaviour_version: 0,
        scenario: "intersection".into(),
        steps: steps as u32,
        agents: agents as u32,
        obs_dim: OBS_DIM as u32,
        action_dim: 2,
        obs: vec![0.5; steps * agents * OBS_DIM],
        actions: vec![0.1; steps * agents * 2],
        log_probs: vec![-1.0; steps * agents],
        rewards: vec![0.3; steps * agents],
        costs: vec![0.0; steps * agents],
        dones: vec![0; steps * agents],
        alive: vec![1; steps * agents],
        bootstrap_obs: vec![0.5; agents * OBS_DIM],
        neighbour_offsets: vec![0; steps * agents + 1],
        neighbour_ids: vec![],
        lcf_features: vec![0.5; steps * agents * lcf_inputs::FEATURES],
        episodes: vec![],
        human_episodes: vec![],
        scene_episodes: vec![],
        sim_seconds: 0.2,
    }
}

/// Sends and receives bytes as they are, so a test can send what no encoder would.
#[derive(Debug, Clone, Copy, Default)]
struct RawCodec;

impl Codec for RawCodec {
    type Encode = Vec<u8>;
    type Decode = Vec<u8>;
    type Encoder = RawCodec;
    type Decoder = RawCodec;

    fn encoder(&mut self) -> RawCodec {
        RawCodec
    }

    fn decoder(&mut self) -> RawCodec {
        RawCodec
    }
}

impl Encoder for RawCodec {
    type Item = Vec<u8>;
    type Error = tonic::Status;

    fn encode(&mut self, item: Vec<u8>, buf: &mut EncodeBuf<'_>) -> Result<(), tonic::Status> {
        buf.put_slice(&item);
        Ok(())
    }
}

impl Decoder for RawCodec {
    type Item = Vec<u8>;
    type Error = tonic::Status;

    fn decode(&mut self, buf: &mut DecodeBuf<'_>) -> Result<Option<Vec<u8>>, tonic::Status> {
        Ok(Some(buf.copy_to_bytes(buf.remaining()).to_vec()))
    }
}

/// Field 1 with wire type 7, which protobuf does not have: no message decodes from it.
const UNDECODABLE: &[u8] = &[0x0f, 0x01];

/// [`UNDECODABLE`] as the only message of the streaming PushRollouts and of the unary Register;
/// the two refusals.
async fn send_undecodable(grpc: &str) -> (tonic::Status, tonic::Status) {
    let channel = tonic::transport::Channel::from_shared(format!("http://{grpc}"))
        .expect("learner address")
        .connect()
        .await
        .expect("connect");
    let mut client = tonic::client::Grpc::new(channel);
    client.ready().await.expect("channel ready");
    let push = client
        .client_streaming(
            tonic::Request::new(tokio_stream::iter(vec![UNDECODABLE.to_vec()])),
            PathAndQuery::from_static("/junction.v1.Learner/PushRollouts"),
            RawCodec,
        )
        .await
        .expect_err("undecodable fragment");
    client.ready().await.expect("channel ready");
    let register = client
        .unary(
            tonic::Request::new(UNDECODABLE.to_vec()),
            PathAndQuery::from_static("/junction.v1.Learner/Register"),
            RawCodec,
        )
        .await
        .expect_err("undecodable registration");
    (push, register)
}

async fn push(
    client: &mut LearnerClient<tonic::transport::Channel>,
    fragment: proto::RolloutFragment,
) -> Result<proto::PushSummary, tonic::Status> {
    client
        .push_rollouts(tokio_stream::iter(vec![fragment]))
        .await
        .map(|r| r.into_inner())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn invalid_fragments_are_refused_with_clear_errors_and_counted() {
    let dir = TempDir::new("bad-input");
    let run_dir = dir.path().join("run");
    let (mut learner, endpoints) = tokio::task::block_in_place(|| {
        start_learner(&run_dir, dir.path(), &["--max-seconds", "120"])
    });
    let mut client = LearnerClient::connect(format!("http://{}", endpoints.grpc))
        .await
        .expect("connect");

    let mut wrong_shape = valid_fragment();
    wrong_shape.obs.truncate(100);
    let mut nan = valid_fragment();
    nan.rewards[1] = f32::NAN;
    let mut inf = valid_fragment();
    inf.obs[7] = f32::INFINITY;
    let mut version = valid_fragment();
    version.protocol_version = PROTOCOL_VERSION + 41;
    let mut dims = valid_fragment();
    dims.obs_dim = 90;
    dims.obs.truncate(2 * 90);
    dims.bootstrap_obs.truncate(90);
    let mut broken_invariant = valid_fragment();
    broken_invariant.alive[1] = 0; // the agent vanished without being done
    let cases = [
        (
            "wrong shape",
            wrong_shape,
            Code::InvalidArgument,
            "obs has 100 values, expected 182",
            "shape",
        ),
        (
            "NaN reward",
            nan,
            Code::InvalidArgument,
            "non-finite value (NaN or inf) in rewards at index 1",
            "non_finite",
        ),
        (
            "infinite obs",
            inf,
            Code::InvalidArgument,
            "in obs at index 7",
            "non_finite",
        ),
        (
            "unknown version",
            version,
            Code::FailedPrecondition,
            "protocol version 42 is not supported",
            "version",
        ),
        (
            "other obs size",
            dims,
            Code::InvalidArgument,
            "the run expects 91 × 2",
            "shape",
        ),
        (
            "broken invariant",
            broken_invariant,
            Code::InvalidArgument,
            "slot 0 is alive and not done at step 0",
            "invariant",
        ),
    ];
    for (what, fragment, code, message, _) in &cases {
        let status = push(&mut client, fragment.clone()).await.expect_err(what);
        assert_eq!(status.code(), *code, "{what}: {status:?}");
        assert!(
            status.message().contains(message),
            "{what}: message {:?} lacks {message:?}",
            status.message()
        );
    }
    // Flag bytes other than 0 and 1.
    let mut flags = valid_fragment();
    flags.dones = vec![7, 0];
    let status = push(&mut client, flags).await.expect_err("bad flag bytes");
    assert!(
        status
            .message()
            .contains("invalid flag byte 7 in dones at index 0"),
        "{status:?}"
    );

    // Bytes that are no protobuf: the sender's fault, named by RPC.
    let (undecodable_push, undecodable_register) = send_undecodable(&endpoints.grpc).await;
    for (status, rpc) in [
        (&undecodable_push, "PushRollouts"),
        (&undecodable_register, "Register"),
    ] {
        assert_eq!(status.code(), Code::InvalidArgument, "{rpc}: {status:?}");
        assert!(
            status.message().starts_with(&format!(
                "{rpc}: the request message could not be decoded: failed to decode Protobuf message"
            )),
            "{rpc}: {status:?}"
        );
    }

    // The learner still serves: a valid fragment is accepted and Status answers.
    let summary = push(&mut client, valid_fragment())
        .await
        .expect("valid fragment accepted");
    assert_eq!(
        (summary.accepted_fragments, summary.accepted_agent_steps),
        (1, 2)
    );
    client
        .status(proto::StatusRequest {})
        .await
        .expect("status after bad input");
    assert!(
        learner.try_exit().is_none(),
        "learner died:\n{}",
        learner.log_tail(30)
    );

    let m = tokio::task::block_in_place(|| scrape(&endpoints.metrics));
    let rejected = |reason: &str| {
        m.get(&format!(
            "junction_learner_fragments_rejected_total{{reason=\"{reason}\"}}"
        ))
        .copied()
        .unwrap_or(0.0)
    };
    assert_eq!(rejected("shape"), 2.0, "{m:?}");
    assert_eq!(rejected("non_finite"), 2.0);
    assert_eq!(rejected("version"), 1.0);
    assert_eq!(rejected("invariant"), 2.0);
    assert_eq!(
        rejected("decode"),
        1.0,
        "the undecodable fragment is counted"
    );
    assert_eq!(metric_sum(&m, "junction_learner_fragments_total"), 1.0);
    assert!(
        learner.log().contains("rejected fragment"),
        "rejections are logged"
    );
    tokio::task::block_in_place(|| learner.stop(Duration::from_secs(30)));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversized_names_and_ids_are_refused_on_every_rpc() {
    let dir = TempDir::new("bad-names");
    let run_dir = dir.path().join("run");
    let (mut learner, endpoints) = tokio::task::block_in_place(|| {
        start_learner(&run_dir, dir.path(), &["--max-seconds", "120"])
    });
    let mut client = LearnerClient::connect(format!("http://{}", endpoints.grpc))
        .await
        .expect("connect");
    let long = "x".repeat(300);
    let register = client
        .register(proto::RegisterRequest {
            protocol_version: PROTOCOL_VERSION,
            actor_name: long.clone(),
            scenes: 1,
            instance: String::new(),
        })
        .await
        .expect_err("a 300-byte actor name");
    assert_eq!(register.code(), Code::InvalidArgument);
    assert!(
        register.message().contains("actor_name is 300 bytes long"),
        "{register:?}"
    );
    let watch = client
        .watch_policy(proto::WatchPolicyRequest {
            protocol_version: PROTOCOL_VERSION,
            actor_id: long.clone(),
            have_version: 0,
        })
        .await
        .expect_err("a 300-byte actor id");
    assert_eq!(watch.code(), Code::InvalidArgument);
    let mut fragment = valid_fragment();
    fragment.actor_id = long;
    let push = push(&mut client, fragment)
        .await
        .expect_err("a 300-byte actor id");
    assert_eq!(push.code(), Code::InvalidArgument);
    assert!(
        push.message().contains("actor_id is 300 bytes long"),
        "{push:?}"
    );
    // Another protocol version on Register and WatchPolicy.
    let old = client
        .register(proto::RegisterRequest {
            protocol_version: PROTOCOL_VERSION + 1,
            actor_name: "a".into(),
            scenes: 1,
            instance: String::new(),
        })
        .await
        .expect_err("another protocol");
    assert_eq!(old.code(), Code::FailedPrecondition);
    client
        .status(proto::StatusRequest {})
        .await
        .expect("still serving");
    let m = tokio::task::block_in_place(|| scrape(&endpoints.metrics));
    assert_eq!(
        m.get("junction_learner_fragments_rejected_total{reason=\"shape\"}"),
        Some(&1.0)
    );
    tokio::task::block_in_place(|| learner.stop(Duration::from_secs(30)));
}
