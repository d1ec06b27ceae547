//! PPO-Lagrangian (Ray et al. 2019), the safe-RL option of every PPO algorithm (`[safety]`,
//! paper §3.5): a cost critic estimates cost advantages A_c beside the reward advantages A_r,
//! the policy ascends the mixed advantage, and a Lagrange multiplier λ ≥ 0 prices the cost:
//!
//! ```text
//! Â = (Â_r − λ·Â_c) / (1 + λ)                       (the policy's advantage)
//! L = L_PPO(Â) + c_v·(L_V(V_r) + L_V(V_c))
//! after the update: λ ← max(0, λ + η_λ·(mean episode cost − cost limit))
//! ```

use tch::Tensor;
use tch::nn;

use junction_common::fragment::RolloutFragment;
use junction_common::mlp::Mlp;
use junction_core::config::SafetyConfig;

pub struct Lagrangian {
    critic: Mlp,
    /// f32 like every checkpointed tensor, so a restored learner continues exactly.
    multiplier: f32,
    cost_limit: f64,
    multiplier_lr: f64,
}

impl Lagrangian {
    /// A cost critic of input width `width` under `path`, λ at its configured start.
    pub fn new(config: &SafetyConfig, path: nn::Path, width: i64, hidden: &[i64]) -> Self {
        Lagrangian {
            critic: Mlp::new(path, width, hidden, 1, 1.0),
            multiplier: config.initial_multiplier.max(0.0),
            cost_limit: f64::from(config.cost_limit),
            multiplier_lr: f64::from(config.multiplier_lr),
        }
    }

    pub fn multiplier(&self) -> f64 {
        f64::from(self.multiplier)
    }

    pub fn set_multiplier(&mut self, multiplier: f64) {
        self.multiplier = multiplier.max(0.0) as f32;
    }

    /// V_c of each critic-input row.
    /// The cost critic, for the update's hand-written gradients.
    pub fn cost_critic(&self) -> &Mlp {
        &self.critic
    }

    pub fn cost_value(&self, critic_inputs: &Tensor) -> Tensor {
        self.critic.infer(critic_inputs).squeeze_dim(-1)
    }

    /// The policy's advantage: the reward advantage less the priced cost advantage, rescaled
    /// so its size does not grow with λ.
    pub fn mixed_advantage(&self, reward: &Tensor, cost: &Tensor) -> Tensor {
        let price = self.multiplier();
        (reward - cost * price) / (1.0 + price)
    }

    /// Dual ascent on λ from the batch's finished episodes; returns their mean cost (None,
    /// and λ unchanged, when no episode finished in the batch).
    pub fn update_multiplier(&mut self, fragments: &[RolloutFragment]) -> Option<f64> {
        let costs: Vec<f64> = fragments
            .iter()
            .flat_map(|f| &f.episodes)
            .map(|e| f64::from(e.total_cost))
            .collect();
        if costs.is_empty() {
            return None;
        }
        let mean = costs.iter().sum::<f64>() / costs.len() as f64;
        self.set_multiplier(self.multiplier() + self.multiplier_lr * (mean - self.cost_limit));
        Some(mean)
    }

    pub fn multiplier_tensor(&self) -> Tensor {
        Tensor::from_slice(&[self.multiplier])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use junction_core::config::{RunConfig, SafetyMode};
    use junction_core::episode::{EpisodeStats, Outcome};
    use tch::Device;

    fn episode(total_cost: f32) -> EpisodeStats {
        EpisodeStats {
            outcome: Outcome::Crash,
            length: 10,
            total_reward: 0.0,
            mean_abs_accel: 0.0,
            max_abs_accel: 0.0,
            collisions: 1,
            energy_kj: 0.0,
            total_cost,
        }
    }

    fn lagrangian(start: f32) -> Lagrangian {
        let mut config = RunConfig::default().safety;
        config.mode = SafetyMode::Lagrangian;
        config.initial_multiplier = start;
        config.cost_limit = 0.5;
        config.multiplier_lr = 0.1;
        let store = nn::VarStore::new(Device::Cpu);
        Lagrangian::new(&config, store.root() / "cost", 3, &[4])
    }

    #[test]
    fn the_multiplier_rises_above_the_limit_falls_below_it_and_stays_non_negative() {
        let mut l = lagrangian(0.2);
        let costly = RolloutFragment {
            episodes: vec![episode(1.0), episode(2.0)],
            ..RolloutFragment::default()
        };
        // Mean cost 1.5, limit 0.5: λ = 0.2 + 0.1 · 1.0.
        assert_eq!(l.update_multiplier(&[costly]), Some(1.5));
        assert!((l.multiplier() - 0.3).abs() < 1e-6);
        let safe = RolloutFragment {
            episodes: vec![episode(0.0)],
            ..RolloutFragment::default()
        };
        // 0.3 + 0.1 · (0 − 0.5) = 0.25, then down to 0 and no further.
        l.update_multiplier(std::slice::from_ref(&safe));
        assert!((l.multiplier() - 0.25).abs() < 1e-6);
        for _ in 0..10 {
            l.update_multiplier(std::slice::from_ref(&safe));
        }
        assert_eq!(l.multiplier(), 0.0);
        // No finished episode: no information, λ stays.
        assert_eq!(l.update_multiplier(&[RolloutFragment::default()]), None);
        assert_eq!(l.multiplier(), 0.0);
    }

    #[test]
    fn the_mixed_advantage_prices_the_cost_by_the_multiplier() {
        let reward = Tensor::from_slice(&[1.0f32, -1.0]);
        let cost = Tensor::from_slice(&[2.0f32, 0.0]);
        // λ = 0: the reward advantage alone.
        let free = Vec::<f32>::try_from(lagrangian(0.0).mixed_advantage(&reward, &cost)).unwrap();
        assert_eq!(free, vec![1.0, -1.0]);
        // λ = 1: (1 − 2)/2 and (−1 − 0)/2.
        let priced = Vec::<f32>::try_from(lagrangian(1.0).mixed_advantage(&reward, &cost)).unwrap();
        assert_eq!(priced, vec![-0.5, -0.5]);
    }
}
