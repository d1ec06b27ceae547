//! Local coordination inside the shared PPO loop: which reward signals get a value head, how
//! their advantages make the policy's, and what is learned besides the policy. The fixed LCF
//! (`[lcf] phi_deg`) lives here; the learned ones in `copo.rs` and `dynamic_lcf.rs`.

use std::borrow::Cow;
use std::collections::BTreeMap;

use rand_chacha::ChaCha8Rng;
use tch::Tensor;

use junction_common::fragment::RolloutFragment;
use junction_common::lcf::{self, NEIGHBOUR_BUCKETS};
use junction_common::policy::GaussianPolicy;
use junction_common::weights::{Decoded, WeightsError};
use junction_core::config::{LcfConfig, PpoConfig};

use super::AlgoError;
use super::batch::TrainBatch;

/// A value head: the critic's name in checkpoints and its discount (`None`: `ppo.gamma`).
pub struct Signal {
    pub critic: &'static str,
    pub gamma: Option<f32>,
    /// The return goes on after the agent ends, with the scene (`lcf.global_return = "scene"`).
    pub outlives_agent: bool,
}

/// What the learned LCF needs after the PPO epochs.
pub struct MetaStep<'a> {
    pub fragments: &'a [RolloutFragment],
    pub batch: &'a TrainBatch,
    /// The policy before the PPO update (θ) and after it (θ').
    pub before: &'a GaussianPolicy,
    pub after: &'a GaussianPolicy,
    pub ppo: &'a PpoConfig,
    pub rng: &'a mut ChaCha8Rng,
}

/// The LCF angle over an update's batch, degrees.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LcfReport {
    pub mean_deg: f64,
    pub std_deg: f64,
    /// Mean φ of the agents with 0, 1–2, 3–5, 6+ neighbours ([`NEIGHBOUR_BUCKETS`]); `None`
    /// where the batch had none.
    pub by_neighbours: [Option<f64>; NEIGHBOUR_BUCKETS.len()],
}

impl LcfReport {
    /// Mean and spread of φ over rows, and its mean per neighbour-count bucket.
    pub fn from_rows(phi_deg: &[f32], neighbour_counts: &[usize]) -> Self {
        let n = phi_deg.len().max(1) as f64;
        let mean = phi_deg.iter().map(|&p| f64::from(p)).sum::<f64>() / n;
        let var = phi_deg
            .iter()
            .map(|&p| (f64::from(p) - mean).powi(2))
            .sum::<f64>()
            / n;
        let mut sums = [(0.0f64, 0usize); NEIGHBOUR_BUCKETS.len()];
        for (&phi, &count) in phi_deg.iter().zip(neighbour_counts) {
            let bucket = &mut sums[lcf::neighbour_bucket(count)];
            bucket.0 += f64::from(phi);
            bucket.1 += 1;
        }
        LcfReport {
            mean_deg: mean,
            std_deg: var.sqrt(),
            by_neighbours: sums.map(|(sum, count)| (count > 0).then(|| sum / count as f64)),
        }
    }
}

/// How an algorithm coordinates its agents (see the module doc).
pub trait Coordination: Send {
    /// The value heads, the first the one whose loss and explained variance are reported.
    fn signals(&self) -> Vec<Signal>;
    /// Signal `index` for every cell of `fragment`.
    fn rewards<'f>(
        &self,
        index: usize,
        fragment: &'f RolloutFragment,
    ) -> Result<Cow<'f, [f32]>, AlgoError>;
    /// The advantage the policy ascends, per row of `batch`, before standardisation.
    fn policy_advantages(&self, batch: &TrainBatch) -> Result<Tensor, AlgoError>;
    /// Whether [`Coordination::learn`] needs the policy from before the update.
    fn learns(&self) -> bool {
        false
    }
    /// After the PPO epochs: the LCF's own update.
    fn learn(&mut self, _step: MetaStep) -> Result<(), AlgoError> {
        Ok(())
    }
    /// φ over the batch (made from `fragments`), as it stands after [`Coordination::learn`].
    fn report(
        &self,
        fragments: &[RolloutFragment],
        batch: &TrainBatch,
    ) -> Result<LcfReport, AlgoError>;
    /// Metadata actors need besides the weights to run the policy.
    fn policy_metadata(&self) -> BTreeMap<String, String> {
        BTreeMap::new()
    }
    /// Learned state for checkpoints.
    fn state_tensors(&self) -> Vec<(String, Tensor)> {
        Vec::new()
    }
    fn restore(&mut self, _state: &mut Decoded) -> Result<(), WeightsError> {
        Ok(())
    }
}

/// A fixed LCF angle: one critic on r_C = α·cos φ·r_i + β·sin φ·r_N (φ = 0, α = 1: IPPO).
pub struct FixedLcf {
    config: LcfConfig,
}

impl FixedLcf {
    pub fn new(config: &LcfConfig) -> Self {
        FixedLcf {
            config: config.clone(),
        }
    }
}

impl Coordination for FixedLcf {
    fn signals(&self) -> Vec<Signal> {
        vec![Signal {
            critic: "critic",
            gamma: None,
            outlives_agent: false,
        }]
    }

    fn rewards<'f>(
        &self,
        _index: usize,
        fragment: &'f RolloutFragment,
    ) -> Result<Cow<'f, [f32]>, AlgoError> {
        let c = &self.config;
        Ok(lcf::coordinated_rewards(
            fragment,
            c.phi_deg.to_radians(),
            c,
        ))
    }

    fn policy_advantages(&self, batch: &TrainBatch) -> Result<Tensor, AlgoError> {
        Ok(batch.heads[0].advantages.shallow_clone())
    }

    fn report(&self, _: &[RolloutFragment], batch: &TrainBatch) -> Result<LcfReport, AlgoError> {
        let phi = vec![self.config.phi_deg; batch.len];
        Ok(LcfReport::from_rows(&phi, &batch.neighbour_counts))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_report_averages_phi_per_neighbour_bucket_and_skips_empty_buckets() {
        // Counts 0, 2, 1, 7, 0 → buckets 0, 1, 1, 3, 0.
        let report = LcfReport::from_rows(&[10.0, 20.0, 40.0, -30.0, 0.0], &[0, 2, 1, 7, 0]);
        assert_eq!(
            report.by_neighbours,
            [Some(5.0), Some(30.0), None, Some(-30.0)]
        );
        assert!((report.mean_deg - 8.0).abs() < 1e-12);
        // Population std of (10, 20, 40, −30, 0) around 8: √((4 + 144 + 1024 + 1444 + 64)/5).
        let expected = (2680.0f64 / 5.0).sqrt();
        assert!((report.std_deg - expected).abs() < 1e-9, "{report:?}");
    }
}
