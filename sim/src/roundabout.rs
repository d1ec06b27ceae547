//! The roundabout (right-hand traffic, counter-clockwise ring), MetaDrive's default geometry.
//!
//! Centre at the origin; arm `a` of `A` points along `d_a` at angle `2π·a/A` (arm 0 east), with
//! `n_a` = `d_a` turned left. Arm lane `k` (0 next to the centre line) of `n` lanes of width `w`
//! lies `o_k = (k + ½)·w` from the arm's centre line: inbound on the `+n_a` side, outbound on
//! the `−n_a` side. The ring is an annulus from the island radius `R` to `R_out = R + r·w`;
//! arm lane `k` drives on ring lane `j = k + r − n` (0 innermost, radius `R + (j + ½)·w`), so
//! the arm's lanes use the ring's outer lanes and lane changes are never needed.
//!
//! Entry and exit connectors are right-turning arcs tangent to both the arm lane and the ring
//! lane. Those of one arm and side share a centre, so they are parallel like lanes of one road
//! and their band of road (an annular sector) meets the arm's edges and the ring's outer edge
//! tangentially. The entry centre lies `e_in` off the arm's centre line, with `e_in` chosen so
//! that the arcs turn through `entry_angle`; the exit centre lies `e_out = exit_radius + o_{n−1}`
//! off it, so the outermost lane's exit arc has radius `exit_radius`.
//!
//! Lane graph per arm lane: approach → entry arc → ring arcs (a "between" arc from this arm's
//! entry to the next arm's exit, then a "pass" arc across that arm's mouth, and so on) → exit
//! arc → exit road. Every exit is a destination, the entry arm's own included (a full circle,
//! as MetaDrive allows).

use std::f32::consts::{FRAC_PI_2, PI, TAU};

use parry2d::math::Vec2;

use junction_core::config::RoundaboutConfig;

use super::SimError;
use super::angle::wrap;
use super::lane::Lane;
use super::network::{Entry, LaneId, RoadNetwork, Route};

/// Connector arcs tighter than this (centre line) are refused: the car turns no tighter than
/// about 2.9 m and needs margin to stay in its lane.
const MIN_CONNECTOR_RADIUS: f32 = 5.0;
/// The straight roads reach this far (metres) into their connector bands and past their
/// ends, so rounding where pieces meet leaves no gap in the drivable area.
const SEAM: f32 = 1e-3;

pub struct Roundabout {
    lanes: Vec<Lane>,
    routes: Vec<Route>,
    entries: Vec<Entry>,
    island: f32,
    ring_outer: f32,
    arms: Vec<Arm>,
}

/// The drivable pieces of one arm besides the ring.
struct Arm {
    direction: Vec2,
    half_width: f32,
    /// Distances from the centre along `direction` where the inbound / outbound straight road
    /// meets its connector band, and where the arm ends.
    entry_start: f32,
    exit_start: f32,
    end: f32,
    entry: Band,
    exit: Band,
}

/// An annular sector: the road swept by a family of concentric connector arcs.
struct Band {
    centre: Vec2,
    inner: f32,
    outer: f32,
    start_angle: f32,
    /// Signed like a lane arc's sweep (< 0 clockwise).
    sweep: f32,
}

impl Band {
    fn contains(&self, p: Vec2) -> bool {
        let rel = p - self.centre;
        let distance = rel.length();
        if distance < self.inner || distance > self.outer {
            return false;
        }
        let from_middle = wrap(rel.to_angle() - self.start_angle - self.sweep / 2.0);
        from_middle.abs() <= self.sweep.abs() / 2.0
    }
}

/// Where the connectors of one arm side meet the arm and the ring: the shared arc centre's
/// offset `e` from the arm's centre line, its distance `x` along the arm, and its polar angle
/// `beta` relative to the arm (the ring tangent points lie on that ray).
struct Connector {
    e: f32,
    x: f32,
    beta: f32,
}

impl Connector {
    /// Arcs about a centre `e` off the arm's centre line, tangent to a ring of radius
    /// `ring_inner` + lane offset: the centre lies `ring_inner + e` from the origin.
    fn new(e: f32, ring_inner: f32) -> Connector {
        let distance = ring_inner + e;
        let x = (distance * distance - e * e).sqrt();
        Connector {
            e,
            x,
            beta: e.atan2(x),
        }
    }
}

