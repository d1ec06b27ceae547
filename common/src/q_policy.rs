//! DQN's policy: a Q-network over a grid of `[steering, throttle_brake]` actions, acting
//! ε-greedily, with the same observation normaliser as the Gaussian policy.
//!
//! The grid is steering values × throttle values, flattened as MetaDrive's `discrete_action`
//! mode does it (`metadrive/policy/env_input_policy.py`): index = throttle_i · |steering| +
//! steering_i. MetaDrive's default is 5 × 5 evenly spaced values in [−1, 1] (`discrete_steering_dim
//! = discrete_throttle_dim = 5`), which is also `[dqn]`'s default. Actors apply and ship the grid
//! point itself, so fragments stay continuous for every consumer; the learner maps it back to
//! its index exactly. The blob carries the grid and ε, so an actor needs no configuration: it
//! acts with whatever the learner broadcasts.

use std::collections::BTreeMap;

use rand::{Rng, RngCore};
use tch::nn::{self, Module};
use tch::{Device, Kind, Tensor};

use crate::mlp::Mlp;
use crate::policy::{
    KIND_KEY, ObsNormTensors, ObsNormalizer, Policy, PolicyMeta, ensure_blob_holds,
    hidden_from_meta, hidden_to_meta, minimum_values, obs_dim_from_meta,
};
use crate::weights::{self, Decoded, WeightsError};
use junction_core::spec::{ACTION_DIM, OBS_LAYOUT_VERSION};

use junction_core::action_grid::ActionGrid;

/// A grid's values as blob metadata (`grid_steering`, `grid_throttle`): comma-separated.
fn grid_values_to_meta(values: &[f32]) -> String {
    values
        .iter()
        .map(f32::to_string)
        .collect::<Vec<_>>()
        .join(",")
}

/// The grid a blob's metadata describes.
fn grid_from_meta(decoded: &Decoded) -> Result<ActionGrid, WeightsError> {
    let bad = || WeightsError::Metadata {
        key: "grid_steering/grid_throttle".into(),
    };
    let parse = |key: &str| -> Result<Vec<f32>, WeightsError> {
        let text: String = decoded.meta(key)?;
        text.split(',')
            .map(|v| v.parse::<f32>().map_err(|_| bad()))
            .collect()
    };
    ActionGrid::new(parse("grid_steering")?, parse("grid_throttle")?).map_err(|_| bad())
}

/// Q(s, ·) over the grid from an MLP on normalised observations; acts ε-greedily.
#[derive(Debug)]
pub struct QPolicy {
    vs: nn::VarStore,
    net: Mlp,
    norm: ObsNormTensors,
    grid: ActionGrid,
    /// Dueling head (Wang et al. 2016): the network outputs V(s) and A(s, ·), and
    /// Q = V + A − mean(A).
    dueling: bool,
    /// Probability of a uniformly random grid action instead of the greedy one.
    epsilon: f64,
    obs_dim: i64,
    hidden: Vec<i64>,
}

impl QPolicy {
    /// [`KIND_KEY`] value of its blobs.
    pub const KIND: &'static str = "q";

    pub fn new(
        device: Device,
        obs_dim: i64,
        hidden: &[i64],
        grid: ActionGrid,
        dueling: bool,
    ) -> Self {
        let vs = nn::VarStore::new(device);
        let root = vs.root();
        let outputs = grid.len() as i64 + i64::from(dueling);
        let net = Mlp::new(&root / "q", obs_dim, hidden, outputs, 1.0);
        let norm = ObsNormTensors::new(&root, obs_dim);
        QPolicy {
            vs,
            net,
            norm,
            grid,
            dueling,
            epsilon: 0.0,
            obs_dim,
            hidden: hidden.to_vec(),
        }
    }

    pub fn grid(&self) -> &ActionGrid {
        &self.grid
    }

    pub fn epsilon(&self) -> f64 {
        self.epsilon
    }

    /// The exploration rate actors use with the next broadcast of this policy.
    pub fn set_epsilon(&mut self, epsilon: f64) {
        self.epsilon = epsilon.clamp(0.0, 1.0);
    }

