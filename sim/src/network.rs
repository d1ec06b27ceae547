//! Road networks: lanes, the routes through them, where cars spawn, and where the road is.
//! Every scene type (the intersection or T-junction, the roundabout) implements
//! [`RoadNetwork`]; the scene itself only talks to this trait.

use parry2d::math::Vec2;

use super::lane::Lane;

pub type LaneId = usize;

/// A path from an entry lane to an exit lane, as consecutive lanes.
#[derive(Debug, Clone, PartialEq)]
pub struct Route {
    pub lanes: Vec<LaneId>,
    /// Route distance at the start of each lane.
    pub offsets: Vec<f32>,
    pub length: f32,
}

impl Route {
    pub fn new(lanes: Vec<LaneId>, all: &[Lane]) -> Route {
        let mut offsets = Vec::with_capacity(lanes.len());
        let mut length = 0.0;
        for &lane in &lanes {
            offsets.push(length);
            length += all[lane].length();
        }
        Route {
            lanes,
            offsets,
            length,
        }
    }
}

/// A spawn lane and the routes a car spawned on it may take.
#[derive(Debug, Clone, PartialEq)]
pub struct Entry {
    pub lane: LaneId,
    /// Indices into [`RoadNetwork::routes`].
    pub routes: Vec<usize>,
}

pub trait RoadNetwork: Send + Sync {
    fn lanes(&self) -> &[Lane];
    fn routes(&self) -> &[Route];
    /// Lanes cars spawn on, each with at least one route.
    fn entries(&self) -> &[Entry];
    /// Is `point` on the drivable road for a car heading `heading`? False off the road
    /// surface (kerbs included) and on the wrong side of a solid centre line.
    fn on_road(&self, point: Vec2, heading: f32) -> bool;
}
