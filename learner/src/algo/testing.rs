//! Fixtures for the algorithms' tests that need no algorithm: small runs, a fragment with a
//! known neighbourhood, one-step bandit fragments, critic rows of an identity-normalised
//! fragment, a checkpoint round trip for any `Algorithm`, and a tiny f64 Gaussian policy for
//! gradient checks. Compiled for tests only. It imports nothing from `algo/` but the common
//! ground (`Algorithm`, the batch types), so any algorithm's tests may use it; the fixtures
//! that build an IPPO learner are in `ippo::fixtures`, above IPPO.

use tch::{Device, Kind, Tensor};

use junction_common::fragment::RolloutFragment;
use junction_common::policy::gaussian_log_prob;
use junction_common::weights::{self, Decoded};
use junction_core::config::RunConfig;
use junction_core::lcf_inputs;

use super::Algorithm;
use super::batch::{CriticInput, NormalizedFragment};

/// The defaults with a small network (hidden [8]) and seed 7.
pub fn small_run() -> RunConfig {
    let mut run = RunConfig::default();
    run.ppo.hidden = vec![8];
    run.run.seed = 7;
    run
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
    debug_assert_eq!(lcf_features.len(), cells * lcf_inputs::FEATURES);
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
        lcf_features: vec![0.0; agents * lcf_inputs::FEATURES],
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

/// f64 tensors on the CPU, for gradients checked against finite differences.
pub const F64: (Kind, Device) = (Kind::Double, Device::Cpu);

/// `values` as a tensor of `shape`.
pub fn t(values: &[f64], shape: &[i64]) -> Tensor {
    Tensor::from_slice(values).reshape(shape)
}

/// A tiny Gaussian policy in f64: mean = tanh(s·W1)·W2, log-std a free vector.
pub struct Tiny {
    pub w1: Tensor,
    pub w2: Tensor,
    pub log_std: Tensor,
}

impl Tiny {
    pub fn params(&self) -> Vec<Tensor> {
        vec![
            self.w1.shallow_clone(),
            self.w2.shallow_clone(),
            self.log_std.shallow_clone(),
        ]
    }

    pub fn log_probs(&self, obs: &Tensor, actions: &Tensor) -> Tensor {
        let mean = obs.matmul(&self.w1).tanh().matmul(&self.w2);
        gaussian_log_prob(&mean, &self.log_std.expand_as(&mean), actions)
    }

    /// θ + η·step, as fresh leaves.
    pub fn moved(&self, step: &[Tensor], eta: f64) -> Tiny {
        let p = self.params();
        let leaf = |i: usize| (&p[i] + &step[i] * eta).detach().set_requires_grad(true);
        Tiny {
            w1: leaf(0),
            w2: leaf(1),
            log_std: leaf(2),
        }
    }
}
