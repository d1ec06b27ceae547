//! CCPPO, concatenating critic (CoPO's baseline): PPO with parameter sharing whose critic also
//! sees the observations and actions of the agent's k nearest neighbours, zero-padded when it
//! has fewer; the actor stays decentralised (own observation only).
//!
//! ```text
//! for each update:
//!     fold the batch's observations into the running normaliser
//!     for each agent i at step t, j₁…j_k = its k nearest live neighbours within d_n at t:
//!         x_i = ô_i ‖ ô_j₁ ‖ … ‖ ô_j_k ‖ a_j₁ ‖ … ‖ a_j_k      (missing ones: zeros; ô normalised)
//!     V ← critic(x); A, R ← GAE(rewards, V, γ, λ) per agent
//!     repeat `epochs` times, over shuffled minibatches:
//!         ρ = π(a|ô) / π_behaviour(a|ô)
//!         L = −min(ρÂ, clip(ρ, 1±ε)Â) + c_v·L_V(V(x), R) − c_e·H[π]
//!         Adam step on ∇L, gradient norm clipped
//! ```
//!
//! k is `ccppo.neighbours` (CoPO: 4); fragments list neighbours nearest first. For the
//! bootstrap value after a fragment, x uses the agent's bootstrap observation with the last
//! step's neighbours: the next step's neighbourhood is not shipped, and one decision step
//! (0.1 s) changes it little.

use std::iter::repeat_n;

use super::batch::{CriticInput, NormalizedFragment};
use super::shared_ppo::SharedPpo;

/// Own observation ‖ the k nearest neighbours' observations ‖ their actions, zero-padded.
pub struct Concat {
    pub neighbours: usize,
}

impl CriticInput for Concat {
    fn width(&self, obs_dim: usize, action_dim: usize) -> usize {
        obs_dim + self.neighbours * (obs_dim + action_dim)
    }

    fn row(&self, f: &NormalizedFragment, own: &[f32], t: usize, slot: usize, out: &mut Vec<f32>) {
        out.extend_from_slice(own);
        let k = self.neighbours;
        let nearest = || f.live_neighbours(t, slot).take(k);
        let present = nearest().count();
        for n in nearest() {
            out.extend_from_slice(f.obs(t, n));
        }
        out.extend(repeat_n(0.0, (k - present) * f.raw.obs_dim));
        for n in nearest() {
            out.extend_from_slice(f.action(t, n));
        }
        out.extend(repeat_n(0.0, (k - present) * f.raw.action_dim));
    }
}

pub type CcppoConcat = SharedPpo<Concat>;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::coordination::FixedLcf;
    use crate::algo::testing::{
        assert_checkpoint_round_trip, close, neighbourhood_fragment, rows, small_run, unnormalized,
    };

    #[test]
    fn concat_rows_on_a_known_neighbourhood() {
        let raw = neighbourhood_fragment();
        let f = unnormalized(&raw);
        let concat = Concat { neighbours: 4 };
        assert_eq!(concat.width(2, 2), 2 + 4 * 4);
        let z = 0.0;
        // Five neighbours, nearest first: the farthest (slot 1) is left out.
        close(
            &rows(&concat, &f, 0, 0),
            &[
                1., 1., 6., 1., 5., 1., 4., 1., 3., 1., 0.6, 0.5, 0.5, 0.5, 0.4, 0.5, 0.3, 0.5,
            ],
        );
        // No neighbours: all padding.
        close(
            &rows(&concat, &f, 0, 1),
            &[2., 1., z, z, z, z, z, z, z, z, z, z, z, z, z, z, z, z],
        );
        close(
            &rows(&concat, &f, 0, 2),
            &[3., 1., 1., 1., z, z, z, z, z, z, 0.1, 0.5, z, z, z, z, z, z],
        );
        // At t = 1 slot 5 is empty, so slot 1 is the nearest.
        close(
            &rows(&concat, &f, 1, 0),
            &[
                1., 11., 2., 11., z, z, z, z, z, z, 0.2, -0.5, z, z, z, z, z, z,
            ],
        );
        // Bootstrap: own bootstrap observation, the last step's neighbours.
        let mut bootstrap = Vec::new();
        concat.row(&f, &f.bootstrap_obs[6..8], 1, 3, &mut bootstrap);
        close(
            &bootstrap,
            &[
                103., 7., 5., 11., z, z, z, z, z, z, 0.5, -0.5, z, z, z, z, z, z,
            ],
        );
    }

    #[test]
    fn checkpoint_state_restores_an_identical_learner() {
        let run = small_run();
        assert_checkpoint_round_trip(|| -> CcppoConcat {
            SharedPpo::new(
                "ccppo-concat",
                Concat { neighbours: 4 },
                Box::new(FixedLcf::new(&run.lcf)),
                &run,
                2,
                2,
                tch::Device::Cpu,
            )
        });
    }
}
