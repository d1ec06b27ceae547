//! The paper's dynamic LCF (§3.2): each agent's angle follows its neighbourhood at every step,
//! φ_i,t = f_ψ(S_N(i,t)), and it trains on the coordinated reward; ψ follows CoPO's
//! meta-gradient of the global objective (meta_lcf.rs), so it learns where cooperation pays.
//!
//! ```text
//! φ_i,t = φ_max·tanh(f_ψ(S_N(i,t)))  f_ψ: a small MLP over the neighbourhood features every
//!                                    fragment ships (count, distances, relative speeds);
//!         0 for an agent without neighbours (it has no neighbourhood reward to weigh)
//! for each update (the loop is shared_ppo.rs's; the critics see the agent's observation):
//!     r_C = α·cos φ·r_i + β·sin φ·r_N     (r_N: mean reward of the live neighbours, 0 alone;
//!                                        centred per fragment by `lcf.neighbourhood_reward`)
//!     r_G = mean reward of every agent in the scene at that step
//!     A_C ← GAE(r_C, V_C) at γ;  A_G ← GAE(r_G, V_G) at γ = 1, ending with the agent or going
//!     on with the scene (`lcf.global_return`)
//!     PPO epochs on standardised A_C; value losses of V_C and V_G
//!     meta-gradient on ψ: A_C is linear in the rewards, so with w = GAEᵀ·c (gae.rs)
//!         mean_k[c_k·A_C,k(ψ)] = mean_j[w_j·r_C,j(ψ)] + terms without ψ
//!         `meta_iterations` passes: Adam ascent on mean_j[w_j·r_C,j(ψ)] / std(A_C)
//!     pace: if the batch's mean |Δφ| exceeds max_phi_step_deg, ψ moves back along the step
//!           until it does not
//! ```
//!
//! Why the bound, the lone-agent rule and the pace (RESULTS.md, "A well-posed dynamic LCF"):
//! with φ free in ±90° and CoPO's r_N = 0 for an agent alone, the meta-gradient drove φ to
//! 90° everywhere (lone agents first: φ only scaled their own reward down) and the agents
//! learned to wait. φ_max keeps every agent's own reward weighted more than its neighbours'
//! (10° by default: at 45° runs whose φ rose past 30° still learned to wait, at 20° half of the
//! roundabout's seeds did); φ = 0 alone makes the lone case IPPO; the pace keeps φ from
//! outrunning the policy that has to adapt to it.
//! What pushes φ up is r_N's level (positive: a bonus for every step among neighbours): with
//! `lcf.neighbourhood_reward = "centred"` φ stays near 0 and the crash reduction goes with it
//! (RESULTS.md, "What the dynamic LCF's φ and fewer crashes come from").
//!
//! φ does not enter the observation: the learner computes it from the features, so actors run
//! the plain policy. f_ψ starts with a near-zero output (φ ≈ 0°: IPPO, like CoPO's μ = 0°).
//! α, β are `[lcf] alpha/beta`; the paper gives no values (1 and 1 by default).

use std::borrow::Cow;

use rand_chacha::ChaCha8Rng;
use tch::nn::{self, Module};
use tch::{Device, Kind, Tensor};

use junction_common::fragment::RolloutFragment;
use junction_common::lcf::{self};
use junction_common::mlp::Mlp;
use junction_common::weights::{self, Decoded, WeightsError};
use junction_core::config::{DynamicLcfConfig, GlobalReturn, LcfConfig, PpoConfig};
use junction_core::lcf_inputs::FEATURES;

use super::AlgoError;
use super::batch::TrainBatch;
use super::coordination::{Coordination, LcfReport, MetaStep, Signal};
use super::copo::META_ADAM_EPS;
use super::gae::reward_adjoint;
use super::meta_lcf;
use crate::optim::Adam;

