//! Fixtures for the algorithms' tests: small runs, a fragment with a known neighbourhood, a
//! hand-checkable batch and a checkpoint round trip. Compiled for tests only, and on top of
//! the algorithms: it imports them, none of them imports it outside its tests.

use tch::{Device, Kind, Tensor};

use junction_common::fragment::RolloutFragment;
use junction_common::lcf;
use junction_common::weights::{self, Decoded};
use junction_core::config::RunConfig;

use super::Algorithm;
use super::batch::{CriticInput, Head, NormalizedFragment, TrainBatch, assemble};
use super::coordination::{Coordination, FixedLcf};
use super::ippo::{Ippo, OwnObservation};
use super::phases::Phases;
use super::shared_ppo::SharedPpo;

/// The defaults with a small network (hidden [8]) and seed 7.
pub fn small_run() -> RunConfig {
    let mut run = RunConfig::default();
    run.ppo.hidden = vec![8];
    run.run.seed = 7;
    run
}

/// IPPO with the run's fixed LCF and safety option, on the CPU.
pub fn ippo(run: &RunConfig, obs_dim: usize, action_dim: usize) -> Ippo {
    SharedPpo::new(
        "ippo",
        OwnObservation,
        Box::new(FixedLcf::new(&run.lcf)),
        run,
        obs_dim,
        action_dim,
        Device::Cpu,
    )
}

/// 2 steps × 6 slots, obs_dim = action_dim = 2, all alive except slot 5 at t = 1 (done at
/// t = 0). obs(t, s) = [s + 1, 10t + 1]; action(t, s) = [0.1(s + 1), 0.5 − t];
/// bootstrap_obs(s) = [100 + s, 7]. Neighbours, nearest first:
/// t = 0: 0 → [5, 4, 3, 2, 1]; 2 → [0]; 3 → [4, 2]; the rest none.
/// t = 1: 0 → [5, 1] (5 is empty then); 3 → [4]; the rest none.
/// S_N(t, s) = [listed neighbours / 20, 0.5, 0.3, 0.1 (s + 1), 0.5].
pub fn neighbourhood_fragment() -> RolloutFragment {
    let (steps, agents) = (2, 6);
    let cells = steps * agents;
    let mut obs = Vec::new();
    let mut actions = Vec::new();
    for t in 0..steps {
        for s in 0..agents {
            obs.extend([s as f32 + 1.0, 10.0 * t as f32 + 1.0]);
            actions.extend([0.1 * (s as f32 + 1.0), 0.5 - t as f32]);
        }
    }
    let mut alive = vec![true; cells];
    alive[agents + 5] = false;
    let mut dones = vec![false; cells];
    dones[5] = true;
    let lists: [&[u32]; 12] = [
        &[5, 4, 3, 2, 1],
        &[],
        &[0],
        &[4, 2],
        &[],
        &[],
        &[5, 1],
        &[],
        &[],
        &[4],
        &[],
        &[],
    ];
    let mut neighbour_offsets = vec![0u32];
    let mut neighbour_ids = Vec::new();
    let mut lcf_features = Vec::new();
    for (cell, list) in lists.iter().enumerate() {
        neighbour_ids.extend_from_slice(list);
        neighbour_offsets.push(neighbour_ids.len() as u32);
        let slot = (cell % agents) as f32;
        lcf_features.extend([list.len() as f32 / 20.0, 0.5, 0.3, 0.1 * (slot + 1.0), 0.5]);
    }
    debug_assert_eq!(lcf_features.len(), cells * lcf::FEATURES);
    RolloutFragment {
        steps,
        agents,
        obs_dim: 2,
        action_dim: 2,
        obs,
        actions,
        log_probs: vec![-2.0; cells],
        rewards: (0..cells).map(|i| (i % 3) as f32 - 0.5).collect(),
        costs: vec![0.0; cells],
        dones,
        alive,
        bootstrap_obs: (0..agents).flat_map(|s| [100.0 + s as f32, 7.0]).collect(),
        neighbour_offsets,
        neighbour_ids,
        lcf_features,
        ..RolloutFragment::default()
    }
}

