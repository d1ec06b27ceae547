//! The shared policy: a diagonal Gaussian over actions from an MLP (PPO's), or a Q-network over
//! a grid of actions (DQN's, [`crate::q_policy`]), with the observation normaliser's statistics
//! stored beside the weights so actors normalise exactly as the learner trained. One parameter
//! set serves every agent (parameter sharing). Actors, `actor render` and evaluation drive
//! either kind through the [`Policy`] trait; the blob's metadata says which kind it is, and
//! `any_policy::decode` rebuilds whichever it holds.

use std::collections::BTreeMap;

use rand::RngCore;
use rand_distr::{Distribution, StandardNormal};
use tch::nn::{self, Module};
use tch::{Device, Kind, Tensor};

use crate::mlp::{Mlp, MlpPass};
use crate::weights::{self, Decoded, WeightsError};
use junction_core::config::ActionStd;
use junction_core::spec::OBS_LAYOUT_VERSION;

/// Normalised observations are clipped to ± this many standard deviations.
const OBS_CLIP: f64 = 10.0;
const OBS_VAR_EPS: f64 = 1e-8;

/// Running mean and variance of observations (Chan et al.'s parallel update), in f64.
#[derive(Debug, Clone, PartialEq)]
pub struct ObsNormalizer {
    pub mean: Vec<f64>,
    pub var: Vec<f64>,
    pub count: f64,
}

impl ObsNormalizer {
    pub fn new(dim: usize) -> Self {
        ObsNormalizer {
            mean: vec![0.0; dim],
            var: vec![1.0; dim],
            count: 0.0,
        }
    }

    /// Folds in `rows` (row-major, `mean.len()` values each).
    pub fn update(&mut self, rows: &[f32]) {
        let dim = self.mean.len();
        let n = (rows.len() / dim) as f64;
        if n == 0.0 {
            return;
        }
        let mut batch_mean = vec![0.0f64; dim];
        for row in rows.chunks_exact(dim) {
            for (m, &x) in batch_mean.iter_mut().zip(row) {
                *m += x as f64;
            }
        }
        batch_mean.iter_mut().for_each(|m| *m /= n);
        let mut batch_var = vec![0.0f64; dim];
        for row in rows.chunks_exact(dim) {
            for ((v, &x), m) in batch_var.iter_mut().zip(row).zip(&batch_mean) {
                *v += (x as f64 - m).powi(2);
            }
        }
        batch_var.iter_mut().for_each(|v| *v /= n);
        let total = self.count + n;
        for i in 0..dim {
            let delta = batch_mean[i] - self.mean[i];
            let m2 = self.var[i] * self.count
                + batch_var[i] * n
                + delta * delta * self.count * n / total;
            self.mean[i] += delta * n / total;
            self.var[i] = m2 / total;
        }
        self.count = total;
    }
}

/// The normaliser's statistics as (non-trained) variables of a policy's store, so they travel
/// in its blob: `obs_norm.{mean,var,count}`.
#[derive(Debug)]
pub struct ObsNormTensors {
    mean: Tensor,
    var: Tensor,
    count: Tensor,
}

impl ObsNormTensors {
    pub fn new(root: &nn::Path, obs_dim: i64) -> Self {
        let norm = root / "obs_norm";
        ObsNormTensors {
            mean: norm.zeros_no_train("mean", &[obs_dim]),
            var: norm.ones_no_train("var", &[obs_dim]),
            count: norm.zeros_no_train("count", &[1]),
        }
    }

    /// (obs − mean) / std, clipped: what the network sees.
    pub fn normalize(&self, obs: &Tensor) -> Tensor {
        ((obs - &self.mean) / (&self.var + OBS_VAR_EPS).sqrt()).clamp(-OBS_CLIP, OBS_CLIP)
    }

    pub fn set(&mut self, stats: &ObsNormalizer) {
        let device = self.mean.device();
        let to = |v: &[f64]| Tensor::from_slice(v).to_kind(Kind::Float).to_device(device);
        tch::no_grad(|| {
            self.mean.copy_(&to(&stats.mean));
            self.var.copy_(&to(&stats.var));
            self.count.copy_(&to(&[stats.count]));
        });
    }

