//! Generalised advantage estimation (Schulman et al. 2016) over a fragment's agent slots.

/// One fragment's per-cell inputs, row-major `[step][slot]`.
pub struct Trajectories<'a> {
    pub steps: usize,
    pub agents: usize,
    pub rewards: &'a [f32],
    pub dones: &'a [bool],
    pub alive: &'a [bool],
    /// V(obs[t][slot]); ignored where the slot is empty.
    pub values: &'a [f32],
    /// V(bootstrap_obs[slot]) for agents that continue past the last step.
    pub bootstrap_values: &'a [f32],
}

/// Advantages and value targets (advantage + value), 0 in empty cells.
pub struct Estimates {
    pub advantages: Vec<f32>,
    pub returns: Vec<f32>,
}

/// A done ends the agent's own chain of advantages and its return, unless the return
/// `outlives_agent`: then it bootstraps from the scene's value after that step
/// (`scene_values_after_step`); an agent alive at the last step bootstraps from its value
/// after the fragment; an empty cell separates agents sharing a slot.
pub fn gae(traj: &Trajectories, gamma: f32, lambda: f32, outlives_agent: bool) -> Estimates {
    let after_done = outlives_agent.then(|| scene_values_after_step(traj));
    let cells = traj.steps * traj.agents;
    let mut advantages = vec![0.0; cells];
    let mut returns = vec![0.0; cells];
    for slot in 0..traj.agents {
        let mut next_value = traj.bootstrap_values[slot];
        let mut next_advantage = 0.0;
        for t in (0..traj.steps).rev() {
            let i = t * traj.agents + slot;
            if !traj.alive[i] {
                next_value = 0.0;
                next_advantage = 0.0;
                continue;
            }
            let (bootstrap, carried) = if traj.dones[i] {
                (after_done.as_ref().map_or(0.0, |v| v[t]), 0.0)
            } else {
                (next_value, next_advantage)
            };
            let delta = traj.rewards[i] + gamma * bootstrap - traj.values[i];
            let advantage = delta + gamma * lambda * carried;
            advantages[i] = advantage;
            returns[i] = advantage + traj.values[i];
            next_value = traj.values[i];
            next_advantage = advantage;
        }
    }
    Estimates {
        advantages,
        returns,
    }
}

/// The scene's value after each step t: the mean value at t + 1 of the agents that go on past
/// t (after the last step, their bootstrap values), what an agent ending at t leaves behind
/// when its return outlives it; 0 where no agent goes on (the scene ended).
fn scene_values_after_step(traj: &Trajectories) -> Vec<f32> {
    let goes_on = |t: usize, slot: usize| {
        let i = t * traj.agents + slot;
        traj.alive[i] && !traj.dones[i]
    };
    (0..traj.steps)
        .map(|t| {
            let (mut sum, mut count) = (0.0, 0usize);
            for slot in (0..traj.agents).filter(|&s| goes_on(t, s)) {
                sum += if t + 1 < traj.steps {
                    traj.values[(t + 1) * traj.agents + slot]
                } else {
                    traj.bootstrap_values[slot]
                };
                count += 1;
            }
            if count == 0 { 0.0 } else { sum / count as f32 }
        })
        .collect()
}