/// Value heads, in [`DynamicLcf::signals`] order.
const COORDINATED: usize = 0;
const GLOBAL: usize = 1;
const ADAM_KEY: &str = "dynamic_lcf.adam";
/// The bound φ was learned under (checkpoints from before it was saved are taken as they are).
const MAX_PHI_KEY: &str = "dynamic_lcf.max_phi_deg";

/// φ in degrees for rows of neighbourhood features [m, FEATURES], within ±`max_deg`; 0 where
/// the first feature (the neighbour count) is 0.
fn phi_deg(net: &Mlp, features: &Tensor, max_deg: f64) -> Tensor {
    let has_neighbours = features.select(1, 0).gt(0.0).to_kind(Kind::Float);
    net.forward(features).squeeze_dim(-1).tanh() * max_deg * has_neighbours
}

/// The features of every alive cell, in batch order, row-major.
fn feature_rows(fragments: &[RolloutFragment]) -> Vec<f32> {
    let mut rows = Vec::new();
    for f in fragments {
        for cell in (0..f.steps * f.agents).filter(|&c| f.alive[c]) {
            rows.extend_from_slice(&f.lcf_features[cell * FEATURES..(cell + 1) * FEATURES]);
        }
    }
    rows
}

pub struct DynamicLcf {
    store: nn::VarStore,
    /// f_ψ.
    net: Mlp,
    adam: Adam,
    /// α, β, where the global return ends and what r_N is.
    lcf: LcfConfig,
    iterations: usize,
    cross_fit: bool,
    max_phi_deg: f64,
    /// Largest mean |Δφ| over a batch per update, degrees (0: unpaced).
    max_phi_step_deg: f64,
}

impl DynamicLcf {
    pub fn new(config: &DynamicLcfConfig, lcf: &LcfConfig, device: Device) -> Self {
        let store = nn::VarStore::new(device);
        let net = Mlp::new(
            store.root() / "lcf_net",
            FEATURES as i64,
            &config.hidden,
            1,
            0.01,
        );
        let adam = Adam::new(store.trainable_variables(), config.lcf_lr, META_ADAM_EPS);
        DynamicLcf {
            store,
            net,
            adam,
            lcf: lcf.clone(),
            iterations: config.meta_iterations,
            cross_fit: config.meta_cross_fit,
            max_phi_deg: f64::from(config.max_phi_deg),
            max_phi_step_deg: f64::from(config.max_phi_step_deg),
        }
    }

    /// Moves ψ back towards `before` (its values before the meta step) until the mean |Δφ|
    /// over `features` is at most `max_phi_step_deg`; returns the mean |Δφ| it leaves.
    fn pace(&mut self, before: &[Tensor], phi_before: &Tensor, features: &Tensor) -> f64 {
        let change = |net: &Mlp| -> f64 {
            tch::no_grad(|| {
                let phi = phi_deg(net, features, self.max_phi_deg);
                f64::try_from((phi - phi_before).abs().mean(Kind::Float)).unwrap_or(f64::NAN)
            })
        };
        let moved = change(&self.net);
        // A NaN step is not scaled (its scale would be NaN too): only a measured overshoot is.
        let overshot = moved > self.max_phi_step_deg;
        if self.max_phi_step_deg <= 0.0 || !overshot {
            return moved;
        }
        let keep = self.max_phi_step_deg / moved;
        tch::no_grad(|| {
            for (mut now, was) in self.store.trainable_variables().into_iter().zip(before) {
                let stepped = was + (&now - was) * keep;
                now.copy_(&stepped);
            }
        });
        change(&self.net)
    }

    fn device(&self) -> Device {
        self.store.device()
    }

    /// φ in degrees of `rows` (row-major features), computed without gradients.
    fn phi_of(&self, rows: &[f32]) -> Result<Vec<f32>, AlgoError> {
        let features = Tensor::from_slice(rows)
            .reshape([(rows.len() / FEATURES) as i64, FEATURES as i64])
            .to_device(self.device());
        let phi = tch::no_grad(|| phi_deg(&self.net, &features, self.max_phi_deg));
        Ok(Vec::<f32>::try_from(phi.to_device(Device::Cpu))?)
    }