    pub fn get(&self) -> Result<ObsNormalizer, WeightsError> {
        let host = |t: &Tensor| -> Result<Vec<f64>, WeightsError> {
            Ok(Vec::<f32>::try_from(t.to_device(Device::Cpu))?
                .into_iter()
                .map(f64::from)
                .collect())
        };
        Ok(ObsNormalizer {
            mean: host(&self.mean)?,
            var: host(&self.var)?,
            count: host(&self.count)?.first().copied().unwrap_or(0.0),
        })
    }
}

/// Version and layout of a weights blob.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PolicyMeta {
    pub version: u64,
    pub obs_layout_version: u32,
}

impl PolicyMeta {
    pub fn read(decoded: &Decoded) -> Result<Self, WeightsError> {
        Ok(PolicyMeta {
            version: decoded.meta("version")?,
            obs_layout_version: decoded.meta("obs_layout_version")?,
        })
    }
}

/// Metadata key naming the policy kind of a blob; blobs without it are Gaussian (they predate
/// the Q-policy).
pub const KIND_KEY: &str = "policy";

/// What actors, `actor render` and evaluation need from a broadcast policy, whatever its kind.
pub trait Policy: Send + std::fmt::Debug {
    fn obs_dim(&self) -> usize;
    /// Values per action (`spec::ACTION_DIM` for every policy the simulator can use).
    fn action_dim(&self) -> usize;
    /// Batched behaviour: `obs` row-major [rows][obs_dim]; returns the actions to apply
    /// [rows][action_dim] and their log-probabilities under this policy, drawing every random
    /// choice from `rng` (the same draws give the same actions).
    fn sample(
        &self,
        obs: &[f32],
        rng: &mut dyn RngCore,
    ) -> Result<(Vec<f32>, Vec<f32>), WeightsError>;
    /// The deterministic action of each row: the Gaussian's mean, the Q-policy's greedy choice.
    fn deterministic(&self, obs: &[f32]) -> Result<Vec<f32>, WeightsError>;
    /// The weights blob broadcast to actors and stored in checkpoints.
    fn to_bytes(&self, version: u64) -> Result<Vec<u8>, WeightsError>;
}

/// `hidden` metadata: layer sizes joined by commas.
pub fn hidden_to_meta(hidden: &[i64]) -> String {
    hidden
        .iter()
        .map(i64::to_string)
        .collect::<Vec<_>>()
        .join(",")
}

/// Parses `hidden` metadata; sizes must be positive and sane.
pub fn hidden_from_meta(decoded: &Decoded) -> Result<Vec<i64>, WeightsError> {
    let text: String = decoded.meta("hidden")?;
    text.split(',')
        .map(|h| {
            h.parse::<i64>()
                .ok()
                .filter(|&h| h > 0 && h <= junction_core::config::MAX_HIDDEN_WIDTH)
        })
        .collect::<Option<Vec<i64>>>()
        .filter(|h| !h.is_empty() && h.len() <= junction_core::config::MAX_HIDDEN_LAYERS)
        .ok_or_else(|| WeightsError::Metadata {
            key: "hidden".into(),
        })
}

/// `obs_dim` metadata, within the fragment limits.
pub fn obs_dim_from_meta(decoded: &Decoded) -> Result<i64, WeightsError> {
    let obs_dim: i64 = decoded.meta("obs_dim")?;
    if obs_dim > 0 && obs_dim as usize <= junction_core::spec::MAX_OBS_DIM {
        Ok(obs_dim)
    } else {
        Err(WeightsError::Metadata {
            key: "obs_dim".into(),
        })
    }
}

/// Metadata key of a blob's [`ActionStd`]; blobs without it have a global one (they predate
/// the choice).
const ACTION_STD_KEY: &str = "action_std";

#[derive(Debug)]
pub struct GaussianPolicy {
    vs: nn::VarStore,
    /// The mean, and with a state-dependent std its log-offset from `log_std` too.
    net: Mlp,
    /// The log-std (global), or the learned bias the network's log-std output is added to.
    log_std: Tensor,
    action_std: ActionStd,
    norm: ObsNormTensors,
    obs_dim: i64,
    action_dim: i64,
    hidden: Vec<i64>,
}

impl GaussianPolicy {
    /// [`KIND_KEY`] value of its blobs.
    pub const KIND: &'static str = "gaussian";