    pub fn device(&self) -> Device {
        self.vs.device()
    }

    /// The Q-network's parameters (not the normaliser).
    pub fn trainable(&self) -> Vec<Tensor> {
        self.vs.trainable_variables()
    }

    pub fn set_obs_stats(&mut self, stats: &ObsNormalizer) {
        self.norm.set(stats);
    }

    pub fn obs_stats(&self) -> Result<ObsNormalizer, WeightsError> {
        self.norm.get()
    }

    pub fn normalize(&self, obs: &Tensor) -> Tensor {
        self.norm.normalize(obs)
    }

    /// Q-values [rows, grid.len()] of normalised observations.
    pub fn q_values(&self, obs_normalized: &Tensor) -> Tensor {
        let out = self.net.forward(obs_normalized);
        if !self.dueling {
            return out;
        }
        let value = out.narrow(-1, 0, 1);
        let advantage = out.narrow(-1, 1, self.grid.len() as i64);
        value + &advantage - advantage.mean_dim(-1, true, Kind::Float)
    }

    /// Copies every variable (network and normaliser) of `source`, e.g. to sync a target
    /// network; both must have the same architecture.
    pub fn copy_from(&mut self, source: &QPolicy) -> Result<(), WeightsError> {
        Ok(self.vs.copy(&source.vs)?)
    }

    /// Every variable by name (for checkpoints).
    pub fn named_tensors(&self) -> Vec<(String, Tensor)> {
        weights::var_store_tensors(&self.vs)
    }

    /// The greedy action index of every row of raw observations.
    fn greedy(&self, obs: &[f32]) -> Result<Vec<i64>, WeightsError> {
        let rows = (obs.len() / self.obs_dim as usize) as i64;
        tch::no_grad(|| {
            let obs = Tensor::from_slice(obs)
                .reshape([rows, self.obs_dim])
                .to_device(self.vs.device());
            let best = self.q_values(&self.normalize(&obs)).argmax(-1, false);
            Ok(Vec::<i64>::try_from(best.to_device(Device::Cpu))?)
        })
    }

    fn points(&self, indices: impl Iterator<Item = usize>) -> Vec<f32> {
        indices.flat_map(|i| self.grid.action(i)).collect()
    }

    pub fn from_bytes(bytes: &[u8], device: Device) -> Result<(Self, PolicyMeta), WeightsError> {
        Self::from_decoded(Decoded::decode(bytes)?, device)
    }

    pub(crate) fn from_decoded(
        mut decoded: Decoded,
        device: Device,
    ) -> Result<(Self, PolicyMeta), WeightsError> {
        let meta = PolicyMeta::read(&decoded)?;
        let obs_dim = obs_dim_from_meta(&decoded)?;
        let hidden = hidden_from_meta(&decoded)?;
        let grid = grid_from_meta(&decoded)?;
        let epsilon: f64 = decoded.meta("epsilon")?;
        let dueling: bool = decoded.meta("dueling")?;
        if !(0.0..=1.0).contains(&epsilon) {
            return Err(WeightsError::Metadata {
                key: "epsilon".into(),
            });
        }
        let actions = grid.len() as i64;
        ensure_blob_holds(&decoded, minimum_values(obs_dim, &hidden, actions))?;
        let mut policy = QPolicy::new(device, obs_dim, &hidden, grid, dueling);
        policy.epsilon = epsilon;
        weights::load_var_store(&policy.vs, &mut decoded)?;
        Ok((policy, meta))
    }

    /// Loads a blob of the same architecture and grid into this policy (resuming), ε included.
    pub fn load_bytes(&mut self, bytes: &[u8]) -> Result<PolicyMeta, WeightsError> {
        let mut decoded = Decoded::decode(bytes)?;
        let meta = PolicyMeta::read(&decoded)?;
        if grid_from_meta(&decoded)? != self.grid {
            return Err(WeightsError::Metadata {
                key: "grid_steering/grid_throttle (another grid than the configured one)".into(),
            });
        }
        let epsilon: f64 = decoded.meta("epsilon")?;
        weights::load_var_store(&self.vs, &mut decoded)?;
        self.set_epsilon(epsilon);
        Ok(meta)
    }
}

