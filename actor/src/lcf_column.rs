//! CoPO's LCF on the actor side: when the policy blob carries an LCF distribution, each agent
//! draws its angle φ from it when it spawns, keeps it for its whole episode, and sees it as one
//! more observation value after the scene's (`lcf_inputs::phi_observation`). A policy without the
//! distribution takes the scene's observation as it is, and nothing here changes it.

use std::borrow::Cow;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use junction_common::lcf::LcfDistribution;
use junction_common::weights::{self, WeightsError};
use junction_core::lcf_inputs;

/// The LCF distribution a policy blob carries, if any.
pub fn blob_distribution(blob: &[u8]) -> Result<Option<LcfDistribution>, WeightsError> {
    LcfDistribution::from_metadata(&weights::metadata(blob)?)
}

pub struct LcfColumn {
    distribution: Option<LcfDistribution>,
    /// φ in degrees of the agent in each slot of each scene; `None`: no agent, or one that has
    /// not been seen yet.
    phi: Vec<Vec<Option<f32>>>,
    /// Its own stream, so the action noise is the same with or without the LCF.
    rng: ChaCha8Rng,
}

impl LcfColumn {
    /// For scenes of `slots` agent slots each.
    pub fn new(seed: u64, slots: impl IntoIterator<Item = usize>) -> Self {
        LcfColumn {
            distribution: None,
            phi: slots.into_iter().map(|n| vec![None; n]).collect(),
            rng: ChaCha8Rng::seed_from_u64(seed),
        }
    }

    /// The distribution of the policy now running; agents already on the road keep their φ.
    pub fn set_distribution(&mut self, distribution: Option<LcfDistribution>) {
        self.distribution = distribution;
    }

    /// Values appended to each observation row.
    pub fn columns(&self) -> usize {
        self.distribution
            .map_or(0, |_| LcfDistribution::OBS_COLUMNS)
    }

    /// Forgets every agent: the scenes were rebuilt with `slots` slots each.
    pub fn reset(&mut self, slots: impl IntoIterator<Item = usize>) {
        self.phi = slots.into_iter().map(|n| vec![None; n]).collect();
    }

    /// Draws φ for the agents alive in scene `scene` that have none yet (just spawned).
    pub fn spawn(&mut self, scene: usize, alive: &[bool]) {
        let Some(distribution) = self.distribution else {
            return;
        };
        for (phi, _) in self.phi[scene]
            .iter_mut()
            .zip(alive)
            .filter(|(phi, alive)| **alive && phi.is_none())
        {
            *phi = Some(distribution.sample(&mut self.rng));
        }
    }

    /// Agents of scene `scene` whose episodes ended this step give up their φ.
    pub fn finish(&mut self, scene: usize, dones: &[bool]) {
        for (phi, _) in self.phi[scene].iter_mut().zip(dones).filter(|(_, d)| **d) {
            *phi = None;
        }
    }

    /// Every slot's observation row as the policy takes it (`obs` holds the scene's rows of
    /// `obs_dim` values): with φ appended, 0 for a slot without an agent.
    pub fn observations<'a>(&self, scene: usize, obs: &'a [f32], obs_dim: usize) -> Cow<'a, [f32]> {
        if self.columns() == 0 {
            return Cow::Borrowed(obs);
        }
        let mut rows = Vec::with_capacity(obs.len() + self.phi[scene].len());
        for (row, phi) in obs.chunks_exact(obs_dim).zip(&self.phi[scene]) {
            rows.extend_from_slice(row);
            rows.push(phi.map_or(0.0, lcf_inputs::phi_observation));
        }
        Cow::Owned(rows)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const WIDE: LcfDistribution = LcfDistribution {
        mean_deg: 20.0,
        std_deg: 30.0,
    };

    #[test]
    fn without_a_distribution_the_observation_is_the_scenes() {
        let mut column = LcfColumn::new(1, [2]);
        column.spawn(0, &[true, true]);
        let obs = [0.1, 0.2, 0.3, 0.4];
        assert!(matches!(column.observations(0, &obs, 2), Cow::Borrowed(o) if o == obs));
        assert_eq!(column.columns(), 0);
    }

    #[test]
    fn an_agent_keeps_its_phi_for_its_episode_and_a_new_one_draws_afresh() {
        let mut column = LcfColumn::new(1, [3]);
        column.set_distribution(Some(WIDE));
        let obs = [0.0f32; 6];
        column.spawn(0, &[true, false, true]);
        let first = column.observations(0, &obs, 2).into_owned();
        assert_eq!(first.len(), 9);
        // Slot 1 is empty: its φ value is 0; the others hold (φ/90° + 1)/2.
        assert_eq!(first[5], 0.0);
        assert!(first[2] > 0.0 && first[8] > 0.0 && first[2] != first[8]);
        // A step later nobody is new: same values, even under another distribution.
        column.set_distribution(Some(LcfDistribution {
            mean_deg: -80.0,
            std_deg: 1.0,
        }));
        column.spawn(0, &[true, false, true]);
        assert_eq!(column.observations(0, &obs, 2).into_owned(), first);
        // Slot 0's agent ends; the agent that takes its place draws from the new distribution.
        column.finish(0, &[true, false, false]);
        column.spawn(0, &[true, true, true]);
        let next = column.observations(0, &obs, 2).into_owned();
        let phi = |v: f32| lcf_inputs::phi_from_observation(v);
        assert!(phi(next[2]) < -70.0, "{}", phi(next[2]));
        assert!(phi(next[5]) < -70.0, "{}", phi(next[5]));
        assert_eq!(next[8], first[8]);
    }

    #[test]
    fn draws_are_seeded() {
        let draw = |seed| {
            let mut column = LcfColumn::new(seed, [4]);
            column.set_distribution(Some(WIDE));
            column.spawn(0, &[true; 4]);
            column.observations(0, &[0.0; 4], 1).into_owned()
        };
        assert_eq!(draw(3), draw(3));
        assert_ne!(draw(3), draw(4));
    }
}
