//! The local coordination factor's sections: `[lcf]` (the fixed LCF every PPO algorithm
//! takes), `[copo]` and `[dynamic_lcf]` (the learned ones), and `[ccppo]` (the
//! centralised-critic baselines).

use serde::{Deserialize, Serialize};

/// A fixed local coordination factor for every PPO algorithm (paper §3.2).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LcfConfig {
    pub phi_deg: f32,
    pub alpha: f32,
    pub beta: f32,
    /// The global return the learned LCFs (copo, dynamic-lcf) climb.
    pub global_return: GlobalReturn,
    /// What r_N pays an agent for having neighbours.
    pub neighbourhood_reward: NeighbourhoodReward,
}

impl LcfConfig {
    /// What is wrong with the section, one line per problem.
    pub(super) fn problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if !(-90.0..=90.0).contains(&self.phi_deg)
            || !self.alpha.is_finite()
            || !self.beta.is_finite()
        {
            problems.push("lcf.phi_deg must be in [-90, 90] and lcf.alpha, lcf.beta finite".into());
        }
        problems
    }
}

/// The neighbourhood reward r_N of an agent with neighbours.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum NeighbourhoodReward {
    /// The paper's and CoPO's: the neighbours' mean reward. Positive on average, so under
    /// φ > 0 every step spent among neighbours pays, and staying on the road longer does too.
    Mean,
    /// The neighbours' mean reward less its mean over every agent with neighbours in the same
    /// fragment: being among neighbours is worth nothing in itself, their doing better than
    /// neighbourhoods usually do is.
    Centred,
}

/// Where an agent's global return (the scene's mean reward, step by step) ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GlobalReturn {
    /// CoPO's: with the agent, so at γ = 1 an agent's global return grows with its own
    /// lifetime, and waiting (or not arriving) earns it more of the scene's reward.
    Agent,
    /// With the scene: after the agent ends the return goes on, bootstrapped from the agents
    /// still in the scene, as the paper's objective (the scene's total reward) does.
    Scene,
}

/// What is wrong with the learned LCFs' sections: each one's bounds, then each one's
/// meta-gradient (the order `RunConfig::validate` reports them in).
pub(super) fn learned_lcf_problems(copo: &CopoConfig, dynamic: &DynamicLcfConfig) -> Vec<String> {
    [
        copo.distribution_problems(),
        dynamic.network_problems(),
        meta_gradient_problems("copo", copo.lcf_lr, copo.meta_iterations),
        meta_gradient_problems("dynamic_lcf", dynamic.lcf_lr, dynamic.meta_iterations),
    ]
    .concat()
}

/// CoPO's learned LCF distribution (`learner.algo = "copo"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CopoConfig {
    /// μ of N(μ, σ) before any meta-gradient step, degrees.
    pub initial_mean_deg: f32,
    /// σ before any meta-gradient step, degrees.
    pub initial_std_deg: f32,
    /// Bound of μ, degrees: μ = max_mean_deg·tanh(ψ_0).
    pub max_mean_deg: f32,
    /// Adam step size of the meta-gradient on (μ, log σ).
    pub lcf_lr: f64,
    /// Passes over the batch's minibatches of the meta-gradient after each PPO update.
    pub meta_iterations: usize,
    /// Estimate the meta-gradient's two factors from different fragments of the batch.
    pub meta_cross_fit: bool,
}

impl CopoConfig {
    /// The LCF distribution's bound and starting point.
    fn distribution_problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        // Written so NaN fails too.
        let bound_ok = self.max_mean_deg > 0.0 && self.max_mean_deg <= 90.0;
        let mean_ok = self.initial_mean_deg.abs() < self.max_mean_deg;
        let std_ok = self.initial_std_deg > 0.0 && self.initial_std_deg.is_finite();
        if !(bound_ok && mean_ok && std_ok) {
            problems.push(
                "copo.max_mean_deg must be in (0, 90], copo.initial_mean_deg within \
                 (-max_mean_deg, max_mean_deg) and copo.initial_std_deg > 0"
                    .into(),
            );
        }
        problems
    }
}

