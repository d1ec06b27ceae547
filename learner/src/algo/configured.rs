//! The algorithm a run's configuration names (`learner.algo`), built. The one file that
//! knows every algorithm, apart so that the algorithms' common ground (`algo/mod.rs`) imports
//! none of them.

use tch::Device;

use junction_core::config::{AlgoKind, RunConfig};
use junction_core::spec::ACTION_DIM;

use super::ccppo_concat::Concat;
use super::ccppo_mf::MeanField;
use super::coordination::{Coordination, FixedLcf};
use super::ippo::OwnObservation;
use super::shared_ppo::SharedPpo;
use super::{AlgoError, Algorithm, cl, copo, dqn, dynamic_lcf};

/// The configured algorithm (`learner.algo`) for the run's observation size, on `device`.
pub fn build(config: &RunConfig, device: Device) -> Result<Box<dyn Algorithm + Send>, AlgoError> {
    let obs_dim = config.policy_obs_dim();
    let ppo = |name, input, coordination: Box<dyn Coordination>| {
        SharedPpo::new(
            name,
            input,
            coordination,
            config,
            obs_dim,
            ACTION_DIM,
            device,
        )
    };
    let fixed = || Box::new(FixedLcf::new(&config.lcf));
    Ok(match config.learner.algo {
        AlgoKind::Ippo => Box::new(ppo("ippo", OwnObservation, fixed())),
        AlgoKind::Cl => Box::new(cl::Cl::new(
            ppo("ippo", OwnObservation, fixed()),
            cl::Curriculum::new(&config.curriculum),
        )),
        AlgoKind::CcppoMf => Box::new(SharedPpo::new(
            "ccppo-mf",
            MeanField,
            fixed(),
            config,
            obs_dim,
            ACTION_DIM,
            device,
        )),
        AlgoKind::CcppoConcat => Box::new(SharedPpo::new(
            "ccppo-concat",
            Concat {
                neighbours: config.ccppo.neighbours,
            },
            fixed(),
            config,
            obs_dim,
            ACTION_DIM,
            device,
        )),
        AlgoKind::Copo => Box::new(ppo(
            "copo",
            OwnObservation,
            Box::new(copo::CopoLcf::new(&config.copo, &config.lcf, device)),
        )),
        AlgoKind::DynamicLcf => Box::new(ppo(
            "dynamic-lcf",
            OwnObservation,
            Box::new(dynamic_lcf::DynamicLcf::new(
                &config.dynamic_lcf,
                &config.lcf,
                device,
            )),
        )),
        AlgoKind::Dqn => Box::new(
            dqn::Dqn::new(&config.dqn, obs_dim, device, config.run.seed)?
                .with_coordination(&config.lcf),
        ),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::Stage;
    use crate::algo::cl::Curriculum;

    #[test]
    fn the_default_schedule_is_copos_and_other_algorithms_train_every_agent() {
        let config = RunConfig::default();
        let c = Curriculum::new(&config.curriculum);
        assert_eq!(
            c.stage(0, 30),
            Stage {
                index: 0,
                agents: 8
            }
        );
        assert_eq!(c.stage(499_999, 30).index, 0);
        assert_eq!(c.stage(500_000, 30).index, 1);
        assert_eq!(
            c.stage(1_500_000, 30),
            Stage {
                index: 3,
                agents: 30
            }
        );
        let mut config = config;
        config.ppo.hidden = vec![8];
        let ippo = crate::algo::configured::build(&config, tch::Device::Cpu).unwrap();
        assert_eq!(
            ippo.stage(0, 30),
            Stage {
                index: 0,
                agents: 30
            }
        );
        config.learner.algo = junction_core::config::AlgoKind::Cl;
        let cl = crate::algo::configured::build(&config, tch::Device::Cpu).unwrap();
        assert_eq!(cl.name(), "cl");
        assert_eq!(
            cl.stage(0, 30),
            Stage {
                index: 0,
                agents: 8
            }
        );
        assert_eq!(
            cl.stage(2_000_000, 30),
            Stage {
                index: 3,
                agents: 30
            }
        );
    }
}