    /// Each batch row's weight w_j in mean_k[c_k·A_C,k] (the reward adjoint of GAE applied to
    /// the sensitivities `c`), with the row's r_i and r_N: A_C is linear in the rewards, so the
    /// meta-objective is a weighted sum of coordinated rewards, the only place ψ enters.
    fn weighted_rewards(
        &self,
        fragments: &[RolloutFragment],
        c: &Tensor,
        ppo: &PpoConfig,
    ) -> Result<WeightedRewards, AlgoError> {
        let c = Vec::<f32>::try_from(c.to_device(Device::Cpu))?;
        let (mut weights, mut own, mut neighbourhood) = (Vec::new(), Vec::new(), Vec::new());
        let mut next = c.iter();
        for f in fragments {
            let cells = f.steps * f.agents;
            let mut cotangents = vec![0.0; cells];
            for cell in (0..cells).filter(|&c| f.alive[c]) {
                cotangents[cell] = next.next().copied().unwrap_or(0.0);
            }
            let w = reward_adjoint(
                (f.steps, f.agents),
                &f.dones,
                &f.alive,
                &cotangents,
                ppo.gamma,
                ppo.gae_lambda,
            );
            let r_n = lcf::neighbourhood_rewards(f, self.lcf.neighbourhood_reward);
            for cell in (0..cells).filter(|&c| f.alive[c]) {
                weights.push(w[cell]);
                own.push(f.rewards[cell]);
                neighbourhood.push(r_n[cell]);
            }
        }
        let device = self.device();
        let to = |v: &[f32]| Tensor::from_slice(v).to_device(device);
        Ok(WeightedRewards {
            weights: to(&weights),
            own: to(&own),
            neighbourhood: to(&neighbourhood),
        })
    }

    /// `meta_iterations` Adam ascent passes on ψ over minibatches of the batch's `rows`, along
    /// mean_j[w_j·r_C,j(ψ)] / `scale`: divided by the coordinated advantage's std so the
    /// step follows the standardised advantage the PPO loss used.
    fn ascend(
        &mut self,
        rewards: &WeightedRewards,
        features: &Tensor,
        scale: f64,
        rows: usize,
        minibatch: usize,
        rng: &mut ChaCha8Rng,
    ) -> Result<(), AlgoError> {
        let device = self.device();
        let (net, alpha, beta) = (
            &self.net,
            f64::from(self.lcf.alpha),
            f64::from(self.lcf.beta),
        );
        let max_deg = self.max_phi_deg;
        let WeightedRewards {
            weights,
            own,
            neighbourhood,
        } = rewards;
        meta_lcf::ascend(
            &mut self.adam,
            self.iterations,
            rows,
            minibatch,
            rng,
            device,
            |idx| {
                let phi = phi_deg(net, &features.index_select(0, idx), max_deg)
                    * (std::f64::consts::PI / 180.0);
                let reward = phi.cos() * own.index_select(0, idx) * alpha
                    + phi.sin() * neighbourhood.index_select(0, idx) * beta;
                (weights.index_select(0, idx) * reward).mean(Kind::Float) / scale
            },
        )?;
        Ok(())
    }
}

/// Per batch row: the weight w_j of its coordinated reward in the meta-objective, and the
/// rewards that one mixes, r_i and r_N.
struct WeightedRewards {
    weights: Tensor,
    own: Tensor,
    neighbourhood: Tensor,
}

impl Coordination for DynamicLcf {
    fn signals(&self) -> Vec<Signal> {
        vec![
            Signal {
                critic: "critic",
                gamma: None,
                outlives_agent: false,
            },
            Signal {
                critic: "global_critic",
                gamma: Some(1.0),
                outlives_agent: self.lcf.global_return == GlobalReturn::Scene,
            },
        ]
    }

