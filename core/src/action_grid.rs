//! DQN's discrete actions: a grid of `[steering, throttle_brake]` points (see `q_policy`), kept
//! free of libtorch so the configuration can check a grid without the network.

/// Most grid points a Q-policy may have (a hostile blob must not ask for a huge output layer).
pub const MAX_GRID_ACTIONS: usize = 4096;

/// The discrete actions: every steering value with every throttle value.
#[derive(Debug, Clone, PartialEq)]
pub struct ActionGrid {
    steering: Vec<f32>,
    throttle: Vec<f32>,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "an action grid needs 1 to {MAX_GRID_ACTIONS} points from steering and throttle values \
     that each lie in [-1, 1] and increase strictly"
)]
pub struct GridError;

impl ActionGrid {
    pub fn new(steering: Vec<f32>, throttle: Vec<f32>) -> Result<Self, GridError> {
        let valid = |values: &[f32]| {
            !values.is_empty()
                && values.iter().all(|v| (-1.0..=1.0).contains(v))
                && values.windows(2).all(|w| w[0] < w[1])
        };
        let points = steering.len().saturating_mul(throttle.len());
        if !valid(&steering) || !valid(&throttle) || points > MAX_GRID_ACTIONS {
            return Err(GridError);
        }
        Ok(ActionGrid { steering, throttle })
    }

    /// Number of discrete actions.
    pub fn len(&self) -> usize {
        self.steering.len() * self.throttle.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// `[steering, throttle_brake]` of action `index` (< `len()`).
    pub fn action(&self, index: usize) -> [f32; 2] {
        let n = self.steering.len();
        [self.steering[index % n], self.throttle[index / n]]
    }

    /// The index of `action` if it is exactly a grid point (what actors apply and ship).
    pub fn index_of(&self, action: &[f32]) -> Option<usize> {
        let [steering, throttle] = action else {
            return None;
        };
        let s = self.steering.iter().position(|v| v == steering)?;
        let t = self.throttle.iter().position(|v| v == throttle)?;
        Some(t * self.steering.len() + s)
    }

    pub fn steering(&self) -> &[f32] {
        &self.steering
    }

    pub fn throttle(&self) -> &[f32] {
        &self.throttle
    }
}