/// GAE's advantages are linear in the rewards: A_k = Σ_j (γλ)^{j−k}·r_j + (terms without
/// rewards), summed over the steps j ≥ k of the same agent up to its done. This is the
/// transpose: given a weight c_k per cell, the weight w_j = Σ_k c_k·∂A_k/∂r_j each reward
/// carries in Σ_k c_k·A_k, computed forwards as w_j = c_j + γλ·w_{j−1} along an agent's steps.
/// (The dynamic LCF's meta-gradient reaches its coordinated rewards through it.)
/// `dones` and `alive` are a fragment's, row-major `[step][slot]` like `cotangents`.
pub fn reward_adjoint(
    (steps, agents): (usize, usize),
    dones: &[bool],
    alive: &[bool],
    cotangents: &[f32],
    gamma: f32,
    lambda: f32,
) -> Vec<f32> {
    let mut weights = vec![0.0; steps * agents];
    for slot in 0..agents {
        let mut carried = 0.0;
        for t in 0..steps {
            let i = t * agents + slot;
            if !alive[i] {
                carried = 0.0;
                continue;
            }
            weights[i] = cotangents[i] + gamma * lambda * carried;
            // The next step is the same agent's unless this one ended it.
            carried = if dones[i] { 0.0 } else { weights[i] };
        }
    }
    weights
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_hand_computed_values() {
        // Two slots, three steps, γ = 0.9, λ = 0.8.
        // Slot 0: agent A done at t = 1, a new agent B at t = 2 that continues (bootstrap 2.0).
        // Slot 1: empty at t = 0, agent C at t = 1..2 continuing (bootstrap 1.0).
        let traj = Trajectories {
            steps: 3,
            agents: 2,
            rewards: &[1.0, 0.0, 2.0, 1.0, 0.5, -1.0],
            dones: &[false, false, true, false, false, false],
            alive: &[true, false, true, true, true, true],
            values: &[0.5, 0.0, 1.0, 0.2, 0.4, 0.3],
            bootstrap_values: &[2.0, 1.0],
        };
        let e = gae(&traj, 0.9, 0.8, false);
        // Slot 0. t=2 (B): δ = 0.5 + 0.9·2.0 − 0.4 = 1.9 → A = 1.9.
        // t=1 (A, done): δ = 2.0 − 1.0 = 1.0 → A = 1.0 (nothing carried across the done).
        // t=0 (A): δ = 1.0 + 0.9·1.0 − 0.5 = 1.4; A = 1.4 + 0.72·1.0 = 2.12.
        // Slot 1. t=2: δ = −1 + 0.9·1.0 − 0.3 = −0.4 → A = −0.4.
        // t=1: δ = 1.0 + 0.9·0.3 − 0.2 = 1.07; A = 1.07 + 0.72·(−0.4) = 0.782.
        let expected_adv = [2.12, 0.0, 1.0, 0.782, 1.9, -0.4];
        let expected_ret = [2.62, 0.0, 2.0, 0.982, 2.3, -0.1];
        for i in 0..6 {
            assert!(
                (e.advantages[i] - expected_adv[i]).abs() < 1e-5,
                "adv[{i}] = {}",
                e.advantages[i]
            );
            assert!(
                (e.returns[i] - expected_ret[i]).abs() < 1e-5,
                "ret[{i}] = {}",
                e.returns[i]
            );
        }
    }

    #[test]
    fn the_reward_adjoint_is_the_transpose_of_gae_in_the_rewards() {
        // The layout of `matches_hand_computed_values`: slot 0 holds agent A (done at t = 1)
        // then B; slot 1 is empty, then holds C.
        let (dones, alive) = (
            [false, false, true, false, false, false],
            [true, false, true, true, true, true],
        );
        let values = [0.5, 0.0, 1.0, 0.2, 0.4, 0.3];
        let traj = |rewards: &[f32; 6]| -> Vec<f32> {
            gae(
                &Trajectories {
                    steps: 3,
                    agents: 2,
                    rewards,
                    dones: &dones,
                    alive: &alive,
                    values: &values,
                    bootstrap_values: &[2.0, 1.0],
                },
                0.9,
                0.8,
                false,
            )
            .advantages
        };
        let c = [1.0, 5.0, -2.0, 0.5, 3.0, 4.0];
        let w = reward_adjoint((3, 2), &dones, &alive, &c, 0.9, 0.8);
        // By hand (γλ = 0.72): A's steps t = 0, 1 (done): w = 1, −2 + 0.72·1; B at t = 2:
        // w = 3 (a new agent carries nothing); C at t = 1, 2: w = 0.5, 4 + 0.72·0.5; the empty
        // cell 0.
        let expected = [1.0, 0.0, -1.28, 0.5, 3.0, 4.36];
        for (got, want) in w.iter().zip(expected) {
            assert!((got - want).abs() < 1e-6, "{w:?}");
        }
        // And it is the transpose: Σ c·(A(r + Δ) − A(r)) = Σ w·Δ for any change Δ.
        let r = [1.0, 0.0, 2.0, 1.0, 0.5, -1.0];
        let delta = [0.3, 0.0, -1.0, 2.0, 0.7, 0.1];
        let shifted: [f32; 6] = std::array::from_fn(|i| r[i] + delta[i]);
        let (before, after) = (traj(&r), traj(&shifted));
        let lhs: f32 = (0..6).map(|i| c[i] * (after[i] - before[i])).sum();
        let rhs: f32 = (0..6).map(|i| w[i] * delta[i]).sum();
        assert!((lhs - rhs).abs() < 1e-5, "{lhs} vs {rhs}");
    }

    #[test]
    fn lambda_one_gamma_one_gives_monte_carlo_returns() {
        let traj = Trajectories {
            steps: 3,
            agents: 1,
            rewards: &[1.0, 2.0, 3.0],
            dones: &[false, false, true],
            alive: &[true, true, true],
            values: &[0.0, 10.0, -4.0],
            bootstrap_values: &[100.0],
        };
        let e = gae(&traj, 1.0, 1.0, false);
        assert_eq!(e.returns, vec![6.0, 5.0, 3.0]);
    }

    #[test]
    fn a_return_that_outlives_its_agent_goes_on_with_the_agents_left_in_the_scene() {
        // Three slots, three steps. Slot 0: agent A ends at t = 0, slot empty after.
        // Slot 1: agent B goes on through the fragment (bootstrap 6.0). Slot 2: agent C goes
        // on past t = 0, ends at t = 1; agent D spawns at t = 2 and goes on (bootstrap 8.0).
        let (dones, alive) = (
            [true, false, false, false, false, true, false, false, false],
            [true, true, true, false, true, true, false, true, true],
        );
        let values = [1.0, 2.0, 3.0, 0.0, 4.0, 5.0, 0.0, 7.0, 9.0];
        let traj = Trajectories {
            steps: 3,
            agents: 3,
            rewards: &[0.5; 9],
            dones: &dones,
            alive: &alive,
            values: &values,
            bootstrap_values: &[0.0, 6.0, 8.0],
        };
        // After t = 0, B and C go on: (4 + 5) / 2; after t = 1 only B does (C ends there,
        // D is not there yet): 7; after t = 2, B and D: (6 + 8) / 2.
        let scene = scene_values_after_step(&traj);
        assert_eq!(scene, vec![4.5, 7.0, 7.0]);
        let e = gae(&traj, 1.0, 0.5, true);
        // A ends at t = 0 but its return goes on: δ = 0.5 + 4.5 − 1 = 4.0; C at t = 1:
        // δ = 0.5 + 7 − 5 = 2.5, and at t = 0 C carries it: 0.5 + 5 − 3 + 0.5·2.5 = 3.75.
        assert_eq!(e.advantages[0], 4.0);
        assert_eq!(e.advantages[5], 2.5);
        assert_eq!(e.advantages[2], 3.75);
        // Where the return ends with the agent, A's is its last reward less its value.
        assert_eq!(gae(&traj, 1.0, 0.5, false).advantages[0], -0.5);
        // A scene whose every agent ends leaves nothing to go on with.
        let all_done = [true; 9];
        let ended = Trajectories {
            dones: &all_done,
            alive: &[true; 9],
            ..traj
        };
        assert_eq!(scene_values_after_step(&ended), vec![0.0; 3]);
    }
}
