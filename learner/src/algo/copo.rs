//! CoPO, coordinated policy optimisation (Peng et al. 2021): every agent carries its own LCF
//! angle φ, drawn from a learned distribution, and ascends a coordinated advantage; the
//! distribution follows the meta-gradient of the global objective (meta_lcf.rs).
//!
//! ```text
//! actors: each agent draws φ ~ N(μ, σ), clipped to ±90°, when it spawns, keeps it for its
//!         episode and observes it as one more value, (φ/90° + 1)/2
//! for each update (the loop is shared_ppo.rs's; the critics see the agent's observation):
//!     r_i: own reward; r_N: mean reward of its live neighbours (0 alone);
//!     r_G: mean reward of every agent in the scene at that step
//!     A_i, A_N ← GAE(r_i, V_i), GAE(r_N, V_N) at γ;  A_G ← GAE(r_G, V_G) at γ = 1, ending
//!     with the agent or going on with the scene (`lcf.global_return`)
//!     A_C = cos φ·A_i + sin φ·A_N                        (φ read from the agent's observation)
//!     PPO epochs on standardised A_C; value losses of V_i, V_N and V_G
//!     meta-gradient on ψ = (atanh(μ/μ_max), ln(σ/90°)), each agent's draw reparameterised:
//!         φ_k(ψ) = clip(μ(ψ) + σ(ψ)·ε_k, ±90°),  ε_k = (φ_k − μ)/σ
//!         `meta_iterations` passes: Adam ascent on mean_k[c_k·A_C,k(ψ)] / std(A_C)
//!     the next broadcast carries (μ, σ)
//! ```
//!
//! Defaults (`[copo]`) are CoPO's but one: μ from 0°, σ from 0.1 of its 90° unit (9°), 5 passes,
//! μ within ±90° (`max_mean_deg`: μ = max_mean_deg·tanh ψ_0, so a tighter bound keeps the
//! meta-gradient smooth up to it, as the dynamic LCF's `max_phi_deg` does); Adam at 2.2e-5, not
//! CoPO's 1e-4, at which μ outran the policy and the agents learned to wait (RESULTS.md).
//! CoPO redraws fresh φ for the meta-gradient; reparameterising the agents' own draws
//! differentiates the same expectation at the samples the update used.

use std::borrow::Cow;
use std::collections::BTreeMap;

use tch::{Device, Kind, Tensor};

use junction_common::fragment::RolloutFragment;
use junction_common::lcf::{self, LcfDistribution};
use junction_common::weights::{Decoded, WeightsError};
use junction_core::config::{CopoConfig, GlobalReturn, LcfConfig, NeighbourhoodReward};
use junction_core::lcf_inputs::MAX_PHI_DEG;

use super::AlgoError;
use super::batch::TrainBatch;
use super::coordination::{Coordination, LcfReport, MetaStep, Signal};
use super::meta_lcf;
use crate::optim::Adam;

/// Value heads, in [`CopoLcf::signals`] order.
const INDIVIDUAL: usize = 0;
const NEIGHBOURHOOD: usize = 1;
const GLOBAL: usize = 2;
const PARAMS_KEY: &str = "copo.lcf_params";
const ADAM_KEY: &str = "copo.lcf_adam";
/// μ_max the saved ψ_0 was learned under; a checkpoint without it predates the key and is read
/// as 90°, CoPO's unit (the few runs bounded before the key existed kept no checkpoints).
const MAX_MEAN_KEY: &str = "copo.max_mean_deg";
/// ε of the meta-gradient's Adam (PyTorch's default, which CoPO uses).
pub const META_ADAM_EPS: f64 = 1e-8;

/// (μ, σ) in degrees of ψ = (atanh(μ/μ_max), ln(σ/90°)), differentiably.
pub fn mean_and_std(params: &Tensor, max_mean_deg: f64) -> (Tensor, Tensor) {
    let mean = params.get(0).tanh() * max_mean_deg;
    // CoPO's bounds on log σ keep σ positive and finite.
    let std = params.get(1).clamp(-20.0, 2.0).exp() * f64::from(MAX_PHI_DEG);
    (mean, std)
}

