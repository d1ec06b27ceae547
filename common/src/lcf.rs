//! Local coordination (paper §3.2, CoPO): the neighbourhood reward r_N, the global reward r_G,
//! the coordinated reward r_C = α·cos φ·r_i + β·sin φ·r_N, CoPO's per-agent LCF distribution
//! (sampled by actors, appended to the observation), and the neighbourhood features S_N(i,t)
//! that the paper's dynamic LCF maps to an angle φ (computed by the simulator and shipped in
//! each `RolloutFragment`; `lcf_inputs` owns their layout and CoPO's φ column encoding).

use std::borrow::Cow;
use std::collections::BTreeMap;

use rand::Rng;
use rand_distr::StandardNormal;

use crate::fragment::RolloutFragment;
use crate::weights::WeightsError;
use junction_core::config::{LcfConfig, NeighbourhoodReward};

use junction_core::lcf_inputs::MAX_PHI_DEG;

/// r_C = α·cos φ·r_i + β·sin φ·r_N: φ = 0 is selfish (IPPO), φ = 90° fully cooperative.
pub fn coordinated_reward(
    own: f32,
    neighbourhood: f32,
    phi_rad: f32,
    alpha: f32,
    beta: f32,
) -> f32 {
    alpha * phi_rad.cos() * own + beta * phi_rad.sin() * neighbourhood
}

/// The reward each cell of `fragment` trains on under a fixed LCF angle (radians): the
/// fragment's own rewards when the coordination changes nothing (φ = 0, α = 1).
pub fn coordinated_rewards<'f>(
    fragment: &'f RolloutFragment,
    phi_rad: f32,
    lcf: &LcfConfig,
) -> Cow<'f, [f32]> {
    if phi_rad == 0.0 && lcf.alpha == 1.0 {
        return Cow::Borrowed(&fragment.rewards);
    }
    let neighbourhood = neighbourhood_rewards(fragment, lcf.neighbourhood_reward);
    fragment
        .rewards
        .iter()
        .zip(neighbourhood)
        .map(|(&own, n)| coordinated_reward(own, n, phi_rad, lcf.alpha, lcf.beta))
        .collect()
}

/// The reward each cell of `fragment` trains on under a per-cell LCF angle (radians, one per
/// cell; the dynamic LCF's).
pub fn coordinated_rewards_per_cell(
    fragment: &RolloutFragment,
    phi_rad: &[f32],
    lcf: &LcfConfig,
) -> Vec<f32> {
    let neighbourhood = neighbourhood_rewards(fragment, lcf.neighbourhood_reward);
    fragment
        .rewards
        .iter()
        .zip(neighbourhood)
        .zip(phi_rad)
        .map(|((&own, n), &phi)| coordinated_reward(own, n, phi, lcf.alpha, lcf.beta))
        .collect()
}

/// r_N per (step, slot) of a fragment: the mean reward of the neighbours that hold an agent at
/// that step, centred over the fragment's agents with neighbours when `kind` says so (0 when
/// alone or for an empty cell either way).
pub fn neighbourhood_rewards(fragment: &RolloutFragment, kind: NeighbourhoodReward) -> Vec<f32> {
    let mut out = vec![0.0; fragment.steps * fragment.agents];
    let mut with_neighbours = Vec::new();
    for t in 0..fragment.steps {
        for slot in 0..fragment.agents {
            let here = fragment.index(t, slot);
            if !fragment.alive[here] {
                continue;
            }
            let (mut sum, mut count) = (0.0f32, 0usize);
            for &j in fragment.neighbours(t, slot) {
                let cell = fragment.index(t, j as usize);
                if j as usize != slot && fragment.alive[cell] {
                    sum += fragment.rewards[cell];
                    count += 1;
                }
            }
            if count > 0 {
                out[here] = sum / count as f32;
                with_neighbours.push(here);
            }
        }
    }
    if kind == NeighbourhoodReward::Centred && !with_neighbours.is_empty() {
        let mean = with_neighbours
            .iter()
            .map(|&c| f64::from(out[c]))
            .sum::<f64>()
            / with_neighbours.len() as f64;
        for &cell in &with_neighbours {
            out[cell] -= mean as f32;
        }
    }
    out
}

/// r_G per (step, slot) of a fragment: the mean reward of every agent alive in the scene at
/// that step (CoPO's global reward), the same for all of them; 0 for empty cells.
pub fn global_rewards(fragment: &RolloutFragment) -> Vec<f32> {
    let mut out = vec![0.0; fragment.steps * fragment.agents];
    for t in 0..fragment.steps {
        let row = fragment.index(t, 0)..fragment.index(t, 0) + fragment.agents;
        let alive = &fragment.alive[row.clone()];
        let count = alive.iter().filter(|a| **a).count();
        if count == 0 {
            continue;
        }
        let sum: f32 = fragment.rewards[row.clone()]
            .iter()
            .zip(alive)
            .filter(|(_, a)| **a)
            .map(|(r, _)| r)
            .sum();
        let mean = sum / count as f32;
        for (value, _) in out[row].iter_mut().zip(alive).filter(|(_, a)| **a) {
            *value = mean;
        }
    }
    out
}