impl Roundabout {
    pub fn new(config: &RoundaboutConfig) -> Result<Roundabout, SimError> {
        let (n, r, w) = (
            config.lanes_per_direction,
            config.ring_lanes,
            config.lane_width,
        );
        let arm_count = config.arms;
        // False for NaN too.
        let positive = |x: f32| x > 0.0;
        if n == 0 || r < n || arm_count < 3 || !positive(w) || !positive(config.radius) {
            return Err(SimError::Geometry(
                "a roundabout needs 3 or more arms, lanes_per_direction > 0, ring_lanes >= \
                 lanes_per_direction, and a positive lane_width and radius"
                    .into(),
            ));
        }
        if !positive(config.approach_length) {
            return Err(SimError::Geometry(
                "roundabout approach_length must be positive".into(),
            ));
        }
        let offset = |k: usize| (k as f32 + 0.5) * w;
        let half_width = n as f32 * w;
        let island = config.radius;
        let ring_outer = island + r as f32 * w;
        // Inner edge of the ring lanes the arms use.
        let ring_inner = island + (r - n) as f32 * w;

        // Entry: the arcs turn through `entry_angle`, so the ring tangent points lie at
        // β = 90° − entry_angle, and sin β = e / (ring_inner + e).
        let entry_angle = config.entry_angle.to_radians();
        if !(entry_angle > 0.0 && entry_angle < FRAC_PI_2) {
            return Err(SimError::Geometry(format!(
                "roundabout entry_angle must lie strictly between 0 and 90°, not {}",
                config.entry_angle
            )));
        }
        let sin_beta = entry_angle.cos();
        let entry = Connector::new(sin_beta * ring_inner / (1.0 - sin_beta), ring_inner);
        let exit = Connector::new(config.exit_radius + offset(n - 1), ring_inner);
        let tightest_entry = entry.e - offset(n - 1);
        if tightest_entry < MIN_CONNECTOR_RADIUS {
            return Err(SimError::Geometry(format!(
                "roundabout entry arcs of {tightest_entry:.1} m (outer lane) are tighter than \
                 {MIN_CONNECTOR_RADIUS} m: use a smaller entry_angle or a larger radius"
            )));
        }
        if config.exit_radius < MIN_CONNECTOR_RADIUS {
            return Err(SimError::Geometry(format!(
                "roundabout exit_radius must be at least {MIN_CONNECTOR_RADIUS} m"
            )));
        }
        let spacing = TAU / arm_count as f32;
        let between_sweep = spacing - entry.beta - exit.beta;
        if !positive(between_sweep) {
            return Err(SimError::Geometry(format!(
                "the entry and exit arcs of {arm_count} arms overlap on a ring of radius {}: \
                 use fewer arms, a larger radius, a larger entry_angle or a smaller exit_radius",
                config.radius
            )));
        }
        let arm_end = entry.x.max(exit.x) + config.approach_length;

        let mut lanes = Vec::new();
        let mut push = |lane: Lane| {
            lanes.push(lane);
            lanes.len() - 1
        };
        // Per arm, per arm lane k: approach, entry arc, ring "pass" arc (across this arm's
        // mouth), ring "between" arc (to the next arm), exit arc, exit road.
        let mut incoming = vec![vec![0; n]; arm_count];
        let mut entry_arc = vec![vec![0; n]; arm_count];
        let mut pass = vec![vec![0; n]; arm_count];
        let mut between = vec![vec![0; n]; arm_count];
        let mut exit_arc = vec![vec![0; n]; arm_count];
        let mut outgoing = vec![vec![0; n]; arm_count];
        let mut arms = Vec::with_capacity(arm_count);
        for a in 0..arm_count {
            let theta = a as f32 * spacing;
            let d = Vec2::from_angle(theta);
            let side = d.perp();
            let entry_centre = d * entry.x + side * entry.e;
            let exit_centre = d * exit.x - side * exit.e;
            for k in 0..n {
                let (left, right) = (offset(k), half_width - offset(k));
                let ring_radius = ring_inner + offset(k);
                let ring_left = ring_radius - island;
                let ring_right = ring_outer - ring_radius;
                incoming[a][k] = push(Lane::straight(
                    d * arm_end + side * offset(k),
                    d * entry.x + side * offset(k),
                    w,
                    left,
                    right,
                ));
                entry_arc[a][k] = push(Lane::arc(
                    entry_centre,
                    entry.e - offset(k),
                    theta - FRAC_PI_2,
                    -(FRAC_PI_2 - entry.beta),
                    w,
                    left,
                    right,
                ));
                pass[a][k] = push(Lane::arc(
                    Vec2::ZERO,
                    ring_radius,
                    theta - exit.beta,
                    exit.beta + entry.beta,
                    w,
                    ring_left,
                    ring_right,
                ));
                between[a][k] = push(Lane::arc(
                    Vec2::ZERO,
                    ring_radius,
                    theta + entry.beta,
                    between_sweep,
                    w,
                    ring_left,
                    ring_right,
                ));
                exit_arc[a][k] = push(Lane::arc(
                    exit_centre,
                    exit.e - offset(k),
                    theta - exit.beta + PI,
                    -(FRAC_PI_2 - exit.beta),
                    w,
                    left,
                    right,
                ));
                outgoing[a][k] = push(Lane::straight(
                    d * exit.x - side * offset(k),
                    d * arm_end - side * offset(k),
                    w,
                    left,
                    right,
                ));
            }
            arms.push(Arm {
                direction: d,
                half_width,
                entry_start: entry.x,
                exit_start: exit.x,
                end: arm_end,
                entry: Band {
                    centre: entry_centre,
                    inner: entry.e - half_width,
                    outer: entry.e,
                    start_angle: theta - FRAC_PI_2,
                    sweep: -(FRAC_PI_2 - entry.beta),
                },
                exit: Band {
                    centre: exit_centre,
                    inner: exit.e - half_width,
                    outer: exit.e,
                    start_angle: theta - exit.beta + PI,
                    sweep: -(FRAC_PI_2 - exit.beta),
                },
            });
        }

        let mut routes = Vec::new();
        let mut entries = Vec::new();
        for a in 0..arm_count {
            for k in 0..n {
                let mut entry_routes = Vec::new();
                // Leave at the m-th exit counter-clockwise; m = arm_count is the entry arm.
                for m in 1..=arm_count {
                    let to = (a + m) % arm_count;
                    let mut path: Vec<LaneId> = vec![incoming[a][k], entry_arc[a][k]];
                    for i in 0..m {
                        path.push(between[(a + i) % arm_count][k]);
                        if i + 1 < m {
                            path.push(pass[(a + i + 1) % arm_count][k]);
                        }
                    }
                    path.push(exit_arc[to][k]);
                    path.push(outgoing[to][k]);
                    entry_routes.push(routes.len());
                    routes.push(Route::new(path, &lanes));
                }
                entries.push(Entry {
                    lane: incoming[a][k],
                    routes: entry_routes,
                });
            }
        }
        Ok(Roundabout {
            lanes,
            routes,
            entries,
            island,
            ring_outer,
            arms,
        })
    }
}

impl RoadNetwork for Roundabout {
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
        let distance = p.length();
        if distance >= self.island && distance <= self.ring_outer {
            return true;
        }
        let forward = Vec2::from_angle(heading);
        for arm in &self.arms {
            if arm.entry.contains(p) || arm.exit.contains(p) {
                return true;
            }
            let along = p.dot(arm.direction);
            let side = p.dot(arm.direction.perp());
            // The inbound road (+n side) and the outbound road (−n side) start where their
            // connector bands end; between them near the ring is the splitter island.
            let start = if side >= 0.0 {
                arm.entry_start
            } else {
                arm.exit_start
            };
            if side.abs() <= arm.half_width && along >= start - SEAM && along <= arm.end + SEAM {
                // The solid centre line: inbound traffic keeps to the +n side.
                let inbound = forward.dot(-arm.direction) > 0.0;
                return if inbound { side >= 0.0 } else { side <= 0.0 };
            }
        }
        false
    }
}
