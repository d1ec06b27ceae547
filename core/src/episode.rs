//! How agent episodes and scene episodes ended: what the simulator reports, fragments carry
//! and evaluations count. Free of the wire and of libtorch, so the simulator can use it.

/// How an agent's episode ended (paper §4.2, CoPO's metrics).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Outcome {
    Success = 0,
    Crash = 1,
    OutOfRoad = 2,
    Timeout = 3,
}

impl Outcome {
    pub const ALL: [Outcome; 4] = [
        Outcome::Success,
        Outcome::Crash,
        Outcome::OutOfRoad,
        Outcome::Timeout,
    ];

    pub fn label(self) -> &'static str {
        match self {
            Outcome::Success => "success",
            Outcome::Crash => "crash",
            Outcome::OutOfRoad => "out_of_road",
            Outcome::Timeout => "timeout",
        }
    }

    pub fn from_code(code: u32) -> Option<Outcome> {
        Outcome::ALL.into_iter().find(|o| *o as u32 == code)
    }
}

/// Where on its route an agent's episode ended: what `actor eval` counts to say where agents
/// fail, beside how.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum RouteStage {
    /// On the lane it entered on: the approach.
    Entry,
    /// On a lane inside the junction or on the ring.
    Junction,
    /// On its exit lane.
    Exit,
}

impl RouteStage {
    pub fn label(self) -> &'static str {
        match self {
            RouteStage::Entry => "entry",
            RouteStage::Junction => "junction",
            RouteStage::Exit => "exit",
        }
    }
}

/// What a crashed car ran into, judged from the two bodies at the contact. Rear-end and
/// sideswipe contacts are the car-following and lane-keeping failures; crossing and head-on
/// ones the failures to give way.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum CrashKind {
    /// A car going the same way (headings within 30°) whose centre lies within a car width of
    /// the line through this one: ahead of it or behind it in the lane.
    RearEnd,
    /// A car going the same way beside it.
    Sideswipe,
    /// A car crossing its path (headings 30° to 150° apart).
    Crossing,
    /// A car coming the other way (headings more than 150° apart).
    HeadOn,
    /// A wreck left on the road.
    Wreck,
}

impl CrashKind {
    pub fn label(self) -> &'static str {
        match self {
            CrashKind::RearEnd => "rear_end",
            CrashKind::Sideswipe => "sideswipe",
            CrashKind::Crossing => "crossing",
            CrashKind::HeadOn => "head_on",
            CrashKind::Wreck => "wreck",
        }
    }
}

/// How and where one agent episode ended, as `actor eval` counts it:
/// `outcome/stage`, and for crashes `crash/stage/kind`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Ending {
    pub outcome: Outcome,
    pub stage: RouteStage,
    /// What the car hit, for a crash.
    pub crash: Option<CrashKind>,
}

impl Ending {
    pub fn key(&self) -> String {
        let mut key = format!("{}/{}", self.outcome.label(), self.stage.label());
        if let Some(kind) = self.crash {
            key.push('/');
            key.push_str(kind.label());
        }
        key
    }
}

/// Statistics of one finished agent episode.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EpisodeStats {
    pub outcome: Outcome,
    /// Decision steps the agent lived.
    pub length: u32,
    pub total_reward: f32,
    /// Mean and max of |longitudinal acceleration| over the episode, m/s².
    pub mean_abs_accel: f32,
    pub max_abs_accel: f32,
    pub collisions: u32,
    pub energy_kj: f32,
    /// Sum of the episode's per-step costs (what a cost limit constrains).
    pub total_cost: f32,
}

/// One scene episode (MetaDrive's environment episode), by the outcomes of the agent episodes
/// that ended in it: the unit of MetaDrive's success rate.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SceneEpisodeStats {
    /// Scene steps from the reset to the end.
    pub steps: u32,
    pub successes: u32,
    pub crashes: u32,
    pub out_of_road: u32,
    pub timeouts: u32,
}

impl SceneEpisodeStats {
    pub fn record(&mut self, outcome: Outcome) {
        let count = match outcome {
            Outcome::Success => &mut self.successes,
            Outcome::Crash => &mut self.crashes,
            Outcome::OutOfRoad => &mut self.out_of_road,
            Outcome::Timeout => &mut self.timeouts,
        };
        *count = count.saturating_add(1);
    }

    /// Agent episodes that ended in the scene episode.
    pub fn agents(&self) -> u64 {
        [
            self.successes,
            self.crashes,
            self.out_of_road,
            self.timeouts,
        ]
        .iter()
        .map(|&c| u64::from(c))
        .sum()
    }

    /// The share of those agent episodes that ended with `outcome` (0 without any).
    pub fn share(&self, outcome: Outcome) -> f64 {
        let count = match outcome {
            Outcome::Success => self.successes,
            Outcome::Crash => self.crashes,
            Outcome::OutOfRoad => self.out_of_road,
            Outcome::Timeout => self.timeouts,
        };
        match self.agents() {
            0 => 0.0,
            n => f64::from(count) / n as f64,
        }
    }
}