/// Labels of the neighbour-count buckets the learned φ is reported by (bounded, so the metric
/// has four series).
pub const NEIGHBOUR_BUCKETS: [&str; 4] = ["0", "1-2", "3-5", "6+"];

/// Index into [`NEIGHBOUR_BUCKETS`] of an agent with `neighbours` neighbours.
pub fn neighbour_bucket(neighbours: usize) -> usize {
    match neighbours {
        0 => 0,
        1..=2 => 1,
        3..=5 => 2,
        _ => 3,
    }
}

/// CoPO's LCF distribution: every agent draws its angle φ ~ N(μ, σ), clipped to ±90°, when it
/// spawns, keeps it for its whole episode and sees it as one more observation value (the last
/// one, [`phi_observation`]). The learner sends the current (μ, σ) in the metadata of every
/// policy blob; a blob without them is a policy that takes the plain observation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LcfDistribution {
    pub mean_deg: f32,
    pub std_deg: f32,
}

impl LcfDistribution {
    /// Metadata keys of a policy blob.
    pub const MEAN_KEY: &'static str = "lcf_mean_deg";
    pub const STD_KEY: &'static str = "lcf_std_deg";
    /// Observation values the LCF adds to the scenario's.
    pub const OBS_COLUMNS: usize = junction_core::spec::LCF_OBS_COLUMNS;

    pub fn to_metadata(self) -> BTreeMap<String, String> {
        // f32's Display is the shortest text that parses back to the same value.
        BTreeMap::from([
            (Self::MEAN_KEY.to_string(), self.mean_deg.to_string()),
            (Self::STD_KEY.to_string(), self.std_deg.to_string()),
        ])
    }

    /// The distribution a policy blob's metadata carries: none when neither key is present; an
    /// error when only one is, or a value is not a finite angle (σ > 0, |μ| ≤ 90°).
    pub fn from_metadata(
        metadata: &BTreeMap<String, String>,
    ) -> Result<Option<Self>, WeightsError> {
        let parse = |key: &str| metadata.get(key).map(|v| v.parse::<f32>().ok());
        match (parse(Self::MEAN_KEY), parse(Self::STD_KEY)) {
            (None, None) => Ok(None),
            (Some(Some(mean_deg)), Some(Some(std_deg)))
                if mean_deg.abs() <= MAX_PHI_DEG && std_deg > 0.0 && std_deg.is_finite() =>
            {
                Ok(Some(LcfDistribution { mean_deg, std_deg }))
            }
            _ => Err(WeightsError::Metadata {
                key: format!("{}/{}", Self::MEAN_KEY, Self::STD_KEY),
            }),
        }
    }

