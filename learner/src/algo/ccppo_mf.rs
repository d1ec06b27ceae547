//! CCPPO, mean-field critic (CoPO's baseline after Yang et al. 2018): PPO with parameter
//! sharing whose critic also sees the agent's neighbourhood summarised by its mean; the actor
//! stays decentralised (own observation only), so acting needs nothing a car cannot sense.
//!
//! ```text
//! for each update:
//!     fold the batch's observations into the running normaliser
//!     for each agent i at step t, N = its live neighbours within d_n at t:
//!         x_i = ô_i ‖ mean_{j∈N} ô_j ‖ mean_{j∈N} a_j      (means 0 when N = ∅; ô normalised)
//!     V ← critic(x); A, R ← GAE(rewards, V, γ, λ) per agent
//!     repeat `epochs` times, over shuffled minibatches:
//!         ρ = π(a|ô) / π_behaviour(a|ô)
//!         L = −min(ρÂ, clip(ρ, 1±ε)Â) + c_v·L_V(V(x), R) − c_e·H[π]
//!         Adam step on ∇L, gradient norm clipped
//! ```
//!
//! The neighbourhood is the fragment's (`scenario.neighbour_radius`, 40 m by default; CoPO's
//! mean-field critic used 10 m). For the bootstrap value after a fragment, x uses the agent's
//! bootstrap observation with the last step's neighbour means: the next step's neighbourhood
//! is not shipped, and one decision step (0.1 s) changes it little.

use super::batch::{CriticInput, NormalizedFragment};
use super::shared_ppo::SharedPpo;

/// Own observation ‖ mean neighbour observation ‖ mean neighbour action.
pub struct MeanField;

impl CriticInput for MeanField {
    fn width(&self, obs_dim: usize, action_dim: usize) -> usize {
        2 * obs_dim + action_dim
    }

    fn row(&self, f: &NormalizedFragment, own: &[f32], t: usize, slot: usize, out: &mut Vec<f32>) {
        out.extend_from_slice(own);
        let start = out.len();
        out.resize(start + f.raw.obs_dim + f.raw.action_dim, 0.0);
        let (mean_obs, mean_action) = out[start..].split_at_mut(f.raw.obs_dim);
        let mut count = 0usize;
        for n in f.live_neighbours(t, slot) {
            mean_obs
                .iter_mut()
                .zip(f.obs(t, n))
                .for_each(|(m, x)| *m += x);
            mean_action
                .iter_mut()
                .zip(f.action(t, n))
                .for_each(|(m, x)| *m += x);
            count += 1;
        }
        if count > 0 {
            out[start..].iter_mut().for_each(|v| *v /= count as f32);
        }
    }
}

pub type CcppoMf = SharedPpo<MeanField>;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::coordination::FixedLcf;
    use crate::algo::testing::{
        assert_checkpoint_round_trip, close, neighbourhood_fragment, rows, small_run, unnormalized,
    };

    #[test]
    fn mean_field_rows_on_a_known_neighbourhood() {
        let raw = neighbourhood_fragment();
        let f = unnormalized(&raw);
        assert_eq!(MeanField.width(2, 2), 6);
        // Five neighbours: obs x mean (6+5+4+3+2)/5 = 4, action mean (.6+.5+.4+.3+.2)/5 = .4.
        close(&rows(&MeanField, &f, 0, 0), &[1.0, 1.0, 4.0, 1.0, 0.4, 0.5]);
        // No neighbours: zero means.
        close(&rows(&MeanField, &f, 0, 1), &[2.0, 1.0, 0.0, 0.0, 0.0, 0.0]);
        close(&rows(&MeanField, &f, 0, 2), &[3.0, 1.0, 1.0, 1.0, 0.1, 0.5]);
        close(&rows(&MeanField, &f, 0, 3), &[4.0, 1.0, 4.0, 1.0, 0.4, 0.5]);
        // At t = 1 slot 5 is empty, so only slot 1 counts.
        close(
            &rows(&MeanField, &f, 1, 0),
            &[1.0, 11.0, 2.0, 11.0, 0.2, -0.5],
        );
        // Bootstrap: own bootstrap observation, the last step's neighbour means.
        let mut bootstrap = Vec::new();
        MeanField.row(&f, &f.bootstrap_obs[0..2], 1, 0, &mut bootstrap);
        close(&bootstrap, &[100.0, 7.0, 2.0, 11.0, 0.2, -0.5]);
    }

    #[test]
    fn checkpoint_state_restores_an_identical_learner() {
        let run = small_run();
        assert_checkpoint_round_trip(|| -> CcppoMf {
            SharedPpo::new(
                "ccppo-mf",
                MeanField,
                Box::new(FixedLcf::new(&run.lcf)),
                &run,
                2,
                2,
                tch::Device::Cpu,
            )
        });
    }
}
