//! Observation and action layout shared by the simulator, the policy and the wire, and the
//! size limits every decoder of a peer's data enforces.
//!
//! The observation follows MetaDrive's multi-agent layout (see `docs/OBSERVATION.md`): ego
//! state, navigation towards the next two checkpoints, then the lidar. Every value is in [0, 1].
//! Change the layout only together with [`OBS_LAYOUT_VERSION`]: checkpoints record it and actors
//! refuse weights trained on another layout.

/// Bumped whenever the meaning or order of observation values changes.
pub const OBS_LAYOUT_VERSION: u32 = 1;

/// Ego state: road-edge distances (2), heading error, speed, steering, last action (2), yaw
/// rate, lateral offset.
pub const EGO_DIM: usize = 9;
/// Navigation: the next two checkpoints × (x, y, bend radius, bend direction, bend angle).
pub const NAV_DIM: usize = 10;
/// Checkpoints described in the navigation part.
pub const NAV_CHECKPOINTS: usize = 2;
/// Values per checkpoint in the navigation part.
pub const NAV_PER_CHECKPOINT: usize = 5;
/// Offset of the first lidar beam in the observation.
pub const LIDAR_OFFSET: usize = EGO_DIM + NAV_DIM;

/// `[steering, throttle_brake]`, both in [-1, 1] (paper §3.3: steering −1 full left, +1 full
/// right; throttle_brake −1 full brake, +1 full throttle; no reverse).
pub const ACTION_DIM: usize = 2;

/// Observation length for a lidar with `lidar_beams` beams (91 for MetaDrive's 72 beams).
pub const fn obs_dim(lidar_beams: usize) -> usize {
    LIDAR_OFFSET + lidar_beams
}

/// Wire protocol version; every message carries it and peers refuse others.
pub const PROTOCOL_VERSION: u32 = 1;

/// Upper bounds that keep a hostile header from asking for absurd allocations.
pub const MAX_STEPS: usize = 100_000;
pub const MAX_AGENTS: usize = 10_000;
pub const MAX_OBS_DIM: usize = 65_536;
pub const MAX_ACTION_DIM: usize = 64;
/// Longest actor id, actor name or scenario name accepted from a peer, in bytes.
pub const MAX_NAME_BYTES: usize = 256;

/// Observation values CoPO's LCF angle adds after the scenario's (one: φ encoded in [0, 1]).
pub const LCF_OBS_COLUMNS: usize = 1;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metadrive_marl_layout_has_91_values() {
        assert_eq!(obs_dim(72), 91);
        assert_eq!(NAV_DIM, NAV_CHECKPOINTS * NAV_PER_CHECKPOINT);
    }
}
