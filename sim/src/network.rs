//! Road networks: lanes, the routes through them, where cars spawn, and where the road is;
//! and what drivers (the autopilot, human drivers) read off a route: its centre line and the
//! speed its bends allow. Every scene type (the intersection or T-junction, the roundabout)
//! implements [`RoadNetwork`]; the scene itself only talks to this trait.

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

/// Bends are taken at the speed that keeps lateral acceleration at this (m/s²).
const COMFORT_LATERAL_ACCEL: f32 = 3.0;

/// The centre-line point `progress` metres along `route` (extrapolated past its end).
pub fn route_point(network: &dyn RoadNetwork, route: &Route, progress: f32) -> Vec2 {
    let i = route
        .offsets
        .iter()
        .rposition(|&o| o <= progress)
        .unwrap_or(0);
    network.lanes()[route.lanes[i]].point(progress - route.offsets[i])
}

/// The smallest bend radius (m) of this lane and the next; infinite on straight road.
pub fn tightest_bend(network: &dyn RoadNetwork, route: &Route, lane_index: usize) -> f32 {
    route.lanes[lane_index..route.lanes.len().min(lane_index + 2)]
        .iter()
        .map(|&l| network.lanes()[l].bend().0.abs())
        .filter(|&r| r > 0.0)
        .fold(f32::INFINITY, f32::min)
}

/// The speed (m/s) at which the bends of this lane and the next keep lateral acceleration
/// comfortable; infinite on straight road.
pub fn bend_speed(network: &dyn RoadNetwork, route: &Route, lane_index: usize) -> f32 {
    (COMFORT_LATERAL_ACCEL * tightest_bend(network, route, lane_index)).sqrt()
}