    /// A policy with one global log-std per action value.
    pub fn new(
        device: Device,
        obs_dim: i64,
        action_dim: i64,
        hidden: &[i64],
        init_log_std: f64,
    ) -> Self {
        Self::with_std(
            device,
            obs_dim,
            action_dim,
            hidden,
            init_log_std,
            ActionStd::Global,
        )
    }

    /// A policy whose std is `action_std`; its log-std starts near `init_log_std` either way
    /// (a state-dependent output starts near 0 on top of the bias).
    pub fn with_std(
        device: Device,
        obs_dim: i64,
        action_dim: i64,
        hidden: &[i64],
        init_log_std: f64,
        action_std: ActionStd,
    ) -> Self {
        let vs = nn::VarStore::new(device);
        let root = vs.root();
        let outputs = match action_std {
            ActionStd::Global => action_dim,
            ActionStd::State => 2 * action_dim,
        };
        let net = Mlp::new(&root / "policy", obs_dim, hidden, outputs, 0.01);
        let log_std = root.var(
            "policy_log_std",
            &[action_dim],
            nn::Init::Const(init_log_std),
        );
        let norm = ObsNormTensors::new(&root, obs_dim);
        GaussianPolicy {
            vs,
            net,
            log_std,
            action_std,
            norm,
            obs_dim,
            action_dim,
            hidden: hidden.to_vec(),
        }
    }

    pub fn obs_dim(&self) -> usize {
        self.obs_dim as usize
    }

    pub fn action_dim(&self) -> usize {
        self.action_dim as usize
    }

    pub fn device(&self) -> Device {
        self.vs.device()
    }

    /// Parameters the optimiser trains (network and log-std; not the normaliser).
    pub fn trainable(&self) -> Vec<Tensor> {
        self.vs.trainable_variables()
    }

    pub fn set_obs_stats(&mut self, stats: &ObsNormalizer) {
        self.norm.set(stats);
    }

    pub fn obs_stats(&self) -> Result<ObsNormalizer, WeightsError> {
        self.norm.get()
    }

    /// (obs − mean) / std, clipped: what the network sees.
    pub fn normalize(&self, obs: &Tensor) -> Tensor {
        self.norm.normalize(obs)
    }

    /// Mean action and log-std, one row per normalised observation.
    pub fn distribution(&self, obs_normalized: &Tensor) -> (Tensor, Tensor) {
        self.head(&self.net.forward(obs_normalized))
    }

