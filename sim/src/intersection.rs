//! The 4-way signal-free intersection (right-hand traffic), MetaDrive's default geometry.
//!
//! Centre at the origin; arm `a` (0 east, 1 north, 2 west, 3 south) points along
//! `d_a = (cos 90°a, sin 90°a)` with `n_a` = `d_a` turned left. Lane `k` (0 next to the centre
//! line) of `n` lanes of width `w` lies `o_k = (k + ½)·w` from the arm's centre line: incoming
//! lanes on the `+n_a` side, outgoing on the `−n_a` side. The junction box has half-size
//! `H = n·w + corner_radius`; its corners are kerbs of radius `corner_radius`. Connectors
//! inside the box: straight from every lane to the same lane opposite, left turns (quarter
//! arcs) from lane 0 to lane 0, right turns from lane n−1 to lane n−1, U-turns (half circles)
//! from lane 0 to the outgoing lane n−1 of the same arm.
//!
//! With `arms = 3` it is a T-junction: the south arm (3) is left out, with every manoeuvre
//! from or to it, and the box's south side is a straight kerb continuing the main road's edge.
//! No U-turns: from lane 0 back into the outgoing lane 0 is a half circle of radius w/2
//! (1.75 m), well under the car's 2.9 m minimum turning radius.

use std::f32::consts::{FRAC_PI_2, PI};

use parry2d::math::Vec2;

use junction_core::config::{IntersectionConfig, Manoeuvre};

use super::SimError;
use super::lane::Lane;
use super::network::{Entry, LaneId, RoadNetwork, Route};

/// The car turns no tighter than wheelbase / tan(40°) ≈ 2.9 m: U-turn arcs tighter than this
/// are left out (1 lane per direction: 1.75 m; 2 lanes: 3.5 m, which the autopilot drives).
const MIN_UTURN_RADIUS: f32 = 3.0;

pub struct Intersection {
    lanes: Vec<Lane>,
    routes: Vec<Route>,
    entries: Vec<Entry>,
    road_half_width: f32,
    box_half: f32,
    corner_radius: f32,
    arm_end: f32,
    /// A T-junction: no south arm.
    tee: bool,
}

fn arm_direction(arm: usize) -> Vec2 {
    Vec2::from_angle(arm as f32 * FRAC_PI_2)
}

impl Intersection {
    // `!(w > 0.0)` rather than `w <= 0.0`: the negation also rejects NaN.
    #[allow(clippy::neg_cmp_op_on_partial_ord)]
    pub fn new(config: &IntersectionConfig) -> Result<Intersection, SimError> {
        let n = config.lanes_per_direction;
        let w = config.lane_width;
        if n == 0 || !(w > 0.0) || !(config.corner_radius >= 0.0) || !(config.approach_length > 0.0)
        {
            return Err(SimError::Geometry(
                "lanes_per_direction, lane_width and approach_length must be positive".into(),
            ));
        }
        let road_half_width = n as f32 * w;
        let h = road_half_width + config.corner_radius;
        let l = config.approach_length;
        let offset = |k: usize| (k as f32 + 0.5) * w;
        let mut lanes = Vec::new();
        let mut incoming = [[0usize; 3]; 4];
        let mut outgoing = [[0usize; 3]; 4];
        let arms = config.arms;
        if !(3..=4).contains(&arms) {
            return Err(SimError::Geometry(format!(
                "an intersection has 3 or 4 arms, not {arms}"
            )));
        }
        for arm in 0..arms {
            let (d, side) = (arm_direction(arm), arm_direction(arm).perp());
            for k in 0..n {
                let (left, right) = (offset(k), road_half_width - offset(k));
                incoming[arm][k] = lanes.len();
                lanes.push(Lane::straight(
                    d * (h + l) + side * offset(k),
                    d * h + side * offset(k),
                    w,
                    left,
                    right,
                ));
                outgoing[arm][k] = lanes.len();
                lanes.push(Lane::straight(
                    d * h - side * offset(k),
                    d * (h + l) - side * offset(k),
                    w,
                    left,
                    right,
                ));
            }
        }
        let uturn_radius = (offset(0) + offset(n - 1)) / 2.0;
        let mut routes = Vec::new();
        let mut entries: Vec<Entry> = Vec::new();
        for (arm, arm_incoming) in incoming.iter().enumerate().take(arms) {
            for (k, &from) in arm_incoming.iter().enumerate().take(n) {
                let mut entry_routes = Vec::new();
                for &manoeuvre in &config.routes {
                    let (to_arm, lane_k) = match manoeuvre {
                        Manoeuvre::Straight => ((arm + 2) % 4, k),
                        Manoeuvre::Left if k == 0 => ((arm + 3) % 4, 0),
                        Manoeuvre::Right if k == n - 1 => ((arm + 1) % 4, n - 1),
                        Manoeuvre::UTurn if k == 0 && uturn_radius >= MIN_UTURN_RADIUS => {
                            (arm, n - 1)
                        }
                        Manoeuvre::Left | Manoeuvre::Right | Manoeuvre::UTurn => continue,
                    };
                    if to_arm >= arms {
                        continue;
                    }
                    let to: LaneId = outgoing[to_arm][lane_k];
                    let (p, q) = (lanes[from].end(), lanes[to].start());
                    let (left, right) = (lanes[from].left_edge, lanes[from].right_edge);
                    let connector = match manoeuvre {
                        Manoeuvre::Straight => Lane::straight(p, q, w, left, right),
                        Manoeuvre::UTurn => {
                            // Half circle turning left, bulging into the junction box.
                            let centre = (p + q) / 2.0;
                            let start = (p - centre).to_angle();
                            Lane::arc(centre, uturn_radius, start, PI, w, left, right)
                        }
                        Manoeuvre::Left | Manoeuvre::Right => {
                            // Quarter arc about the box corner between the two arms.
                            let centre = (arm_direction(arm) + arm_direction(to_arm)) * h;
                            let sweep = if manoeuvre == Manoeuvre::Left {
                                FRAC_PI_2
                            } else {
                                -FRAC_PI_2
                            };
                            let radius = (p - centre).length();
                            Lane::arc(
                                centre,
                                radius,
                                (p - centre).to_angle(),
                                sweep,
                                w,
                                left,
                                right,
                            )
                        }
                    };
                    let connector_id = lanes.len();
                    lanes.push(connector);
                    entry_routes.push(routes.len());
                    routes.push(Route::new(vec![from, connector_id, to], &lanes));
                }
                if !entry_routes.is_empty() {
                    entries.push(Entry {
                        lane: from,
                        routes: entry_routes,
                    });
                }
            }
        }
        if entries.is_empty() {
            return Err(SimError::Geometry(
                "no lane admits any of the configured routes".into(),
            ));
        }
        Ok(Intersection {
            lanes,
            routes,
            entries,
            road_half_width,
            box_half: h,
            corner_radius: config.corner_radius,
            arm_end: h + l,
            tee: arms == 3,
        })
    }
}