    /// One agent's φ in degrees, clipped to ±90°.
    pub fn sample(self, rng: &mut impl Rng) -> f32 {
        let z: f32 = rng.sample(StandardNormal);
        (self.mean_deg + self.std_deg * z).clamp(-MAX_PHI_DEG, MAX_PHI_DEG)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use std::f32::consts::FRAC_PI_2;

    /// The paper's coordination with weights α, β.
    fn weights(alpha: f32, beta: f32) -> LcfConfig {
        LcfConfig {
            alpha,
            beta,
            neighbourhood_reward: NeighbourhoodReward::Mean,
            ..junction_core::config::RunConfig::default().lcf
        }
    }

    #[test]
    fn coordinated_reward_spans_selfish_to_cooperative() {
        // φ = 0: the agent's own reward (IPPO); φ = 90°: only the neighbourhood's.
        assert_eq!(coordinated_reward(2.0, 7.0, 0.0, 1.0, 1.0), 2.0);
        assert!((coordinated_reward(2.0, 7.0, FRAC_PI_2, 1.0, 1.0) - 7.0).abs() < 1e-5);
        // φ = 60°, α = 1, β = 0.5: 2·½ + 0.5·7·(√3/2) = 1 + 3.0311
        let r = coordinated_reward(2.0, 7.0, FRAC_PI_2 * 2.0 / 3.0, 1.0, 0.5);
        assert!((r - 4.031_089).abs() < 1e-4, "{r}");
        // Alone (r_N = 0) at 90°: nothing to gain.
        assert!(coordinated_reward(2.0, 0.0, FRAC_PI_2, 1.0, 1.0).abs() < 1e-6);
    }

    #[test]
    fn neighbourhood_reward_is_the_mean_over_the_neighbours_at_that_step() {
        // 2 steps × 3 slots; step 0: 0 sees {1, 2}, 1 sees {0}, 2 alone; step 1: slot 2 empty,
        // 0 lists {1, 2} (the empty slot 2 does not count).
        let fragment = RolloutFragment {
            steps: 2,
            agents: 3,
            rewards: vec![1.0, 2.0, 6.0, 3.0, 5.0, 0.0],
            alive: vec![true, true, true, true, true, false],
            dones: vec![false; 6],
            neighbour_offsets: vec![0, 2, 3, 3, 5, 5, 5],
            neighbour_ids: vec![1, 2, 0, 1, 2],
            ..RolloutFragment::default()
        };
        assert_eq!(
            neighbourhood_rewards(&fragment, NeighbourhoodReward::Mean),
            vec![4.0, 1.0, 0.0, 5.0, 0.0, 0.0]
        );
        // Centred: the three agents with neighbours average 10/3, which each gives up; the
        // lone and the empty cells stay 0.
        let centred = neighbourhood_rewards(&fragment, NeighbourhoodReward::Centred);
        let third = 1.0 / 3.0;
        let expected = [
            4.0 - 10.0 * third,
            1.0 - 10.0 * third,
            0.0,
            5.0 - 10.0 * third,
            0.0,
            0.0,
        ];
        for (got, want) in centred.iter().zip(expected) {
            assert!((got - want).abs() < 1e-5, "{centred:?}");
        }
        // φ = 0, α = 1 trains on the own rewards untouched; φ = 90° on the neighbourhood's.
        assert!(matches!(
            coordinated_rewards(&fragment, 0.0, &weights(1.0, 1.0)),
            Cow::Borrowed(r) if r == fragment.rewards.as_slice()
        ));
        let cooperative = coordinated_rewards(&fragment, FRAC_PI_2, &weights(1.0, 1.0));
        let expected = [4.0, 1.0, 0.0, 5.0, 0.0, 0.0];
        for (got, want) in cooperative.iter().zip(expected) {
            assert!((got - want).abs() < 1e-5, "{cooperative:?}");
        }

        // A per-cell φ (the dynamic LCF), α = 1, β = 0.5: 0° at (0, 0) is the own reward bit
        // for bit; 90° is β·r_N alone; an agent without neighbours keeps only cos φ·r_i.
        let phi: Vec<f32> = [0.0f32, 90.0, 30.0, 90.0, -45.0, 0.0]
            .iter()
            .map(|d| d.to_radians())
            .collect();
        let per_cell = coordinated_rewards_per_cell(&fragment, &phi, &weights(1.0, 0.5));
        assert_eq!(per_cell[0], fragment.rewards[0]);
        let half_sqrt3 = 3.0f32.sqrt() / 2.0;
        let expected = [
            1.0,
            0.5 * 1.0,
            half_sqrt3 * 6.0,
            0.5 * 5.0,
            std::f32::consts::FRAC_1_SQRT_2 * 5.0,
            0.0,
        ];
        for (got, want) in per_cell.iter().zip(expected) {
            assert!((got - want).abs() < 1e-5, "{per_cell:?} vs {expected:?}");
        }
    }

    #[test]
    fn global_reward_is_the_scene_mean_over_the_agents_alive_at_that_step() {
        // Step 0: all three alive, mean (1 + 2 + 6)/3 = 3; step 1: slot 2 empty, (3 + 5)/2 = 4.
        let fragment = RolloutFragment {
            steps: 2,
            agents: 3,
            rewards: vec![1.0, 2.0, 6.0, 3.0, 5.0, 0.0],
            alive: vec![true, true, true, true, true, false],
            ..RolloutFragment::default()
        };
        assert_eq!(
            global_rewards(&fragment),
            vec![3.0, 3.0, 3.0, 4.0, 4.0, 0.0]
        );
    }

    #[test]
    fn neighbour_counts_fall_into_four_buckets() {
        let buckets: Vec<usize> = [0, 1, 2, 3, 5, 6, 40].map(neighbour_bucket).to_vec();
        assert_eq!(buckets, vec![0, 1, 1, 2, 2, 3, 3]);
    }

    #[test]
    fn the_lcf_distribution_round_trips_through_metadata_and_samples_within_range() {
        let d = LcfDistribution {
            mean_deg: 12.345_678,
            std_deg: 9.0,
        };
        assert_eq!(
            LcfDistribution::from_metadata(&d.to_metadata()).unwrap(),
            Some(d)
        );
        assert_eq!(
            LcfDistribution::from_metadata(&BTreeMap::new()).unwrap(),
            None
        );
        let mut half = d.to_metadata();
        half.remove(LcfDistribution::STD_KEY);
        assert!(LcfDistribution::from_metadata(&half).is_err());
        let mut bad = d.to_metadata();
        bad.insert(LcfDistribution::STD_KEY.into(), "NaN".into());
        assert!(LcfDistribution::from_metadata(&bad).is_err());
        bad.insert(LcfDistribution::STD_KEY.into(), "-1".into());
        assert!(LcfDistribution::from_metadata(&bad).is_err());

        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let wide = LcfDistribution {
            mean_deg: 80.0,
            std_deg: 50.0,
        };
        let samples: Vec<f32> = (0..1000).map(|_| wide.sample(&mut rng)).collect();
        assert!(samples.iter().all(|p| p.abs() <= 90.0));
        assert!(samples.contains(&90.0), "clipped at 90°");
    }
}