    fn rewards<'f>(
        &self,
        index: usize,
        fragment: &'f RolloutFragment,
    ) -> Result<Cow<'f, [f32]>, AlgoError> {
        if index == GLOBAL {
            return Ok(Cow::Owned(lcf::global_rewards(fragment)));
        }
        let phi: Vec<f32> = self
            .phi_of(&fragment.lcf_features)?
            .into_iter()
            .map(f32::to_radians)
            .collect();
        Ok(Cow::Owned(lcf::coordinated_rewards_per_cell(
            fragment, &phi, &self.lcf,
        )))
    }

    fn policy_advantages(&self, batch: &TrainBatch) -> Result<Tensor, AlgoError> {
        Ok(batch.heads[COORDINATED].advantages.shallow_clone())
    }

    fn learns(&self) -> bool {
        true
    }

    /// The module documentation's meta-gradient on ψ, then the pace.
    fn learn(&mut self, step: MetaStep) -> Result<(), AlgoError> {
        let batch = step.batch;
        let c = meta_lcf::sensitivities(
            step.before,
            step.after,
            batch,
            &batch.heads[GLOBAL].advantages,
            step.ppo.clip,
            step.ppo.minibatch_size,
            &meta_lcf::segments(step.fragments, self.cross_fit),
        )?;
        let rewards = self.weighted_rewards(step.fragments, &c, step.ppo)?;
        let rows = feature_rows(step.fragments);
        let features = Tensor::from_slice(&rows)
            .to_device(self.device())
            .reshape([batch.len as i64, FEATURES as i64]);
        let scale = f64::try_from(batch.heads[COORDINATED].advantages.std(true))? + 1e-8;
        let before: Vec<Tensor> = self
            .store
            .trainable_variables()
            .iter()
            .map(|v| v.detach().copy())
            .collect();
        let phi_before = tch::no_grad(|| phi_deg(&self.net, &features, self.max_phi_deg));
        let minibatch = step.ppo.minibatch_size;
        self.ascend(&rewards, &features, scale, batch.len, minibatch, step.rng)?;
        self.pace(&before, &phi_before, &features);
        Ok(())
    }

    fn report(
        &self,
        fragments: &[RolloutFragment],
        batch: &TrainBatch,
    ) -> Result<LcfReport, AlgoError> {
        let phi = self.phi_of(&feature_rows(fragments))?;
        Ok(LcfReport::from_rows(&phi, &batch.neighbour_counts))
    }

    fn state_tensors(&self) -> Vec<(String, Tensor)> {
        let mut state = weights::var_store_tensors(&self.store);
        state.push((
            MAX_PHI_KEY.to_string(),
            Tensor::from_slice(&[self.max_phi_deg as f32]),
        ));
        state.extend(self.adam.state(ADAM_KEY));
        state
    }

    /// Refuses a checkpoint learned under another `max_phi_deg`: the same f_ψ would give every
    /// neighbourhood a φ scaled by the ratio of the bounds, and no change of f_ψ undoes that.
    fn restore(&mut self, state: &mut Decoded) -> Result<(), WeightsError> {
        if state.tensors.contains_key(MAX_PHI_KEY) {
            let saved = f64::try_from(state.take(MAX_PHI_KEY, &[1])?.sum(Kind::Float))?;
            if saved != self.max_phi_deg {
                return Err(WeightsError::Mismatch(format!(
                    "the dynamic LCF's φ was learned within ±{saved}°, this run bounds it at \
                     dynamic_lcf.max_phi_deg = {}°; resume with --set dynamic_lcf.max_phi_deg={saved}",
                    self.max_phi_deg
                )));
            }
        }
        weights::load_var_store(&self.store, state)?;
        self.adam.load_state(ADAM_KEY, state)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::Algorithm;
    use crate::algo::coordination::FixedLcf;
    use crate::algo::ippo::OwnObservation;
    use crate::algo::ippo::fixtures::constant_critic_batch;
    use crate::algo::shared_ppo::{SharedPpo, copy_networks};
    use crate::algo::testing::{
        assert_checkpoint_round_trip, host_state, neighbourhood_fragment, small_run,
    };
    use junction_core::config::{DynamicLcfConfig, NeighbourhoodReward, RunConfig};

    /// f_ψ with every weight 0 and output bias `bias`, bounded at 90°: φ = 90°·tanh(bias)
    /// for every agent with a neighbour.
    fn constant(bias: f64, lcf: &LcfConfig, lr: f64) -> DynamicLcf {
        let mut config = RunConfig::default().dynamic_lcf;
        config.lcf_lr = lr;
        config.max_phi_deg = 90.0;
        let dynamic = DynamicLcf::new(&config, lcf, Device::Cpu);
        tch::no_grad(|| {
            for (name, mut var) in dynamic.store.variables() {
                let last_bias = name.ends_with(&format!("l{}.bias", config.hidden.len()));
                let _ = var.fill_(if last_bias { bias } else { 0.0 });
            }
        });
        dynamic
    }

    fn host(t: &Tensor) -> Vec<f32> {
        Vec::<f32>::try_from(t.to_device(Device::Cpu)).unwrap()
    }

    #[test]
    fn only_the_global_head_outlives_the_agent_and_only_when_asked() {
        for (global_return, outlives) in [(GlobalReturn::Agent, false), (GlobalReturn::Scene, true)]
        {
            let lcf = LcfConfig {
                global_return,
                ..RunConfig::default().lcf
            };
            let dynamic = DynamicLcf::new(&RunConfig::default().dynamic_lcf, &lcf, Device::Cpu);
            let flags: Vec<bool> = dynamic.signals().iter().map(|s| s.outlives_agent).collect();
            assert_eq!(flags, vec![false, outlives]);
        }
    }

    #[test]
    fn the_coordinated_reward_by_hand() {
        // φ = 30° for agents with neighbours, α = 1, β = ½; critics ≡ 0 and λ = 0 make
        // A_C = r_C. Rewards by slot: −½, ½, 3⁄2, −½, ½, 3⁄2 at both steps; r_N at t = 0:
        // slot 0 → 0.7, 2 → −½, 3 → 1; at t = 1: 0 → ½ (empty slot 5 left out), 3 → ½; the
        // rest have no neighbours: φ = 0, their own reward. Centred, the five r_N give up
        // their mean, 2.2 / 5; the agents without neighbours are untouched.
        for (neighbourhood_reward, shift) in [
            (NeighbourhoodReward::Mean, 0.0),
            (NeighbourhoodReward::Centred, 0.44),
        ] {
            let lcf = LcfConfig {
                phi_deg: 0.0,
                alpha: 1.0,
                beta: 0.5,
                global_return: GlobalReturn::Agent,
                neighbourhood_reward,
            };
            let dynamic = constant((1.0f64 / 3.0).atanh(), &lcf, 1e-4);
            let batch = constant_critic_batch(&dynamic, &neighbourhood_fragment(), 0.0, 0.99, 0.0);
            let (c, s) = (3.0f32.sqrt() / 2.0, 0.5 * 0.5);
            let expected = [
                c * -0.5 + s * (0.7 - shift),
                0.5,
                c * 1.5 + s * (-0.5 - shift),
                c * -0.5 + s * (1.0 - shift),
                0.5,
                1.5,
                c * -0.5 + s * (0.5 - shift),
                0.5,
                1.5,
                c * -0.5 + s * (0.5 - shift),
                0.5,
            ];
            let got = host(&dynamic.policy_advantages(&batch).unwrap());
            for (g, e) in got.iter().zip(expected) {
                assert!(
                    (g - e).abs() < 1e-5,
                    "{neighbourhood_reward:?}: {got:?} vs {expected:?}"
                );
            }
            // φ itself does not depend on what r_N is; 5 of the 11 agent-steps have neighbours.
            let report = dynamic.report(&[neighbourhood_fragment()], &batch).unwrap();
            assert!(
                (report.mean_deg - 30.0 * 5.0 / 11.0).abs() < 1e-4,
                "{}",
                report.mean_deg
            );
            let lone = report.by_neighbours[0].unwrap();
            assert_eq!(lone, 0.0, "φ = 0 without neighbours");
            assert!((report.by_neighbours[1].unwrap() - 30.0).abs() < 1e-4);
        }
    }

    #[test]
    fn a_checkpoint_learned_under_another_bound_is_refused() {
        let lcf = RunConfig::default().lcf;
        let bounded_at = |max_phi_deg| {
            let mut config = RunConfig::default().dynamic_lcf;
            config.max_phi_deg = max_phi_deg;
            DynamicLcf::new(&config, &lcf, Device::Cpu)
        };
        let saved = |drop_bound: bool| {
            let state = bounded_at(45.0).state_tensors();
            let refs: Vec<(String, &Tensor)> = state
                .iter()
                .filter(|(name, _)| !(drop_bound && name == MAX_PHI_KEY))
                .map(|(name, t)| (name.clone(), t))
                .collect();
            Decoded::decode(&weights::encode(&refs, Default::default()).unwrap()).unwrap()
        };
        bounded_at(45.0).restore(&mut saved(false)).unwrap();
        let err = bounded_at(20.0).restore(&mut saved(false)).unwrap_err();
        assert!(
            matches!(err, WeightsError::Mismatch(_)) && err.to_string().contains("max_phi_deg=45"),
            "{err}"
        );
        // A checkpoint from before the bound was saved restores as it always did.
        bounded_at(20.0).restore(&mut saved(true)).unwrap();
    }

    #[test]
    fn phi_stays_within_its_bound_and_the_pace_limits_its_change_per_update() {
        let lcf = RunConfig::default().lcf;
        let mut config = RunConfig::default().dynamic_lcf;
        config.max_phi_deg = 45.0;
        let dynamic = DynamicLcf::new(&config, &lcf, Device::Cpu);
        // A huge output saturates tanh: φ = ±45°, never more; 0 alone.
        tch::no_grad(|| {
            for (name, mut var) in dynamic.store.variables() {
                if name.ends_with("bias") {
                    let _ = var.fill_(50.0);
                }
            }
        });
        let features = [0.1, 0.5, 0.3, 0.1, 0.5, 0.0, 1.0, 1.0, 0.0, 0.5];
        let phi = dynamic.phi_of(&features).unwrap();
        assert!((phi[0] - 45.0).abs() < 1e-3 && phi[1] == 0.0, "{phi:?}");

        // Pacing: a meta step that moved φ by ≈ 10° is pulled back to 1°.
        let mut paced = DynamicLcf::new(
            &DynamicLcfConfig {
                max_phi_step_deg: 1.0,
                ..config.clone()
            },
            &lcf,
            Device::Cpu,
        );
        let rows = Tensor::from_slice(&features[..5]).reshape([1, 5]);
        let before: Vec<Tensor> = paced
            .store
            .trainable_variables()
            .iter()
            .map(|v| v.detach().copy())
            .collect();
        let phi_before = phi_deg(&paced.net, &rows, 45.0).detach();
        tch::no_grad(|| {
            for (name, mut var) in paced.store.variables() {
                if name.ends_with(&format!("l{}.bias", config.hidden.len())) {
                    // φ ≈ 45·tanh(0.23) ≈ 10° away from ≈ 0.
                    let _ = var.g_add_scalar_(0.23);
                }
            }
        });
        let unpaced_change = f64::try_from(
            (phi_deg(&paced.net, &rows, 45.0) - &phi_before)
                .abs()
                .mean(Kind::Float),
        )
        .unwrap();
        assert!(unpaced_change > 5.0, "{unpaced_change}");
        let left = paced.pace(&before, &phi_before, &rows);
        assert!((left - 1.0).abs() < 0.1, "paced change {left}");
        // Unpaced (0): the step stays.
        paced.max_phi_step_deg = 0.0;
        let again = paced.pace(&before, &phi_before, &rows);
        assert!((again - left).abs() < 1e-9);
    }

    /// PPO without gradient-norm clipping: the global head's gradient would change the norm.
    fn unclipped_run() -> RunConfig {
        let mut run = small_run();
        run.ppo.max_grad_norm = 0.0;
        run
    }

    #[test]
    fn a_zero_lcf_trains_exactly_like_ippo() {
        let run = unclipped_run();
        let fragment = neighbourhood_fragment();
        // f_ψ ≡ 0 (φ = 0) and a meta step size of 0, so φ stays 0.
        let zero = constant(0.0, &run.lcf, 0.0);
        let mut dynamic = SharedPpo::new(
            "dynamic-lcf",
            OwnObservation,
            Box::new(zero),
            &run,
            2,
            2,
            Device::Cpu,
        );
        let mut ippo = SharedPpo::new(
            "ippo",
            OwnObservation,
            Box::new(FixedLcf::new(&run.lcf)),
            &run,
            2,
            2,
            Device::Cpu,
        );
        copy_networks(&dynamic, &mut ippo);
        for _ in 0..2 {
            let stats = dynamic.update(std::slice::from_ref(&fragment)).unwrap();
            assert_eq!((stats.lcf_mean_deg, stats.lcf_std_deg), (0.0, 0.0));
            ippo.update(std::slice::from_ref(&fragment)).unwrap();
        }
        assert_eq!(
            dynamic.policy_bytes(1).unwrap(),
            ippo.policy_bytes(1).unwrap(),
            "policy"
        );
        let critic = |state: Vec<(String, Vec<f32>)>| -> Vec<(String, Vec<f32>)> {
            state
                .into_iter()
                .filter(|(name, _)| name.starts_with("critic."))
                .collect()
        };
        let ippo_critic = critic(host_state(&ippo));
        assert!(!ippo_critic.is_empty());
        assert_eq!(critic(host_state(&dynamic)), ippo_critic, "critic");
    }

    fn dynamic_learner() -> SharedPpo<OwnObservation> {
        let run = small_run();
        SharedPpo::new(
            "dynamic-lcf",
            OwnObservation,
            Box::new(DynamicLcf::new(&run.dynamic_lcf, &run.lcf, Device::Cpu)),
            &run,
            2,
            2,
            Device::Cpu,
        )
    }

    #[test]
    fn the_meta_gradient_moves_f_and_phi_is_reported_by_neighbour_count() {
        let _rng = crate::test_rng::seeded(6);
        let mut learner = dynamic_learner();
        let fragment = neighbourhood_fragment();
        let net = |l: &SharedPpo<OwnObservation>| -> Vec<(String, Vec<f32>)> {
            host_state(l)
                .into_iter()
                .filter(|(name, _)| name.starts_with("lcf_net."))
                .collect()
        };
        let before = net(&learner);
        assert!(!before.is_empty());
        let stats = learner.update(std::slice::from_ref(&fragment)).unwrap();
        assert_ne!(
            net(&learner),
            before,
            "the meta-gradient left f_ψ unchanged"
        );
        // The fixture's agents have 0, 1–2 and 3–5 neighbours, none 6 or more.
        let buckets = stats.lcf_phi_by_neighbours;
        assert!(buckets[..3].iter().all(Option::is_some) && buckets[3].is_none());
        assert!(
            stats.lcf_std_deg > 0.0,
            "φ should vary with the neighbourhood"
        );
        assert!(stats.lcf_mean_deg.abs() < 90.0);
        assert_checkpoint_round_trip(|| {
            let mut learner = dynamic_learner();
            learner.update(std::slice::from_ref(&fragment)).unwrap();
            learner
        });
    }
}
