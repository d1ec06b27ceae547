//! A broadcast policy of whichever kind its blob holds: the Gaussian policy
//! ([`GaussianPolicy`], PPO's) or the Q-policy over an action grid ([`QPolicy`], DQN's),
//! told apart by the blob's `policy` metadata ([`KIND_KEY`]). Actors, `actor render` and
//! evaluation take every policy through here; it sits above both kinds, which know nothing
//! of each other.

use tch::Device;

use crate::policy::{GaussianPolicy, KIND_KEY, Policy, PolicyMeta};
use crate::q_policy::QPolicy;
use crate::weights::{Decoded, WeightsError};

/// Rebuilds whichever policy a blob holds (its metadata says which), on `device`.
pub fn decode(bytes: &[u8], device: Device) -> Result<(Box<dyn Policy>, PolicyMeta), WeightsError> {
    let decoded = Decoded::decode(bytes)?;
    match decoded.metadata.get(KIND_KEY).map(String::as_str) {
        None | Some(GaussianPolicy::KIND) => {
            let (policy, meta) = GaussianPolicy::from_decoded(decoded, device)?;
            Ok((Box::new(policy), meta))
        }
        Some(QPolicy::KIND) => {
            let (policy, meta) = QPolicy::from_decoded(decoded, device)?;
            Ok((Box::new(policy), meta))
        }
        Some(_) => Err(WeightsError::Metadata {
            key: KIND_KEY.to_string(),
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::ObsNormalizer;
    use crate::q_policy::tests::metadrive_grid;
    use crate::weights;
    use junction_core::action_grid::ActionGrid;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use tch::Tensor;

    #[test]
    fn the_blob_says_its_kind_and_round_trips_grid_epsilon_and_weights() {
        tch::manual_seed(5);
        let mut q = QPolicy::new(Device::Cpu, 4, &[8, 8], metadrive_grid(), true);
        let mut stats = ObsNormalizer::new(4);
        stats.update(&[0.0, 1.0, 2.0, 3.0, 1.0, 1.0, 1.0, 1.0]);
        q.set_obs_stats(&stats);
        q.set_epsilon(0.25);
        let bytes = Policy::to_bytes(&q, 11).unwrap();
        let obs = [0.3f32, 0.1, 0.9, 0.5, 0.2, 0.2, 0.7, 0.4];
        let (decoded, meta) = decode(&bytes, Device::Cpu).unwrap();
        assert_eq!(meta.version, 11);
        assert_eq!(
            decoded.deterministic(&obs).unwrap(),
            q.deterministic(&obs).unwrap()
        );
        let draws = |p: &dyn Policy| p.sample(&obs, &mut ChaCha8Rng::seed_from_u64(2)).unwrap();
        assert_eq!(
            draws(decoded.as_ref()),
            draws(&q),
            "ε travels with the blob"
        );

        let (mut other, _) = QPolicy::from_bytes(&bytes, Device::Cpu).unwrap();
        assert_eq!((other.epsilon(), other.grid()), (0.25, q.grid()));
        assert_eq!(other.obs_stats().unwrap(), q.obs_stats().unwrap());
        // A Gaussian blob decodes as a Gaussian, and is not a Q-policy's.
        let gaussian = GaussianPolicy::new(Device::Cpu, 4, 2, &[8], 0.0)
            .to_bytes(1)
            .unwrap();
        let (g, _) = decode(&gaussian, Device::Cpu).unwrap();
        assert_eq!(g.deterministic(&obs).unwrap().len(), 4);
        assert!(other.load_bytes(&gaussian).is_err());
        // Another grid is refused even with as many points.
        let mut shifted = QPolicy::new(
            Device::Cpu,
            4,
            &[8, 8],
            ActionGrid::new(
                vec![-1.0, -0.5, 0.0, 0.5, 1.0],
                vec![-1.0, -0.25, 0.0, 0.25, 1.0],
            )
            .unwrap(),
            true,
        );
        assert!(shifted.load_bytes(&bytes).is_err());
    }

    #[test]
    fn unknown_kinds_and_bad_metadata_are_errors() {
        let q = QPolicy::new(Device::Cpu, 2, &[4], metadrive_grid(), true);
        let named = q.named_tensors();
        let refs: Vec<(String, &Tensor)> = named.iter().map(|(n, t)| (n.clone(), t)).collect();
        let good = Policy::to_bytes(&q, 1).unwrap();
        let metadata = Decoded::decode(&good).unwrap().metadata;
        for (key, value) in [
            (KIND_KEY, "sarsa"),
            ("epsilon", "1.5"),
            ("grid_steering", "0,x"),
            ("grid_throttle", "1,0"),
            ("dueling", "maybe"),
        ] {
            let mut bad = metadata.clone();
            bad.insert(key.into(), value.into());
            let bytes = weights::encode(&refs, bad).unwrap();
            assert!(
                matches!(
                    decode(&bytes, Device::Cpu),
                    Err(WeightsError::Metadata { .. })
                ),
                "{key} = {value} was accepted"
            );
        }
    }
}