/// φ = clip(μ(ψ) + σ(ψ)·ε, ±90°), degrees, for standard-normal draws ε.
pub fn reparameterised_phi(params: &Tensor, noise: &Tensor, max_mean_deg: f64) -> Tensor {
    let (mean, std) = mean_and_std(params, max_mean_deg);
    let limit = f64::from(MAX_PHI_DEG);
    (mean + std * noise).clamp(-limit, limit)
}

/// A_C = cos φ·A_i + sin φ·A_N, φ in degrees: φ = 0 is A_i exactly, 90° A_N.
pub fn coordinated_advantage(
    phi_deg: &Tensor,
    individual: &Tensor,
    neighbourhood: &Tensor,
) -> Tensor {
    let phi = phi_deg * (std::f64::consts::PI / 180.0);
    phi.cos() * individual + phi.sin() * neighbourhood
}

/// Each row's φ, degrees, from the last value of its raw observation.
fn phi_of_rows(batch: &TrainBatch) -> Tensor {
    let limit = f64::from(MAX_PHI_DEG);
    ((batch.obs.select(1, -1) * 2.0 - 1.0) * limit).clamp(-limit, limit)
}

/// CoPO's coordination: three value heads, the coordinated advantage, the learned N(μ, σ).
pub struct CopoLcf {
    /// ψ = [atanh(μ/μ_max), ln(σ/90°)] (CoPO's parameterisation in its unit of 90°).
    params: Tensor,
    /// μ_max, degrees.
    max_mean_deg: f64,
    adam: Adam,
    iterations: usize,
    cross_fit: bool,
    global_return: GlobalReturn,
    neighbourhood_reward: NeighbourhoodReward,
}

impl CopoLcf {
    pub fn new(config: &CopoConfig, lcf: &LcfConfig, device: Device) -> Self {
        let start = [
            (config.initial_mean_deg / config.max_mean_deg).atanh(),
            (config.initial_std_deg / MAX_PHI_DEG).ln(),
        ];
        let params = Tensor::from_slice(&start)
            .to_device(device)
            .set_requires_grad(true);
        CopoLcf {
            adam: Adam::new(vec![params.shallow_clone()], config.lcf_lr, META_ADAM_EPS),
            params,
            max_mean_deg: f64::from(config.max_mean_deg),
            iterations: config.meta_iterations,
            cross_fit: config.meta_cross_fit,
            global_return: lcf.global_return,
            neighbourhood_reward: lcf.neighbourhood_reward,
        }
    }

    /// The distribution agents draw from now.
    pub fn distribution(&self) -> Result<LcfDistribution, AlgoError> {
        let (mean, std) = tch::no_grad(|| mean_and_std(&self.params, self.max_mean_deg));
        Ok(LcfDistribution {
            mean_deg: f64::try_from(mean)? as f32,
            std_deg: f64::try_from(std)? as f32,
        })
    }
}

impl Coordination for CopoLcf {
    fn signals(&self) -> Vec<Signal> {
        vec![
            Signal {
                critic: "critic",
                gamma: None,
                outlives_agent: false,
            },
            Signal {
                critic: "neighbourhood_critic",
                gamma: None,
                outlives_agent: false,
            },
            Signal {
                critic: "global_critic",
                gamma: Some(1.0),
                outlives_agent: self.global_return == GlobalReturn::Scene,
            },
        ]
    }