impl Policy for QPolicy {
    fn obs_dim(&self) -> usize {
        self.obs_dim as usize
    }

    fn action_dim(&self) -> usize {
        ACTION_DIM
    }

    /// ε-greedy: per row one uniform draw decides whether to explore, and an exploring row a
    /// second draw picks its grid point. The log-probability is the behaviour policy's:
    /// ln(ε/|A| + (1 − ε)·[a = greedy]).
    fn sample(
        &self,
        obs: &[f32],
        rng: &mut dyn RngCore,
    ) -> Result<(Vec<f32>, Vec<f32>), WeightsError> {
        let greedy = self.greedy(obs)?;
        let n = self.grid.len();
        let uniform = self.epsilon / n as f64;
        let mut log_probs = Vec::with_capacity(greedy.len());
        let chosen: Vec<usize> = greedy
            .iter()
            .map(|&best| {
                let best = best as usize;
                let action = if rng.r#gen::<f64>() < self.epsilon {
                    rng.gen_range(0..n)
                } else {
                    best
                };
                let greedy_mass = if action == best {
                    1.0 - self.epsilon
                } else {
                    0.0
                };
                log_probs.push((uniform + greedy_mass).ln() as f32);
                action
            })
            .collect();
        Ok((self.points(chosen.into_iter()), log_probs))
    }

    fn deterministic(&self, obs: &[f32]) -> Result<Vec<f32>, WeightsError> {
        let greedy = self.greedy(obs)?;
        Ok(self.points(greedy.into_iter().map(|i| i as usize)))
    }

    fn to_bytes(&self, version: u64) -> Result<Vec<u8>, WeightsError> {
        let named = self.named_tensors();
        let refs: Vec<(String, &Tensor)> = named.iter().map(|(n, t)| (n.clone(), t)).collect();
        let metadata = BTreeMap::from([
            (KIND_KEY.to_string(), Self::KIND.to_string()),
            ("version".to_string(), version.to_string()),
            (
                "obs_layout_version".to_string(),
                OBS_LAYOUT_VERSION.to_string(),
            ),
            ("obs_dim".to_string(), self.obs_dim.to_string()),
            ("action_dim".to_string(), ACTION_DIM.to_string()),
            ("hidden".to_string(), hidden_to_meta(&self.hidden)),
            (
                "grid_steering".to_string(),
                grid_values_to_meta(self.grid.steering()),
            ),
            (
                "grid_throttle".to_string(),
                grid_values_to_meta(self.grid.throttle()),
            ),
            ("epsilon".to_string(), self.epsilon.to_string()),
            ("dueling".to_string(), self.dueling.to_string()),
        ]);
        weights::encode(&refs, metadata)
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use junction_core::action_grid::GridError;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// MetaDrive's 5 × 5 discrete action grid (also the fixture of `any_policy`'s tests).
    pub(crate) fn metadrive_grid() -> ActionGrid {
        let values = vec![-1.0, -0.5, 0.0, 0.5, 1.0];
        ActionGrid::new(values.clone(), values).unwrap()
    }

    #[test]
    fn the_grid_flattens_like_metadrive_and_maps_points_back_exactly() {
        let grid = metadrive_grid();
        assert_eq!(grid.len(), 25);
        // MetaDrive: steering = (a % 5) · 0.5 − 1, throttle = (a // 5) · 0.5 − 1.
        assert_eq!(grid.action(0), [-1.0, -1.0]);
        assert_eq!(grid.action(7), [0.0, -0.5]);
        assert_eq!(grid.action(24), [1.0, 1.0]);
        for index in 0..grid.len() {
            assert_eq!(grid.index_of(&grid.action(index)), Some(index));
        }
        assert_eq!(grid.index_of(&[0.0, 0.25]), None, "off the grid");
        assert_eq!(grid.index_of(&[0.0, 0.5000001]), None, "only exact points");
        assert_eq!(grid.index_of(&[0.0]), None, "wrong arity");
        for (steering, throttle) in [
            (vec![], vec![0.0]),
            (vec![0.5, 0.0], vec![0.0]),
            (vec![0.0, 0.0], vec![0.0]),
            (vec![0.0, 1.5], vec![0.0]),
            (vec![f32::NAN], vec![0.0]),
        ] {
            assert_eq!(ActionGrid::new(steering, throttle), Err(GridError));
        }
    }

    #[test]
    fn epsilon_greedy_acts_on_the_grid_with_the_behaviour_log_probability() {
        tch::manual_seed(4);
        let mut q = QPolicy::new(Device::Cpu, 3, &[8], metadrive_grid(), false);
        let obs: Vec<f32> = (0..300).map(|i| (i % 7) as f32 / 7.0).collect();
        let greedy = q.deterministic(&obs).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let (actions, log_probs) = q.sample(&obs, &mut rng).unwrap();
        assert_eq!(actions, greedy, "ε = 0 is greedy");
        assert!(log_probs.iter().all(|&lp| lp == 0.0));

        q.set_epsilon(0.5);
        let (actions, log_probs) = q.sample(&obs, &mut rng).unwrap();
        let (on_greedy, off) = (
            (0.5f64 / 25.0 + 0.5).ln() as f32,
            (0.5f64 / 25.0).ln() as f32,
        );
        let mut explored = 0;
        for ((action, greedy), lp) in actions.chunks(2).zip(greedy.chunks(2)).zip(&log_probs) {
            assert!(
                q.grid().index_of(action).is_some(),
                "{action:?} off the grid"
            );
            if action == greedy {
                assert_eq!(*lp, on_greedy);
            } else {
                assert_eq!(*lp, off);
                explored += 1;
            }
        }
        // About ε · 24/25 of 100 rows leave the greedy action.
        assert!((25..=70).contains(&explored), "{explored} rows explored");
        // The same draws give the same actions.
        let again = q.sample(&obs, &mut ChaCha8Rng::seed_from_u64(9)).unwrap();
        assert_eq!(
            again,
            q.sample(&obs, &mut ChaCha8Rng::seed_from_u64(9)).unwrap()
        );
    }

    #[test]
    fn a_dueling_head_adds_the_state_value_to_centred_advantages() {
        tch::manual_seed(6);
        let x = Tensor::from_slice(&[0.1f32, -0.4, 0.8, 0.3, 0.0, -1.0]).reshape([2, 3]);
        let dueling = QPolicy::new(Device::Cpu, 3, &[8], metadrive_grid(), true);
        let out = dueling.net.forward(&x);
        assert_eq!(out.size(), [2, 26], "V and 25 advantages");
        let q = dueling.q_values(&x);
        let (value, advantage) = (out.narrow(-1, 0, 1), out.narrow(-1, 1, 25));
        let expected = &value + &advantage - advantage.mean_dim(-1, true, Kind::Float);
        assert!(bool::try_from((&q - expected).abs().max().le(1e-6)).unwrap());
        // Q's mean over actions is V.
        let mean_q = Vec::<f32>::try_from(q.mean_dim(-1, false, Kind::Float)).unwrap();
        let v = Vec::<f32>::try_from(value.squeeze_dim(-1)).unwrap();
        assert!(mean_q.iter().zip(&v).all(|(a, b)| (a - b).abs() < 1e-5));
        // Without the head the network's outputs are Q itself, and the flag travels.
        let plain = QPolicy::new(Device::Cpu, 3, &[8], metadrive_grid(), false);
        assert_eq!(plain.q_values(&x).size(), [2, 25]);
        let (decoded, _) =
            QPolicy::from_bytes(&Policy::to_bytes(&plain, 1).unwrap(), Device::Cpu).unwrap();
        assert!(!decoded.dueling);
    }
}