    /// The network's pass for hand-written gradients: the update builds its loss on
    /// `head(&pass.output)`, then calls `pass.backward()` ([`Mlp::forward_pass`]).
    pub fn forward_pass(&self, obs_normalized: &Tensor) -> MlpPass<'_> {
        self.net.forward_pass(obs_normalized)
    }

    /// Mean action and log-std from the network's output rows.
    pub fn head(&self, out: &Tensor) -> (Tensor, Tensor) {
        match self.action_std {
            ActionStd::Global => (out.shallow_clone(), self.log_std.expand_as(out)),
            ActionStd::State => {
                let (mean, offset) = (
                    out.narrow(-1, 0, self.action_dim),
                    out.narrow(-1, self.action_dim, self.action_dim),
                );
                (mean, offset + &self.log_std)
            }
        }
    }

    pub fn action_std(&self) -> ActionStd {
        self.action_std
    }

    /// Holds the learned global log-std at or under `ceiling` (`ppo.log_std_cap`): a value
    /// under it is left as it is.
    pub fn cap_log_std(&self, ceiling: f64) {
        tch::no_grad(|| {
            let _ = self.log_std.shallow_clone().clamp_max_(ceiling);
        });
    }

    /// Batched inference for actors: `obs` row-major [rows][obs_dim]; `noise` [rows][action_dim]
    /// standard normal draws (all zero gives the mean action). Returns actions and their
    /// log-probabilities under this policy.
    pub fn act(&self, obs: &[f32], noise: &[f32]) -> Result<(Vec<f32>, Vec<f32>), WeightsError> {
        let rows = (obs.len() / self.obs_dim as usize) as i64;
        tch::no_grad(|| {
            let device = self.vs.device();
            let obs = Tensor::from_slice(obs)
                .reshape([rows, self.obs_dim])
                .to_device(device);
            let noise = Tensor::from_slice(noise)
                .reshape([rows, self.action_dim])
                .to_device(device);
            let (mean, log_std) = self.head(&self.net.infer(&self.normalize(&obs)));
            let actions = &mean + log_std.exp() * noise;
            let log_probs = gaussian_log_prob(&mean, &log_std, &actions);
            let actions = Vec::<f32>::try_from(actions.to_device(Device::Cpu).flatten(0, -1))?;
            let log_probs = Vec::<f32>::try_from(log_probs.to_device(Device::Cpu))?;
            Ok((actions, log_probs))
        })
    }

    /// Every variable by name (for checkpoints and the wire).
    pub fn named_tensors(&self) -> Vec<(String, Tensor)> {
        weights::var_store_tensors(&self.vs)
    }

    /// The weights blob broadcast to actors and stored in checkpoints.
    pub fn to_bytes(&self, version: u64) -> Result<Vec<u8>, WeightsError> {
        self.to_bytes_with_metadata(version, BTreeMap::new())
    }

    /// The blob with `extra` metadata beside the architecture's (e.g. CoPO's LCF
    /// distribution, which actors need to build the observation this policy takes).
    pub fn to_bytes_with_metadata(
        &self,
        version: u64,
        extra: BTreeMap<String, String>,
    ) -> Result<Vec<u8>, WeightsError> {
        let named = self.named_tensors();
        let refs: Vec<(String, &Tensor)> = named.iter().map(|(n, t)| (n.clone(), t)).collect();
        let mut metadata = extra;
        metadata.extend([
            (KIND_KEY.to_string(), Self::KIND.to_string()),
            ("version".to_string(), version.to_string()),
            (
                "obs_layout_version".to_string(),
                OBS_LAYOUT_VERSION.to_string(),
            ),
            ("obs_dim".to_string(), self.obs_dim.to_string()),
            ("action_dim".to_string(), self.action_dim.to_string()),
            ("hidden".to_string(), hidden_to_meta(&self.hidden)),
            (
                ACTION_STD_KEY.to_string(),
                self.action_std.label().to_string(),
            ),
        ]);
        weights::encode(&refs, metadata)
    }

    /// Rebuilds a policy from a blob; the architecture comes from the blob's metadata and every
    /// tensor's shape is checked, so a malformed blob is an error, never a panic.
    pub fn from_bytes(bytes: &[u8], device: Device) -> Result<(Self, PolicyMeta), WeightsError> {
        Self::from_decoded(Decoded::decode(bytes)?, device)
    }

    pub(crate) fn from_decoded(
        mut decoded: Decoded,
        device: Device,
    ) -> Result<(Self, PolicyMeta), WeightsError> {
        let meta = PolicyMeta::read(&decoded)?;
        let obs_dim = obs_dim_from_meta(&decoded)?;
        let action_dim: i64 = decoded.meta("action_dim")?;
        let hidden = hidden_from_meta(&decoded)?;
        if !(action_dim > 0 && action_dim as usize <= junction_core::spec::MAX_ACTION_DIM) {
            return Err(WeightsError::Metadata {
                key: "action_dim".into(),
            });
        }
        let action_std = match decoded.metadata.get(ACTION_STD_KEY) {
            None => ActionStd::Global,
            Some(label) => ActionStd::from_label(label).ok_or_else(|| WeightsError::Metadata {
                key: ACTION_STD_KEY.into(),
            })?,
        };
        let outputs = match action_std {
            ActionStd::Global => action_dim,
            ActionStd::State => 2 * action_dim,
        };
        // The log-std beside the network and its normaliser.
        ensure_blob_holds(
            &decoded,
            minimum_values(obs_dim, &hidden, outputs) + action_dim,
        )?;
        let policy =
            GaussianPolicy::with_std(device, obs_dim, action_dim, &hidden, 0.0, action_std);
        weights::load_var_store(&policy.vs, &mut decoded)?;
        Ok((policy, meta))
    }

    /// Loads a blob into this policy (same architecture), e.g. when resuming.
    pub fn load_bytes(&mut self, bytes: &[u8]) -> Result<PolicyMeta, WeightsError> {
        let mut decoded = Decoded::decode(bytes)?;
        let meta = PolicyMeta::read(&decoded)?;
        weights::load_var_store(&self.vs, &mut decoded)?;
        Ok(meta)
    }
}