/// The batch of `fragment` with every critic predicting `value` (so GAE can be worked by
/// hand): `coordination`'s heads, `gamma` where a head does not set its own.
pub fn constant_critic_batch(
    coordination: &dyn Coordination,
    fragment: &RolloutFragment,
    value: f32,
    gamma: f32,
    lambda: f32,
) -> TrainBatch {
    let heads: Vec<Head> = coordination
        .signals()
        .iter()
        .enumerate()
        .map(|(index, signal)| Head {
            rewards: vec![coordination.rewards(index, fragment).unwrap()],
            value: Box::new(move |x: &Tensor| {
                Tensor::full([x.size()[0]], f64::from(value), (Kind::Float, x.device()))
            }),
            gamma: signal.gamma.unwrap_or(gamma),
            outlives_agent: signal.outlives_agent,
        })
        .collect();
    let fragments = std::slice::from_ref(fragment);
    assemble(
        fragments,
        &OwnObservation,
        &heads,
        Tensor::shallow_clone,
        lambda,
        Device::Cpu,
        &mut Phases::default(),
    )
    .unwrap()
}

/// `raw` as if the normaliser were the identity, so expected rows can be hand-computed.
pub fn unnormalized(raw: &RolloutFragment) -> NormalizedFragment<'_> {
    NormalizedFragment {
        raw,
        obs: raw.obs.clone(),
        bootstrap_obs: raw.bootstrap_obs.clone(),
    }
}

/// The critic row of `slot` at `t` (own = its observation there) and its bootstrap row.
pub fn rows(input: &impl CriticInput, f: &NormalizedFragment, t: usize, slot: usize) -> Vec<f32> {
    let mut out = Vec::new();
    input.row(f, f.obs(t, slot), t, slot, &mut out);
    out
}

/// Equal up to float rounding, with both sides shown on failure.
pub fn close(got: &[f32], expected: &[f32]) {
    assert_eq!(got.len(), expected.len(), "{got:?}");
    for (g, e) in got.iter().zip(expected) {
        assert!((g - e).abs() < 1e-6, "got {got:?}, expected {expected:?}");
    }
}

pub fn host_state(algo: &dyn Algorithm) -> Vec<(String, Vec<f32>)> {
    algo.state_tensors()
        .into_iter()
        .map(|(n, t)| (n, Vec::<f32>::try_from(t.flatten(0, -1)).unwrap()))
        .collect()
}

/// A one-step bandit round: every slot acts once on `obs` (rows of `obs_dim`) and is done,
/// with no neighbours.
pub fn one_step_fragment(
    obs: Vec<f32>,
    obs_dim: usize,
    actions: Vec<f32>,
    log_probs: Vec<f32>,
    rewards: Vec<f32>,
) -> RolloutFragment {
    let agents = rewards.len();
    RolloutFragment {
        steps: 1,
        agents,
        obs_dim,
        action_dim: 2,
        obs,
        actions,
        log_probs,
        rewards,
        costs: vec![0.0; agents],
        dones: vec![true; agents],
        alive: vec![true; agents],
        bootstrap_obs: vec![0.0; agents * obs_dim],
        neighbour_offsets: vec![0; agents + 1],
        lcf_features: vec![0.0; agents * lcf::FEATURES],
        ..RolloutFragment::default()
    }
}

/// A learner restored from another's checkpoint holds the same state and, given the same
/// fragment, makes the same next update (policy, critic and Adam moments alike).
pub fn assert_checkpoint_round_trip<A: Algorithm>(make: impl Fn() -> A) {
    assert_checkpoint_round_trip_on(make, &neighbourhood_fragment());
}

/// [`assert_checkpoint_round_trip`] on `fragment`; the restored learner gets the policy
/// blob actors would (with its metadata).
pub fn assert_checkpoint_round_trip_on<A: Algorithm>(
    make: impl Fn() -> A,
    fragment: &RolloutFragment,
) {
    // Seeds only the learners' first initialisation; b is restored from a's state, and
    // their updates draw nothing from the generator, so this needs no test_rng lock (the
    // callers may hold it).
    tch::manual_seed(3);
    let fragment = fragment.clone();
    let mut a = make();
    a.update(std::slice::from_ref(&fragment)).unwrap();
    let state = a.state_tensors();
    let refs: Vec<(String, &Tensor)> = state.iter().map(|(n, t)| (n.clone(), t)).collect();
    let bytes = weights::encode(&refs, Default::default()).unwrap();
    let mut b = make();
    b.restore(
        &a.policy_bytes(1).unwrap(),
        &mut Decoded::decode(&bytes).unwrap(),
    )
    .unwrap();
    assert_eq!(host_state(&a), host_state(&b), "restored state");
    a.update(std::slice::from_ref(&fragment)).unwrap();
    b.update(std::slice::from_ref(&fragment)).unwrap();
    assert_eq!(
        a.policy_bytes(2).unwrap(),
        b.policy_bytes(2).unwrap(),
        "policy after the next update"
    );
    assert_eq!(
        host_state(&a),
        host_state(&b),
        "state after the next update"
    );
}