impl RoadNetwork for Intersection {
    fn lanes(&self) -> &[Lane] {
        &self.lanes
    }

    fn routes(&self) -> &[Route] {
        &self.routes
    }

    fn entries(&self) -> &[Entry] {
        &self.entries
    }

    fn on_road(&self, p: Vec2, heading: f32) -> bool {
        let (h, rc) = (self.box_half, self.corner_radius);
        let (ax, ay) = (p.x.abs(), p.y.abs());
        if self.tee && p.y < -self.road_half_width {
            // South of the main road: the T's straight kerb, no arm.
            return false;
        }
        if ax <= h && ay <= h {
            // Inside the junction box: everything but the rounded kerbs at its corners.
            let in_corner_zone = ax > h - rc && ay > h - rc;
            return !in_corner_zone || (Vec2::new(ax, ay) - Vec2::new(h, h)).length() >= rc;
        }
        let arm = if ax > h && ay <= self.road_half_width && ax <= self.arm_end {
            if p.x > 0.0 { 0 } else { 2 }
        } else if ay > h && ax <= self.road_half_width && ay <= self.arm_end {
            if p.y > 0.0 { 1 } else { 3 }
        } else {
            return false;
        };
        // The solid centre line: inbound traffic keeps to the +n side, outbound to the −n side.
        let d = arm_direction(arm);
        let side = p.dot(d.perp());
        let inbound = Vec2::from_angle(heading).dot(-d) > 0.0;
        if inbound { side >= 0.0 } else { side <= 0.0 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use junction_core::config::ScenarioConfig;

    fn default_intersection() -> Intersection {
        Intersection::new(&ScenarioConfig::default().intersection).unwrap()
    }

    #[test]
    fn routes_connect_entry_to_exit_without_gaps() {
        let net = default_intersection();
        // 4 arms × (2 straight + 1 left + 1 right).
        assert_eq!(net.routes().len(), 16);
        assert_eq!(net.entries().len(), 8);
        for route in net.routes() {
            for pair in route.lanes.windows(2) {
                let gap = (net.lanes()[pair[0]].end() - net.lanes()[pair[1]].start()).length();
                assert!(gap < 1e-3, "gap of {gap} m in {route:?}");
                let turn = super::super::angle::wrap(
                    net.lanes()[pair[0]].heading(net.lanes()[pair[0]].length())
                        - net.lanes()[pair[1]].heading(0.0),
                );
                assert!(turn.abs() < 1e-4, "kink of {turn} rad in {route:?}");
            }
        }
    }

    #[test]
    fn drivable_area_has_kerbs_and_a_solid_centre_line() {
        let net = default_intersection();
        let west = std::f32::consts::PI; // inbound on the east arm
        assert!(net.on_road(Vec2::new(40.0, 2.0), west), "inbound lane");
        assert!(
            !net.on_road(Vec2::new(40.0, -2.0), west),
            "inbound car across the centre line"
        );
        assert!(net.on_road(Vec2::new(40.0, -2.0), 0.0), "outbound lane");
        assert!(
            !net.on_road(Vec2::new(40.0, 7.5), west),
            "beyond the road edge"
        );
        assert!(
            !net.on_road(Vec2::new(90.0, 2.0), west),
            "beyond the end of the arm"
        );
        assert!(net.on_road(Vec2::new(0.0, 0.0), 1.0), "junction centre");
        // The box corner (17, 17) lies on the kerb; (7.5, 7.5) is still drivable.
        assert!(!net.on_road(Vec2::new(16.0, 16.0), 0.0));
        assert!(net.on_road(Vec2::new(7.5, 7.5), 0.0));
    }
}