/// Values an MLP of these sizes stores (weights and biases). Inputs are bounded by the
/// metadata checks, so no overflow.
fn mlp_values(in_dim: i64, hidden: &[i64], out_dim: i64) -> i64 {
    let mut width = in_dim;
    let mut total = 0;
    for &size in hidden.iter().chain(std::iter::once(&out_dim)) {
        total += width * size + size;
        width = size;
    }
    total
}

/// A network is built (allocated) only once the blob is known to hold at least the `needed`
/// values its metadata describes: metadata alone must not be able to ask for gigabytes.
pub(crate) fn ensure_blob_holds(decoded: &Decoded, needed: i64) -> Result<(), WeightsError> {
    if needed > decoded.total_values() {
        return Err(WeightsError::Metadata {
            key: format!(
                "hidden (describes {needed} values, the blob holds {})",
                decoded.total_values()
            ),
        });
    }
    Ok(())
}

/// Values a network of `obs_dim` inputs, `hidden` layers and `out_dim` outputs stores at the
/// least, with its observation normaliser (mean, variance, count).
pub(crate) fn minimum_values(obs_dim: i64, hidden: &[i64], out_dim: i64) -> i64 {
    mlp_values(obs_dim, hidden, out_dim) + 2 * obs_dim + 1
}

impl Policy for GaussianPolicy {
    fn obs_dim(&self) -> usize {
        self.obs_dim as usize
    }

    fn action_dim(&self) -> usize {
        self.action_dim as usize
    }

    /// Mean plus standard-normal noise scaled by the std: one draw per action value, row by row.
    fn sample(
        &self,
        obs: &[f32],
        rng: &mut dyn RngCore,
    ) -> Result<(Vec<f32>, Vec<f32>), WeightsError> {
        let values = obs.len() / self.obs_dim as usize * self.action_dim as usize;
        let noise: Vec<f32> = (0..values).map(|_| StandardNormal.sample(rng)).collect();
        self.act(obs, &noise)
    }

    fn deterministic(&self, obs: &[f32]) -> Result<Vec<f32>, WeightsError> {
        let values = obs.len() / self.obs_dim as usize * self.action_dim as usize;
        Ok(self.act(obs, &vec![0.0; values])?.0)
    }

    fn to_bytes(&self, version: u64) -> Result<Vec<u8>, WeightsError> {
        GaussianPolicy::to_bytes(self, version)
    }
}

/// log N(actions | mean, exp(log_std)), summed over action dimensions (in the inputs'
/// precision).
pub fn gaussian_log_prob(mean: &Tensor, log_std: &Tensor, actions: &Tensor) -> Tensor {
    let z = (actions - mean) / log_std.exp();
    let per_dim = z.square() * -0.5 - log_std - 0.5 * (2.0 * std::f64::consts::PI).ln();
    per_dim.sum_dim_intlist(-1, false, per_dim.kind())
}

/// KL(p ‖ q) of two diagonal Gaussians, summed over action dimensions.
pub fn gaussian_kl(
    mean_p: &Tensor,
    log_std_p: &Tensor,
    mean_q: &Tensor,
    log_std_q: &Tensor,
) -> Tensor {
    let var_q = (log_std_q * 2.0).exp();
    let per_dim = log_std_q - log_std_p
        + ((log_std_p * 2.0).exp() + (mean_p - mean_q).square()) / (var_q * 2.0)
        - 0.5;
    per_dim.sum_dim_intlist(-1, false, per_dim.kind())
}