    fn rewards<'f>(
        &self,
        index: usize,
        fragment: &'f RolloutFragment,
    ) -> Result<Cow<'f, [f32]>, AlgoError> {
        Ok(match index {
            INDIVIDUAL => Cow::Borrowed(fragment.rewards.as_slice()),
            NEIGHBOURHOOD => Cow::Owned(lcf::neighbourhood_rewards(
                fragment,
                self.neighbourhood_reward,
            )),
            _ => Cow::Owned(lcf::global_rewards(fragment)),
        })
    }

    fn policy_advantages(&self, batch: &TrainBatch) -> Result<Tensor, AlgoError> {
        Ok(coordinated_advantage(
            &phi_of_rows(batch),
            &batch.heads[INDIVIDUAL].advantages,
            &batch.heads[NEIGHBOURHOOD].advantages,
        ))
    }

    fn learns(&self) -> bool {
        true
    }

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
        let phi = phi_of_rows(batch);
        let individual = &batch.heads[INDIVIDUAL].advantages;
        let neighbourhood = &batch.heads[NEIGHBOURHOOD].advantages;
        let scale =
            f64::try_from(coordinated_advantage(&phi, individual, neighbourhood).std(true))? + 1e-8;
        let noise = tch::no_grad(|| {
            let (mean, std) = mean_and_std(&self.params, self.max_mean_deg);
            (&phi - mean) / std
        });
        let params = &self.params;
        let max_mean_deg = self.max_mean_deg;
        meta_lcf::ascend(
            &mut self.adam,
            self.iterations,
            batch.len,
            step.ppo.minibatch_size,
            step.rng,
            params.device(),
            |idx| {
                let advantage = coordinated_advantage(
                    &reparameterised_phi(params, &noise.index_select(0, idx), max_mean_deg),
                    &individual.index_select(0, idx),
                    &neighbourhood.index_select(0, idx),
                );
                (c.index_select(0, idx) * advantage).mean(Kind::Float) / scale
            },
        )?;
        Ok(())
    }

    fn report(&self, _: &[RolloutFragment], batch: &TrainBatch) -> Result<LcfReport, AlgoError> {
        let phi = Vec::<f32>::try_from(phi_of_rows(batch).to_device(Device::Cpu))?;
        let distribution = self.distribution()?;
        Ok(LcfReport {
            mean_deg: f64::from(distribution.mean_deg),
            std_deg: f64::from(distribution.std_deg),
            ..LcfReport::from_rows(&phi, &batch.neighbour_counts)
        })
    }

    fn policy_metadata(&self) -> BTreeMap<String, String> {
        self.distribution()
            .map(LcfDistribution::to_metadata)
            .unwrap_or_default()
    }

    fn state_tensors(&self) -> Vec<(String, Tensor)> {
        let mut state = vec![
            (PARAMS_KEY.to_string(), self.params.detach().copy()),
            (
                MAX_MEAN_KEY.to_string(),
                Tensor::from_slice(&[self.max_mean_deg as f32]),
            ),
        ];
        state.extend(self.adam.state(ADAM_KEY));
        state
    }

    /// Keeps the checkpoint's μ when this run bounds μ differently (ψ_0 re-expressed under
    /// the new bound), so continuing a run under another `max_mean_deg` does not silently
    /// rescale what it learned; a μ outside the new bound is refused.
    fn restore(&mut self, state: &mut Decoded) -> Result<(), WeightsError> {
        let params = state.take(PARAMS_KEY, &[2])?;
        let saved_bound = if state.tensors.contains_key(MAX_MEAN_KEY) {
            f64::try_from(state.take(MAX_MEAN_KEY, &[1])?.sum(Kind::Float))?
        } else {
            f64::from(MAX_PHI_DEG)
        };
        let params = if saved_bound == self.max_mean_deg {
            params
        } else {
            let mean_deg = f64::try_from(params.get(0).tanh())? * saved_bound;
            if mean_deg.abs() >= self.max_mean_deg {
                return Err(WeightsError::Mismatch(format!(
                    "CoPO's μ is {mean_deg:.1}° in the checkpoint, outside this run's bound \
                     copo.max_mean_deg = {}°; resume with --set copo.max_mean_deg={saved_bound}",
                    self.max_mean_deg
                )));
            }
            let psi_0 = (mean_deg / self.max_mean_deg).atanh();
            tracing::info!(
                mean_deg,
                from_bound_deg = saved_bound,
                to_bound_deg = self.max_mean_deg,
                "CoPO's μ kept across a changed copo.max_mean_deg"
            );
            Tensor::from_slice(&[psi_0 as f32, f64::try_from(params.get(1))? as f32])
        };
        self.adam.load_state(ADAM_KEY, state)?;
        tch::no_grad(|| self.params.copy_(&params.to_device(self.params.device())));
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::Algorithm;
    use crate::algo::ippo::OwnObservation;
    use crate::algo::ippo::fixtures::constant_critic_batch;
    use crate::algo::meta_lcf::{log_prob_jvp, objective_gradient};
    use crate::algo::ppo::clipped_surrogate;
    use crate::algo::shared_ppo::SharedPpo;
    use crate::algo::testing::{
        F64, Tiny, assert_checkpoint_round_trip_on, neighbourhood_fragment, small_run, t,
    };
    use junction_core::config::RunConfig;
    use junction_core::lcf_inputs;

    /// φ of each slot in [`copo_fragment`], degrees.
    const PHI_BY_SLOT: [f32; 6] = [0.0, -45.0, 30.0, 90.0, 60.0, -90.0];

    /// The neighbourhood fixture with each agent's φ as its last observation value.
    fn copo_fragment() -> RolloutFragment {
        let mut f = neighbourhood_fragment();
        for cell in 0..f.steps * f.agents {
            f.obs[cell * f.obs_dim + 1] = lcf_inputs::phi_observation(PHI_BY_SLOT[cell % f.agents]);
        }
        f
    }

    fn host(t: &Tensor) -> Vec<f32> {
        Vec::<f32>::try_from(t.to_device(Device::Cpu)).unwrap()
    }

    /// The default coordination with the global return ending as `global_return` says.
    fn ending(global_return: GlobalReturn) -> LcfConfig {
        LcfConfig {
            global_return,
            ..RunConfig::default().lcf
        }
    }

    fn coordination() -> CopoLcf {
        CopoLcf::new(
            &RunConfig::default().copo,
            &ending(GlobalReturn::Agent),
            Device::Cpu,
        )
    }

    #[test]
    fn a_scene_global_return_goes_on_past_an_agents_end_and_nothing_else_does() {
        // Critics ≡ 2 and λ = 0: A = r + γ·(value after) − 2. Slot 5 ends at t = 0 (row 5);
        // the other five slots go on, so the scene's value after it is 2.
        let fragment = copo_fragment();
        let batch_of = |global_return| {
            let copo = CopoLcf::new(
                &RunConfig::default().copo,
                &ending(global_return),
                Device::Cpu,
            );
            constant_critic_batch(&copo, &fragment, 2.0, 0.99, 0.0)
        };
        let (agent, scene) = (batch_of(GlobalReturn::Agent), batch_of(GlobalReturn::Scene));
        for head in 0..3 {
            let (a, s) = (
                host(&agent.heads[head].advantages),
                host(&scene.heads[head].advantages),
            );
            for row in 0..a.len() {
                let lifted = if head == GLOBAL && row == 5 { 2.0 } else { 0.0 };
                assert!(
                    (s[row] - a[row] - lifted).abs() < 1e-6,
                    "head {head} row {row}: {} vs {}",
                    s[row],
                    a[row]
                );
            }
        }
    }

    #[test]
    fn the_coordinated_advantage_by_hand() {
        // Critics ≡ 0 and λ = 0 make each head's advantage its reward: A_i = r_i, A_N = r_N.
        // Rewards (cell i: i mod 3 − ½) by slot: −½, ½, 3⁄2, −½, ½, 3⁄2 at both steps.
        // r_N at t = 0: slot 0 (5 neighbours) 0.7, 2 → −½, 3 → 1; at t = 1: 0 → ½ (slot 5 is
        // empty then and does not count), 3 → ½; the others have no neighbours.
        let batch = constant_critic_batch(&coordination(), &copo_fragment(), 0.0, 0.99, 0.0);
        let got = host(&coordination().policy_advantages(&batch).unwrap());
        let (c30, s45) = (3.0f32.sqrt() / 2.0, std::f32::consts::FRAC_1_SQRT_2);
        let expected = [
            // t = 0, slots 0–5: φ = 0 → A_i; −45° without neighbours → cos·A_i; 30°; 90° → A_N;
            // 60° alone; −90° alone → 0.
            -0.5,
            s45 * 0.5,
            c30 * 1.5 + 0.5 * -0.5,
            1.0,
            0.5 * 0.5,
            0.0,
            // t = 1, slots 0–4.
            -0.5,
            s45 * 0.5,
            c30 * 1.5,
            0.5,
            0.5 * 0.5,
        ];
        assert_eq!(got.len(), expected.len());
        for (g, e) in got.iter().zip(expected) {
            assert!((g - e).abs() < 1e-5, "{got:?} vs {expected:?}");
        }
        // φ = 0 is IPPO's advantage bit for bit.
        let individual = host(&batch.heads[INDIVIDUAL].advantages);
        assert_eq!((got[0], got[6]), (individual[0], individual[6]));
    }

    #[test]
    fn the_global_head_runs_gae_on_the_scene_mean_reward_at_gamma_one() {
        // r_G: t = 0 the mean of all six rewards, 3/6 = ½; t = 1 of the five alive, 1.5/5 = 0.3.
        // V ≡ 1 everywhere (bootstraps too), λ = ½, γ = 1 (not the 0.99 given for the others):
        // slots 0–4 at t = 1: δ = 0.3 + 1 − 1 = 0.3; at t = 0: δ = ½, A = ½ + ½·0.3 = 0.65;
        // slot 5 ends at t = 0: δ = ½ − 1 = −½.
        let batch = constant_critic_batch(&coordination(), &copo_fragment(), 1.0, 0.99, 0.5);
        let global = &batch.heads[GLOBAL];
        let expected = [0.65, 0.65, 0.65, 0.65, 0.65, -0.5, 0.3, 0.3, 0.3, 0.3, 0.3];
        for (name, got, want) in [
            ("advantages", host(&global.advantages), expected),
            ("returns", host(&global.returns), expected.map(|a| a + 1.0)),
        ] {
            for (g, e) in got.iter().zip(want) {
                assert!((g - e).abs() < 1e-6, "{name}: {got:?} vs {want:?}");
            }
        }
    }

    fn copo_learner() -> SharedPpo<OwnObservation> {
        copo_learner_with(small_run())
    }

    fn copo_learner_with(run: RunConfig) -> SharedPpo<OwnObservation> {
        SharedPpo::new(
            "copo",
            OwnObservation,
            Box::new(CopoLcf::new(&run.copo, &run.lcf, Device::Cpu)),
            &run,
            2,
            2,
            Device::Cpu,
        )
    }

    #[test]
    fn an_update_moves_the_distribution_actors_receive_and_checkpoints_continue_exactly() {
        let _rng = crate::test_rng::seeded(4);
        let mut learner = copo_learner();
        let start = LcfDistribution::from_metadata(
            &junction_common::weights::metadata(&learner.policy_bytes(0).unwrap()).unwrap(),
        )
        .unwrap()
        .unwrap();
        assert!(start.mean_deg.abs() < 1e-6 && (start.std_deg - 9.0).abs() < 1e-4);
        let fragment = copo_fragment();
        let stats = learner.update(std::slice::from_ref(&fragment)).unwrap();
        let after = LcfDistribution::from_metadata(
            &junction_common::weights::metadata(&learner.policy_bytes(1).unwrap()).unwrap(),
        )
        .unwrap()
        .unwrap();
        assert_ne!(after, start, "the meta-gradient moved neither μ nor σ");
        assert_eq!(
            (stats.lcf_mean_deg as f32, stats.lcf_std_deg as f32),
            (after.mean_deg, after.std_deg)
        );
        // Per neighbour bucket, the agents' own φ; without neighbours: slots 1, 4, 5 at t = 0
        // and 1, 2, 4 at t = 1.
        let lonely = [-45.0, 60.0, -90.0, -45.0, 30.0, 60.0];
        let mean = lonely.iter().sum::<f64>() / 6.0;
        let got = stats.lcf_phi_by_neighbours[0].unwrap();
        assert!((got - mean).abs() < 1e-3, "{got} vs {mean}");
        assert_checkpoint_round_trip_on(
            || {
                let mut learner = copo_learner();
                learner.update(std::slice::from_ref(&fragment)).unwrap();
                learner
            },
            &fragment,
        );
    }

    /// μ of the distribution after `updates` updates with a meta step large enough to
    /// saturate tanh, starting from μ = 10°.
    fn mean_after_large_meta_steps(max_mean_deg: f32, updates: usize) -> f32 {
        let _rng = crate::test_rng::seeded(5);
        let mut run = small_run();
        run.copo.max_mean_deg = max_mean_deg;
        run.copo.initial_mean_deg = 10.0;
        run.copo.lcf_lr = 0.5;
        let mut learner = copo_learner_with(run);
        let fragment = copo_fragment();
        let mut mean = f32::NAN;
        for _ in 0..updates {
            mean = learner
                .update(std::slice::from_ref(&fragment))
                .unwrap()
                .lcf_mean_deg as f32;
        }
        mean
    }

    /// CoPO's state at μ = `mean_deg` under the bound `max_mean_deg`, through the checkpoint
    /// format, without the saved bound when `drop_bound`.
    fn saved_state(max_mean_deg: f32, mean_deg: f32, drop_bound: bool) -> Decoded {
        let mut config = RunConfig::default().copo;
        config.max_mean_deg = max_mean_deg;
        config.initial_mean_deg = mean_deg;
        let state =
            CopoLcf::new(&config, &ending(GlobalReturn::Agent), Device::Cpu).state_tensors();
        let refs: Vec<(String, &Tensor)> = state
            .iter()
            .filter(|(name, _)| !(drop_bound && name == MAX_MEAN_KEY))
            .map(|(name, t)| (name.clone(), t))
            .collect();
        Decoded::decode(&junction_common::weights::encode(&refs, Default::default()).unwrap())
            .unwrap()
    }

    fn bounded_at(max_mean_deg: f32) -> CopoLcf {
        let mut config = RunConfig::default().copo;
        config.max_mean_deg = max_mean_deg;
        CopoLcf::new(&config, &ending(GlobalReturn::Agent), Device::Cpu)
    }

    #[test]
    fn a_checkpoint_keeps_its_mean_under_another_bound_or_is_refused() {
        let mut tighter = bounded_at(20.0);
        tighter
            .restore(&mut saved_state(90.0, 12.0, false))
            .unwrap();
        let kept = tighter.distribution().unwrap();
        assert!(
            (kept.mean_deg - 12.0).abs() < 1e-3,
            "μ = {}°",
            kept.mean_deg
        );
        assert!((kept.std_deg - 9.0).abs() < 1e-3, "σ = {}°", kept.std_deg);
        // A checkpoint from before the bound was saved is read as CoPO's 90°.
        let mut from_old = bounded_at(20.0);
        from_old
            .restore(&mut saved_state(90.0, 12.0, true))
            .unwrap();
        assert!((from_old.distribution().unwrap().mean_deg - 12.0).abs() < 1e-3);
        let err = bounded_at(20.0)
            .restore(&mut saved_state(90.0, 30.0, false))
            .unwrap_err();
        assert!(
            matches!(err, WeightsError::Mismatch(_)) && err.to_string().contains("max_mean_deg=90"),
            "{err}"
        );
    }

    #[test]
    fn a_bounded_mean_starts_where_configured_and_never_passes_its_bound() {
        let mut config = RunConfig::default().copo;
        config.max_mean_deg = 20.0;
        config.initial_mean_deg = 10.0;
        let copo = CopoLcf::new(&config, &ending(GlobalReturn::Agent), Device::Cpu);
        assert!((copo.distribution().unwrap().mean_deg - 10.0).abs() < 1e-4);
        // The same steps take CoPO's unbounded μ well past 20°; the bounded one stays within.
        let unbounded = mean_after_large_meta_steps(90.0, 4);
        let bounded = mean_after_large_meta_steps(20.0, 4);
        assert!(unbounded.abs() > 30.0, "μ moved only to {unbounded}°");
        assert!(
            bounded.abs() <= 20.0 + 1e-4,
            "μ = {bounded}° past its 20° bound"
        );
        assert!(
            bounded.abs() > 15.0,
            "μ = {bounded}°: the meta step did not move it"
        );
    }

    /// J(ψ) = J_G(θ + η·∇θ L_in(θ, ψ)), L_in = mean_k[A_C,k(ψ)/s·log π_θ(a_k|s_k)]: one plain
    /// SGD step of the policy on CoPO's coordinated advantage, then the global objective.
    struct Problem {
        theta: Tiny,
        obs: Tensor,
        actions: Tensor,
        behaviour: Tensor,
        individual: Tensor,
        neighbourhood: Tensor,
        global: Tensor,
        noise: Tensor,
        scale: f64,
        eta: f64,
        clip: f64,
    }

    impl Problem {
        fn coordinated(&self, psi: &Tensor) -> Tensor {
            coordinated_advantage(
                &reparameterised_phi(psi, &self.noise, f64::from(MAX_PHI_DEG)),
                &self.individual,
                &self.neighbourhood,
            ) / self.scale
        }

        fn updated_policy(&self, psi: &Tensor) -> Tiny {
            let inner = (self.coordinated(psi).detach()
                * self.theta.log_probs(&self.obs, &self.actions))
            .mean(Kind::Double);
            let step = objective_gradient(&inner, &self.theta.params()).unwrap();
            self.theta.moved(&step, self.eta)
        }

        fn global_objective(&self, policy: &Tiny) -> Tensor {
            -clipped_surrogate(
                &policy.log_probs(&self.obs, &self.actions),
                &self.behaviour,
                &self.global,
                self.clip,
            )
            .loss
        }

        fn objective(&self, psi: &[f64]) -> f64 {
            let psi = t(psi, &[2]);
            f64::try_from(self.global_objective(&self.updated_policy(&psi))).unwrap()
        }
    }

    #[test]
    fn the_meta_gradient_matches_central_differences_of_the_global_objective() {
        let _rng = crate::test_rng::seeded(11);
        let rows = 7;
        let theta = Tiny {
            w1: Tensor::randn([3, 4], F64).set_requires_grad(true),
            w2: Tensor::randn([4, 2], F64).set_requires_grad(true),
            log_std: t(&[-0.3, 0.2], &[2]).set_requires_grad(true),
        };
        let obs = Tensor::randn([rows, 3], F64);
        let actions = Tensor::randn([rows, 2], F64);
        // Behaviour log-probabilities near the policy's, so every ratio stays inside the clip
        // range (J is smooth there).
        let behaviour =
            theta.log_probs(&obs, &actions).detach() + Tensor::randn([rows], F64) * 0.01;
        let problem = Problem {
            theta,
            obs,
            actions,
            behaviour,
            individual: Tensor::randn([rows], F64),
            neighbourhood: Tensor::randn([rows], F64),
            global: Tensor::randn([rows], F64),
            noise: Tensor::randn([rows], F64),
            scale: 1.7,
            eta: 0.05,
            clip: 0.3,
        };
        // ψ = (atanh(μ/90°), ln(σ/90°)): μ = 20°, σ = 15°.
        let psi0 = [(20.0f64 / 90.0).atanh(), (15.0f64 / 90.0).ln()];

        // Analytic: g at θ', c through θ, then η·∇ψ mean_k[c_k·A_C,k(ψ)].
        let psi = t(&psi0, &[2]).set_requires_grad(true);
        let after = problem.updated_policy(&psi.detach());
        let g = objective_gradient(&problem.global_objective(&after), &after.params()).unwrap();
        let log_probs = problem.theta.log_probs(&problem.obs, &problem.actions);
        let c = log_prob_jvp(&log_probs, &problem.theta.params(), &g).unwrap();
        let meta = (c * problem.coordinated(&psi)).mean(Kind::Double) * problem.eta;
        let analytic =
            Vec::<f64>::try_from(&objective_gradient(&meta, &[psi]).unwrap()[0]).unwrap();

        let h = 1e-5;
        for i in 0..2 {
            let (mut up, mut down) = (psi0, psi0);
            up[i] += h;
            down[i] -= h;
            let numeric = (problem.objective(&up) - problem.objective(&down)) / (2.0 * h);
            assert!(
                numeric.abs() > 1e-4,
                "a vanishing gradient proves nothing: {numeric}"
            );
            let error = (analytic[i] - numeric).abs() / numeric.abs();
            assert!(
                error < 1e-6,
                "∂J/∂ψ[{i}]: analytic {} vs central difference {numeric}",
                analytic[i]
            );
        }
    }
}