/// The paper's dynamic LCF φ = f_ψ(S_N) (`learner.algo = "dynamic-lcf"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DynamicLcfConfig {
    /// Hidden layer sizes of f_ψ (tanh).
    pub hidden: Vec<i64>,
    /// Adam step size of the meta-gradient on ψ.
    pub lcf_lr: f64,
    /// Passes over the batch's minibatches of the meta-gradient after each PPO update.
    pub meta_iterations: usize,
    /// Estimate the meta-gradient's two factors from different fragments of the batch.
    pub meta_cross_fit: bool,
    /// Bound of φ, degrees: φ = max_phi_deg · tanh(f_ψ).
    pub max_phi_deg: f32,
    /// Largest mean change of φ over a batch per update, degrees (0 = unpaced).
    pub max_phi_step_deg: f32,
}

impl DynamicLcfConfig {
    /// f_ψ's layers and the bounds of the φ it gives.
    fn network_problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if self.hidden.is_empty() || self.hidden.iter().any(|&h| h <= 0) {
            problems.push("dynamic_lcf.hidden must list at least one positive layer size".into());
        }
        let phi_bounds_valid = self.max_phi_deg > 0.0
            && self.max_phi_deg <= 90.0
            && self.max_phi_step_deg >= 0.0
            && self.max_phi_step_deg.is_finite();
        if !phi_bounds_valid {
            problems.push(
                "dynamic_lcf.max_phi_deg must be in (0, 90] and dynamic_lcf.max_phi_step_deg >= 0"
                    .into(),
            );
        }
        problems
    }
}

/// A learned LCF's meta-gradient settings, `key` naming its section.
fn meta_gradient_problems(key: &str, lr: f64, iterations: usize) -> Vec<String> {
    let mut problems = Vec::new();
    let lr_ok = lr >= 0.0 && lr.is_finite();
    if !lr_ok {
        problems.push(format!("{key}.lcf_lr must be a number >= 0"));
    }
    if iterations == 0 {
        problems.push(format!("{key}.meta_iterations must be > 0"));
    }
    problems
}

/// The centralised-critic baselines' own settings (`ccppo-concat`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CcppoConfig {
    /// k: nearest neighbours whose observations and actions the concat critic sees.
    pub neighbours: usize,
}

impl CcppoConfig {
    /// What is wrong with the section.
    pub(super) fn problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if self.neighbours == 0 {
            problems.push("ccppo.neighbours must be > 0".to_string());
        }
        problems
    }
}

#[cfg(test)]
mod tests {
    use crate::config::*;

    #[test]
    fn learned_lcf_bounds_outside_their_range_are_refused() {
        let c = RunConfig::default();
        assert_eq!(
            (c.copo.max_mean_deg, c.dynamic_lcf.max_phi_deg),
            (90.0, 10.0)
        );
        for bad in [
            vec!["copo.max_mean_deg=0.0"],
            vec!["copo.max_mean_deg=91.0"],
            vec!["copo.max_mean_deg=nan"],
            vec!["copo.max_mean_deg=20.0", "copo.initial_mean_deg=20.0"],
            vec!["copo.initial_mean_deg=-90.0"],
            vec!["dynamic_lcf.max_phi_deg=0.0"],
            vec!["dynamic_lcf.max_phi_step_deg=-1.0"],
        ] {
            let overrides: Vec<String> = bad.iter().map(|s| s.to_string()).collect();
            let err = RunConfig::load(None, &overrides);
            assert!(
                matches!(err, Err(ConfigError::Invalid(_))),
                "{bad:?} was accepted: {err:?}"
            );
        }
        let bounded = RunConfig::load(None, &["copo.max_mean_deg=20.0".into()]).unwrap();
        assert_eq!(bounded.copo.max_mean_deg, 20.0);
    }
}