/// Entropy of the diagonal Gaussian, summed over action dimensions.
pub fn gaussian_entropy(log_std: &Tensor) -> Tensor {
    (log_std + 0.5 * (1.0 + (2.0 * std::f64::consts::PI).ln())).sum_dim_intlist(
        -1,
        false,
        Kind::Float,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaussian_kl_by_hand_and_zero_for_equal_distributions() {
        // p = N(0, 1), q = N(1, 2²) in one dimension: ln 2 + (1 + 1)/8 − ½.
        let t = |v: &[f32]| Tensor::from_slice(v).reshape([1, v.len() as i64]);
        let kl = gaussian_kl(&t(&[0.0]), &t(&[0.0]), &t(&[1.0]), &t(&[2f32.ln()]));
        let expected = 2f64.ln() + 0.25 - 0.5;
        assert!((f64::try_from(kl.sum(Kind::Float)).unwrap() - expected).abs() < 1e-6);
        let same = gaussian_kl(
            &t(&[0.3, -1.0]),
            &t(&[0.1, 0.2]),
            &t(&[0.3, -1.0]),
            &t(&[0.1, 0.2]),
        );
        assert!(f64::try_from(same.sum(Kind::Float)).unwrap().abs() < 1e-7);
    }

    #[test]
    fn normalizer_matches_two_pass_statistics() {
        let rows: Vec<f32> = vec![1.0, 10.0, 2.0, 20.0, 3.0, 30.0, 4.0, 40.0, 5.0, 50.0];
        let mut n = ObsNormalizer::new(2);
        n.update(&rows[..4]);
        n.update(&rows[4..]);
        assert_eq!(n.count, 5.0);
        assert!((n.mean[0] - 3.0).abs() < 1e-12 && (n.mean[1] - 30.0).abs() < 1e-12);
        // Population variance of 1..5 is 2.
        assert!((n.var[0] - 2.0).abs() < 1e-12 && (n.var[1] - 200.0).abs() < 1e-9);
    }

    #[test]
    fn log_prob_matches_closed_form() {
        let mean = Tensor::from_slice(&[0.0f32, 1.0]).reshape([1, 2]);
        let log_std = Tensor::from_slice(&[0.0f32, (2.0f32).ln()]).reshape([1, 2]);
        let a = Tensor::from_slice(&[1.0f32, 1.0]).reshape([1, 2]);
        let lp = f64::try_from(gaussian_log_prob(&mean, &log_std, &a).sum(Kind::Float)).unwrap();
        let ln2pi = (2.0 * std::f64::consts::PI).ln();
        let expected = (-0.5 - 0.5 * ln2pi) + (-(2.0f64).ln() - 0.5 * ln2pi);
        assert!((lp - expected).abs() < 1e-5, "{lp} vs {expected}");
        let h = f64::try_from(gaussian_entropy(&log_std).sum(Kind::Float)).unwrap();
        assert!((h - (ln2pi + 1.0 + (2.0f64).ln())).abs() < 1e-5);
    }

    /// A blob with `metadata` and one small tensor.
    fn blob_with_metadata(metadata: &[(&str, &str)]) -> Vec<u8> {
        let metadata = metadata
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        let x = Tensor::from_slice(&[1.0f32; 4]);
        weights::encode(&[("x".into(), &x)], metadata).unwrap()
    }

    #[test]
    fn hostile_metadata_is_refused_before_anything_is_allocated() {
        let base = [
            ("version", "1"),
            ("obs_layout_version", "1"),
            ("obs_dim", "65536"),
            ("action_dim", "2"),
        ];
        // 16 layers of 65536 would be ~69 G values: refused from the blob's 4 values alone.
        let huge = vec!["65536"; 16].join(",");
        for hidden in [huge.as_str(), "65536,65536", "8"] {
            let mut metadata = base.to_vec();
            metadata.push(("hidden", hidden));
            let err = GaussianPolicy::from_bytes(&blob_with_metadata(&metadata), Device::Cpu)
                .unwrap_err();
            assert!(
                matches!(err, WeightsError::Metadata { .. }),
                "{hidden}: {err}"
            );
        }
        for (key, value) in [
            ("hidden", "0"),
            ("hidden", "-3"),
            ("hidden", ""),
            ("hidden", "65537"),
            ("obs_dim", "0"),
            ("action_dim", "65"),
            ("version", "not a number"),
        ] {
            let mut metadata: Vec<(&str, &str)> = base.to_vec();
            metadata.retain(|(k, _)| *k != key);
            metadata.push((key, value));
            if key != "hidden" {
                metadata.push(("hidden", "8"));
            }
            assert!(
                GaussianPolicy::from_bytes(&blob_with_metadata(&metadata), Device::Cpu).is_err(),
                "{key} = {value:?} was accepted"
            );
        }
        // Too many layers, even small ones.
        let mut metadata = base.to_vec();
        let many = vec!["1"; junction_core::config::MAX_HIDDEN_LAYERS + 1].join(",");
        metadata.push(("hidden", &many));
        assert!(GaussianPolicy::from_bytes(&blob_with_metadata(&metadata), Device::Cpu).is_err());
    }

    #[test]
    fn weights_round_trip_reproduce_actions_and_reject_other_shapes() {
        tch::manual_seed(3);
        let mut p = GaussianPolicy::new(Device::Cpu, 5, 2, &[8, 8], -0.5);
        let mut stats = ObsNormalizer::new(5);
        stats.update(&[0.0, 1.0, 2.0, 3.0, 4.0, 1.0, 1.0, 1.0, 1.0, 1.0]);
        p.set_obs_stats(&stats);
        let obs = [0.1f32, 0.2, 0.3, 0.4, 0.5, 0.9, 0.8, 0.7, 0.6, 0.5];
        let noise = [0.3f32, -1.0, 0.0, 2.0];
        let before = p.act(&obs, &noise).unwrap();
        let bytes = p.to_bytes(42).unwrap();
        let (q, meta) = GaussianPolicy::from_bytes(&bytes, Device::Cpu).unwrap();
        assert_eq!(
            meta,
            PolicyMeta {
                version: 42,
                obs_layout_version: OBS_LAYOUT_VERSION
            }
        );
        assert_eq!(q.act(&obs, &noise).unwrap(), before);
        assert_eq!(q.obs_stats().unwrap().count, 2.0);
        let mut other = GaussianPolicy::new(Device::Cpu, 5, 2, &[16], 0.0);
        assert!(matches!(
            other.load_bytes(&bytes),
            Err(WeightsError::Missing(_) | WeightsError::Shape { .. })
        ));
    }

    #[test]
    fn a_state_dependent_std_varies_by_state_and_travels_in_the_blob() {
        tch::manual_seed(4);
        let p = GaussianPolicy::with_std(Device::Cpu, 5, 2, &[8], -0.5, ActionStd::State);
        let obs = Tensor::from_slice(&[0.1f32, 0.2, 0.3, 0.4, 0.5, -3.0, 2.0, 0.0, 1.0, -1.0])
            .reshape([2, 5]);
        let (mean, log_std) = p.distribution(&obs);
        assert_eq!((mean.size(), log_std.size()), (vec![2, 2], vec![2, 2]));
        let log_std = Vec::<f32>::try_from(log_std.flatten(0, -1)).unwrap();
        assert_ne!(log_std[..2], log_std[2..], "one std per state");
        // Near the initial value: the network's offset starts small.
        assert!(log_std.iter().all(|l| (l + 0.5).abs() < 0.1), "{log_std:?}");
        let noise = [0.3f32, -1.0, 0.5, 2.0];
        let flat: Vec<f32> = Vec::<f32>::try_from(obs.flatten(0, -1)).unwrap();
        let bytes = p.to_bytes(7).unwrap();
        let (q, _) = GaussianPolicy::from_bytes(&bytes, Device::Cpu).unwrap();
        assert_eq!(q.action_std(), ActionStd::State);
        assert_eq!(q.act(&flat, &noise).unwrap(), p.act(&flat, &noise).unwrap());
        // A global-std policy of the same layers cannot take its weights, nor the reverse.
        let mut global = GaussianPolicy::new(Device::Cpu, 5, 2, &[8], -0.5);
        assert!(global.load_bytes(&bytes).is_err());
        let mut state = GaussianPolicy::with_std(Device::Cpu, 5, 2, &[8], -0.5, ActionStd::State);
        assert!(state.load_bytes(&global.to_bytes(1).unwrap()).is_err());
        // An unknown kind of std in the metadata is refused, not guessed.
        let named = p.named_tensors();
        let refs: Vec<(String, &Tensor)> = named.iter().map(|(n, t)| (n.clone(), t)).collect();
        let mut metadata: BTreeMap<String, String> = [
            ("version", "1"),
            ("obs_layout_version", "1"),
            ("obs_dim", "5"),
            ("action_dim", "2"),
            ("hidden", "8"),
            ("action_std", "per-episode"),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect();
        metadata.insert("obs_layout_version".into(), OBS_LAYOUT_VERSION.to_string());
        let odd = weights::encode(&refs, metadata).unwrap();
        assert!(matches!(
            GaussianPolicy::from_bytes(&odd, Device::Cpu),
            Err(WeightsError::Metadata { key }) if key == "action_std"
        ));
    }
}
