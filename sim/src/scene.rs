//! A traffic scene: agents in slots driving routes through a road network, an endless flow
//! (every car that leaves is replaced when a spawn point is free), observations, Reward I,
//! costs, neighbourhoods and per-episode statistics. Pure: state changes only in `step`.

use parry2d::math::{Pose, Vec2};
use parry2d::query::intersection_test;
use parry2d::shape::Cuboid;
use rand::seq::index::sample;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use junction_core::config::{AfterHorizon, ScenarioConfig, SceneKind, Simulator};
use junction_core::episode::{
    CrashKind, Ending, EpisodeStats, Outcome, RouteStage, SceneEpisodeStats,
};
use junction_core::lcf_inputs;
use junction_core::spec::{ACTION_DIM, LIDAR_OFFSET};

use super::SimError;
use super::angle;
use super::car::Car;
use super::grid::Grid;
use super::human::{self, Seen};
use super::intersection::Intersection;
use super::lidar;
use super::network::{Entry, RoadNetwork};
use super::observation::{self, RoutePosition};
use super::reward::{self, StepFacts};
use super::roundabout::Roundabout;
use super::vehicle::{BOUNDING_RADIUS, Dynamics, Kinematics, LENGTH, WIDTH};

/// A destination counts as reached within this distance of its lane's end (MetaDrive: 5 m).
const ARRIVAL_TOLERANCE: f32 = 5.0;
/// Grid cell size: a few car lengths, so collision queries touch a handful of cells.
const GRID_CELL: f32 = 10.0;

/// A crashed car left on the road for a while.
#[derive(Debug, Clone)]
struct Obstacle {
    kin: Kinematics,
    steps_left: u32,
    /// The slot the car drove in (kept empty while the wreck stands, with
    /// `scenario.wreck_holds_slot`).
    slot: usize,
}

/// An episode that ended in `step`, in slot `slot`.
#[derive(Debug, Clone, PartialEq)]
pub struct FinishedEpisode {
    pub slot: usize,
    pub stats: EpisodeStats,
    /// The car's body when the episode ended: the car itself is gone by then (a renderer
    /// marks where it arrived, crashed or left the road).
    pub vehicle: VehicleView,
    /// Where on its route it ended and, for a crash, what it hit.
    pub ending: Ending,
    /// What the car observed where it ended (`obs_dim` values): the slot's row of
    /// [`Scene::observations`] already belongs to its successor or is empty, and a learner that
    /// bootstraps a cut-off episode (or a Gym environment's final observation) needs this one.
    pub observation: Vec<f32>,
}

/// What one `step` produced, per slot (0 / false for slots that did not act).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StepResult {
    pub rewards: Vec<f32>,
    pub costs: Vec<f32>,
    pub dones: Vec<bool>,
    pub finished: Vec<FinishedEpisode>,
    /// Contact events this step (vehicle–vehicle or vehicle–obstacle pairs).
    pub collisions: u32,
    /// Episodes of human-driven vehicles that ended this step (reward 0: they do not learn).
    pub human_finished: Vec<EpisodeStats>,
    /// The scene episode that ended with this step (the scene has started afresh), if one did.
    pub scene_episode: Option<SceneEpisodeStats>,
}

/// What a vehicle touched first in a step: another vehicle (its pose) or a wreck.
#[derive(Debug, Clone, Copy)]
enum Contact {
    Vehicle { position: Vec2, heading: f32 },
    Wreck,
}

impl Contact {
    /// The kind of crash this contact is for a car in `kin`.
    fn kind(self, kin: &Kinematics) -> CrashKind {
        let Contact::Vehicle { position, heading } = self else {
            return CrashKind::Wreck;
        };
        let apart = angle::wrap(heading - kin.heading).abs().to_degrees();
        if apart > 150.0 {
            CrashKind::HeadOn
        } else if apart > 30.0 {
            CrashKind::Crossing
        } else if Vec2::from_angle(kin.heading)
            .perp_dot(position - kin.position)
            .abs()
            < WIDTH
        {
            CrashKind::RearEnd
        } else {
            CrashKind::Sideswipe
        }
    }
}

/// A body, for rendering and tests.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VehicleView {
    pub position: Vec2,
    pub heading: f32,
    pub speed: f32,
    pub length: f32,
    pub width: f32,
    /// The agent slot, or None for a crashed car left as an obstacle or a human driver.
    pub slot: Option<usize>,
    pub human: bool,
}

impl VehicleView {
    fn of(kin: &Kinematics, slot: Option<usize>, human: bool) -> VehicleView {
        VehicleView {
            position: kin.position,
            heading: kin.heading,
            speed: kin.speed,
            length: LENGTH,
            width: WIDTH,
            slot,
            human,
        }
    }
}

pub struct Scene {
    config: ScenarioConfig,
    network: Box<dyn RoadNetwork>,
    rng: ChaCha8Rng,
    /// Learning agents in slots `0..agents`, human drivers after them.
    cars: Vec<Option<Car>>,
    agents: usize,
    obstacles: Vec<Obstacle>,
    steps: u32,
    /// Outcomes of the agent episodes of the current scene episode so far.
    episode: SceneEpisodeStats,
    /// Every spawn point: (entry index, distance along the entry lane).
    spawn_points: Vec<(usize, f32)>,
    observations: Vec<f32>,
    alive: Vec<bool>,
    neighbour_offsets: Vec<u32>,
    neighbour_ids: Vec<u32>,
    lcf_features: Vec<f32>,
    result: StepResult,
    // Scratch space reused every step.
    grid: Grid,
    bodies: Vec<(Vec2, f32, Option<usize>)>,
    /// Each vehicle's first contact this step (`Some` exactly where it crashed).
    contacts: Vec<Option<Contact>>,
    lidar: Vec<f32>,
    progress_gain: Vec<f32>,
    accel: Vec<f32>,
    steer_change: Vec<f32>,
    energy_kj: Vec<f32>,
    human_actions: Vec<[f32; 2]>,
    near: Vec<usize>,
    nearby_agents: Vec<u32>,
}

impl Scene {
    pub fn new(config: &ScenarioConfig, seed: u64) -> Result<Scene, SimError> {
        config
            .validate()
            .map_err(|e| SimError::Config(e.to_string()))?;
        if config.simulator != Simulator::Junction {
            return Err(SimError::Config(format!(
                "scenario {:?} runs on MetaDrive (scenario.simulator = \"metadrive\"): its \
                 actor is `python -m junction.metadrive_actor` (docs/PYTHON.md)",
                config.name
            )));
        }
        let network: Box<dyn RoadNetwork> = match config.kind {
            SceneKind::Intersection => Box::new(Intersection::new(&config.intersection)?),
            SceneKind::Roundabout => Box::new(Roundabout::new(&config.roundabout)?),
        };
        let spacing = config.spawn.slot_spacing;
        let mut spawn_points = Vec::new();
        for (e, entry) in network.entries().iter().enumerate() {
            let length = network.lanes()[entry.lane].length();
            let mut k = 0;
            while spacing * (k as f32 + 1.0) <= length {
                spawn_points.push((e, spacing * (k as f32 + 0.5)));
                k += 1;
            }
        }
        let vehicles = config.agent_count() + config.human_count();
        if vehicles > spawn_points.len() {
            return Err(SimError::TooManyAgents {
                agents: config.agent_count(),
                humans: config.human_count(),
                spawn_points: spawn_points.len(),
            });
        }
        let extent = network
            .lanes()
            .iter()
            .flat_map(|l| [l.start(), l.end()])
            .fold(0.0f32, |m, p| m.max(p.x.abs()).max(p.y.abs()));
        let slots = config.agent_count();
        let mut scene = Scene {
            config: config.clone(),
            network,
            rng: ChaCha8Rng::seed_from_u64(seed),
            cars: vec![None; vehicles],
            agents: slots,
            obstacles: Vec::new(),
            steps: 0,
            episode: SceneEpisodeStats::default(),
            spawn_points,
            observations: vec![0.0; slots * config.obs_dim()],
            alive: vec![false; slots],
            neighbour_offsets: vec![0; slots + 1],
            neighbour_ids: Vec::new(),
            lcf_features: vec![0.0; slots * lcf_inputs::FEATURES],
            result: StepResult {
                rewards: vec![0.0; slots],
                costs: vec![0.0; slots],
                dones: vec![false; slots],
                ..StepResult::default()
            },
            grid: Grid::new(extent + GRID_CELL, GRID_CELL),
            bodies: Vec::new(),
            contacts: vec![None; vehicles],
            lidar: vec![0.0; config.sensors.lidar_beams],
            progress_gain: vec![0.0; vehicles],
            accel: vec![0.0; vehicles],
            steer_change: vec![0.0; vehicles],
            energy_kj: vec![0.0; vehicles],
            human_actions: vec![[0.0; 2]; vehicles - slots],
            near: Vec::new(),
            nearby_agents: Vec::new(),
        };
        scene.reset();
        Ok(scene)
    }

    pub fn config(&self) -> &ScenarioConfig {
        &self.config
    }

    /// Learning-agent slots (human drivers are not among them).
    pub fn slots(&self) -> usize {
        self.agents
    }

    pub fn obs_dim(&self) -> usize {
        self.config.obs_dim()
    }

    pub fn observations(&self) -> &[f32] {
        &self.observations
    }

    pub fn alive(&self) -> &[bool] {
        &self.alive
    }

    pub fn neighbours(&self) -> (&[u32], &[u32]) {
        (&self.neighbour_offsets, &self.neighbour_ids)
    }

    /// S_N of every slot (`lcf_inputs::FEATURES` each, zeros for empty slots), for the LCF methods.
    pub fn lcf_features(&self) -> &[f32] {
        &self.lcf_features
    }

    pub fn steps_since_reset(&self) -> u32 {
        self.steps
    }

    pub fn network(&self) -> &dyn RoadNetwork {
        self.network.as_ref()
    }

    pub(super) fn car(&self, slot: usize) -> Option<&Car> {
        self.cars.get(slot).and_then(Option::as_ref)
    }

    /// Every body on the road: agents first (by slot), human drivers, then crashed cars left
    /// as obstacles.
    pub fn vehicles(&self) -> impl Iterator<Item = VehicleView> + '_ {
        let agents = self.agents;
        let cars = self.cars.iter().enumerate().filter_map(move |(i, c)| {
            let human = i >= agents;
            c.as_ref()
                .map(|c| VehicleView::of(&c.kin, (!human).then_some(i), human))
        });
        cars.chain(
            self.obstacles
                .iter()
                .map(|o| VehicleView::of(&o.kin, None, false)),
        )
    }

    /// Advances one decision step; see [`StepResult`].
    pub fn step(&mut self, actions: &[f32]) -> &StepResult {
        let slots = self.slots();
        self.result.rewards.fill(0.0);
        self.result.costs.fill(0.0);
        self.result.dones.fill(false);
        self.result.finished.clear();
        self.result.human_finished.clear();
        self.result.scene_episode = None;
        self.result.collisions = 0;
        let dt = self.config.decision_dt;
        self.plan_human_drivers();

        // Move every vehicle and follow its route.
        let agents = self.agents;
        for (slot, car) in self.cars.iter_mut().enumerate() {
            let Some(car) = car else { continue };
            let action = if slot < agents {
                [
                    actions.get(slot * ACTION_DIM).copied().unwrap_or(0.0),
                    actions.get(slot * ACTION_DIM + 1).copied().unwrap_or(0.0),
                ]
            } else {
                self.human_actions[slot - agents]
            };
            let (speed_before, steer_before) = (car.kin.speed, car.kin.steer);
            self.energy_kj[slot] = car.kin.advance(action, dt, self.config.substeps);
            let before = car.progress;
            track_route(car, self.network.as_ref());
            self.progress_gain[slot] = car.progress - before;
            self.accel[slot] = (car.kin.speed - speed_before) / dt;
            self.steer_change[slot] = car.kin.steer - steer_before;
            car.age += 1;
        }
        self.obstacles.retain_mut(|o| {
            o.steps_left = o.steps_left.saturating_sub(1);
            o.steps_left > 0
        });

        self.detect_collisions();

        // Outcomes, rewards, costs.
        let horizon_cuts = self.config.after_horizon == AfterHorizon::Reset
            && self.steps + 1 >= self.config.horizon;
        for slot in 0..self.cars.len() {
            let Some(car) = self.cars[slot].as_mut() else {
                continue;
            };
            let route = &self.network.routes()[car.route];
            let on_final_lane = car.lane_index + 1 == route.lanes.len();
            let lane = &self.network.lanes()[route.lanes[car.lane_index]];
            let outcome = if self.contacts[slot].is_some() {
                Some(Outcome::Crash)
            } else if car
                .kin
                .corners()
                .iter()
                .any(|&c| !self.network.on_road(c, car.kin.heading))
            {
                Some(Outcome::OutOfRoad)
            } else if on_final_lane && car.s >= lane.length() - ARRIVAL_TOLERANCE {
                Some(Outcome::Success)
            } else if car.age >= self.config.agent_horizon || horizon_cuts {
                Some(Outcome::Timeout)
            } else {
                None
            };
            let facts = StepFacts {
                progress: self.progress_gain[slot],
                speed: car.kin.speed,
                lateral: car.lateral,
                lane_width: lane.width,
                heading_error: angle::wrap(car.kin.heading - lane.heading(car.s)),
                steer_change: self.steer_change[slot],
                collided: self.contacts[slot].is_some(),
                energy_kj: self.energy_kj[slot],
                outcome,
            };
            // Human drivers neither learn nor pay: no reward, no cost.
            let human = slot >= slots;
            let r = if human {
                0.0
            } else {
                self.result.costs[slot] = reward::cost(&self.config.cost, &facts);
                self.result.rewards[slot] = reward::reward(&self.config.reward, &facts);
                self.result.rewards[slot]
            };
            if self.contacts[slot].is_some() {
                car.collisions += 1;
            }
            car.energy_kj += facts.energy_kj;
            car.total_reward += r;
            car.total_cost += self.result.costs.get(slot).copied().unwrap_or(0.0);
            let accel = self.accel[slot].abs();
            car.abs_accel_sum += accel;
            car.max_abs_accel = car.max_abs_accel.max(accel);
            if let Some(outcome) = outcome {
                let stats = EpisodeStats {
                    outcome,
                    length: car.age,
                    total_reward: car.total_reward,
                    mean_abs_accel: car.abs_accel_sum / car.age.max(1) as f32,
                    max_abs_accel: car.max_abs_accel,
                    collisions: car.collisions,
                    energy_kj: car.energy_kj,
                    total_cost: car.total_cost,
                };
                if human {
                    self.result.human_finished.push(stats);
                } else {
                    self.episode.record(outcome);
                    self.result.dones[slot] = true;
                    let mut observation = vec![0.0; self.config.obs_dim()];
                    let view = Surroundings {
                        network: self.network.as_ref(),
                        bodies: &self.bodies,
                        grid: &self.grid,
                        lidar_range: self.config.sensors.lidar_range,
                    };
                    view.observe(slot, car, &mut observation, &mut self.near, &mut self.lidar);
                    let stage = if car.lane_index == 0 {
                        RouteStage::Entry
                    } else if on_final_lane {
                        RouteStage::Exit
                    } else {
                        RouteStage::Junction
                    };
                    self.result.finished.push(FinishedEpisode {
                        slot,
                        stats,
                        ending: Ending {
                            outcome,
                            stage,
                            crash: self.contacts[slot].map(|c| c.kind(&car.kin)),
                        },
                        vehicle: VehicleView::of(&car.kin, Some(slot), false),
                        observation,
                    });
                }
                if outcome == Outcome::Crash && self.config.crash_obstacle_steps > 0 {
                    self.obstacles.push(Obstacle {
                        kin: car.kin,
                        steps_left: self.config.crash_obstacle_steps,
                        slot,
                    });
                }
                self.cars[slot] = None;
            }
        }

        self.steps += 1;
        self.episode.steps = self.steps;
        let agents_left = self.cars[..agents].iter().any(Option::is_some);
        let episode_over = self.steps >= self.config.horizon
            && (self.config.after_horizon == AfterHorizon::Reset || !agents_left);
        if episode_over {
            self.result.scene_episode = Some(std::mem::take(&mut self.episode));
            self.reset();
        } else {
            if self.steps < self.config.horizon {
                self.respawn();
            }
            self.refresh();
        }
        &self.result
    }

    /// Clears the road and spawns `agents` cars on distinct spawn points.
    fn reset(&mut self) {
        self.steps = 0;
        self.episode = SceneEpisodeStats::default();
        self.obstacles.clear();
        self.cars.iter_mut().for_each(|c| *c = None);
        let chosen = sample(&mut self.rng, self.spawn_points.len(), self.cars.len());
        for (slot, point) in chosen.into_iter().enumerate() {
            let (entry, s) = self.spawn_points[point];
            self.cars[slot] = Some(self.spawn_car(entry, s));
        }
        self.refresh();
    }

    /// Fills empty slots with new cars at the first spawn point of lanes whose start is clear,
    /// each with the scenario's respawn probability.
    fn respawn(&mut self) {
        let spacing = self.config.spawn.slot_spacing;
        let probability = self.config.respawn_probability();
        for slot in 0..self.cars.len() {
            if self.cars[slot].is_some() || self.wreck_holds(slot) {
                continue;
            }
            // Drawn only for rates below 1, so the default keeps its random sequence.
            if probability < 1.0 && !self.rng.gen_bool(f64::from(probability)) {
                continue;
            }
            let free: Vec<usize> = (0..self.network.entries().len())
                .filter(|&e| self.spawn_point_clear(e, spacing / 2.0))
                .collect();
            if free.is_empty() {
                return;
            }
            let entry = free[self.rng.gen_range(0..free.len())];
            self.cars[slot] = Some(self.spawn_car(entry, spacing / 2.0));
        }
    }

    /// The wreck of the slot's last car still stands and keeps the slot empty.
    fn wreck_holds(&self, slot: usize) -> bool {
        self.config.wreck_holds_slot && self.obstacles.iter().any(|o| o.slot == slot)
    }

    fn spawn_point_clear(&self, entry: usize, s: f32) -> bool {
        let lane = &self.network.lanes()[self.network.entries()[entry].lane];
        let spawn = &self.config.spawn;
        let area = Cuboid::new(Vec2::new(
            spawn.respawn_clear_length / 2.0,
            spawn.respawn_clear_width / 2.0,
        ));
        let area_pose = Pose::new(lane.point(s), lane.heading(s));
        let reach = area.half_extents.length() + BOUNDING_RADIUS;
        let body = Cuboid::new(Vec2::new(LENGTH / 2.0, WIDTH / 2.0));
        self.vehicles().all(|v| {
            (v.position - lane.point(s)).length() > reach
                || !intersection_test(&area_pose, &area, &Pose::new(v.position, v.heading), &body)
                    .map(|i| i.intersecting)
                    .unwrap_or(true)
        })
    }

    fn spawn_car(&mut self, entry_index: usize, s: f32) -> Car {
        let Entry { lane, routes } = &self.network.entries()[entry_index];
        let route = routes[self.rng.gen_range(0..routes.len())];
        let spawn = &self.config.spawn;
        let along = s + jitter(&mut self.rng, spawn.longitudinal_jitter);
        let across = jitter(&mut self.rng, spawn.lateral_jitter);
        let lane = &self.network.lanes()[*lane];
        let heading = lane.heading(along);
        let position = lane.point(along) + Vec2::from_angle(heading).perp() * across;
        let dynamics = Dynamics::from(&self.config.vehicle);
        let mut car = Car {
            kin: Kinematics::new(position, heading, spawn.initial_speed).with_dynamics(dynamics),
            route,
            lane_index: 0,
            s: 0.0,
            lateral: 0.0,
            progress: 0.0,
            age: 0,
            total_reward: 0.0,
            abs_accel_sum: 0.0,
            max_abs_accel: 0.0,
            collisions: 0,
            energy_kj: 0.0,
            total_cost: 0.0,
        };
        track_route(&mut car, self.network.as_ref());
        car
    }

    fn rebuild_bodies(&mut self) {
        self.bodies.clear();
        for (slot, car) in self.cars.iter().enumerate() {
            if let Some(car) = car {
                self.bodies
                    .push((car.kin.position, car.kin.heading, Some(slot)));
            }
        }
        for o in &self.obstacles {
            self.bodies.push((o.kin.position, o.kin.heading, None));
        }
        self.grid.rebuild(self.bodies.iter().map(|b| b.0));
    }

    /// Marks every agent touching another body as crashed; counts contact pairs.
    /// Chooses every human driver's action from the state the agents observed.
    fn plan_human_drivers(&mut self) {
        let seen = |kin: &Kinematics| Seen {
            position: kin.position,
            heading: kin.heading,
            speed: kin.speed,
        };
        let (cars, obstacles) = (&self.cars, &self.obstacles);
        for (h, action) in self.human_actions.iter_mut().enumerate() {
            let me = self.agents + h;
            let Some(car) = cars[me].as_ref() else {
                continue;
            };
            let others = cars
                .iter()
                .enumerate()
                .filter(move |&(j, _)| j != me)
                .filter_map(|(_, c)| c.as_ref().map(|c| seen(&c.kin)))
                .chain(obstacles.iter().map(|o| seen(&o.kin)));
            *action = human::drive(car, self.network.as_ref(), &self.config.humans, others);
        }
    }

    fn detect_collisions(&mut self) {
        self.contacts.fill(None);
        self.rebuild_bodies();
        let shape = Cuboid::new(Vec2::new(LENGTH / 2.0, WIDTH / 2.0));
        let mut contacts = 0;
        let bodies = &self.bodies;
        let contacts_of = &mut self.contacts;
        for (i, &(p, h, slot)) in bodies.iter().enumerate() {
            if slot.is_none() {
                continue; // obstacles do not move: their contacts are found from the agent's side
            }
            self.grid.for_each_near(p, 2.0 * BOUNDING_RADIUS, |j| {
                let (q, g, other) = bodies[j];
                // Each agent pair once (i < j); agent–obstacle pairs from the agent.
                if j == i || (other.is_some() && j < i) || (p - q).length() > 2.0 * BOUNDING_RADIUS
                {
                    return;
                }
                let touching =
                    intersection_test(&Pose::new(p, h), &shape, &Pose::new(q, g), &shape)
                        .map(|r| r.intersecting)
                        .unwrap_or(false);
                if touching {
                    contacts += 1;
                    if let Some(s) = slot {
                        contacts_of[s].get_or_insert(match other {
                            Some(_) => Contact::Vehicle {
                                position: q,
                                heading: g,
                            },
                            None => Contact::Wreck,
                        });
                    }
                    if let Some(o) = other {
                        contacts_of[o].get_or_insert(Contact::Vehicle {
                            position: p,
                            heading: h,
                        });
                    }
                }
            });
        }
        self.result.collisions = contacts;
    }

    /// Recomputes observations, the alive mask and neighbourhoods for the current state.
    fn refresh(&mut self) {
        self.rebuild_bodies();
        let obs_dim = self.obs_dim();
        let range = self.config.sensors.lidar_range;
        let radius = self.config.neighbour_radius;
        let agents = self.agents;
        self.neighbour_ids.clear();
        self.neighbour_offsets[0] = 0;
        for slot in 0..self.slots() {
            let row = &mut self.observations[slot * obs_dim..(slot + 1) * obs_dim];
            let features = &mut self.lcf_features
                [slot * lcf_inputs::FEATURES..(slot + 1) * lcf_inputs::FEATURES];
            let Some(car) = self.cars[slot].as_ref() else {
                row.fill(0.0);
                features.fill(0.0);
                self.alive[slot] = false;
                self.neighbour_offsets[slot + 1] = self.neighbour_ids.len() as u32;
                continue;
            };
            self.alive[slot] = true;
            let view = Surroundings {
                network: self.network.as_ref(),
                bodies: &self.bodies,
                grid: &self.grid,
                lidar_range: range,
            };
            view.observe(slot, car, row, &mut self.near, &mut self.lidar);
            let (p, bodies, grid) = (car.kin.position, &self.bodies, &self.grid);
            let neighbours = &mut self.nearby_agents;
            neighbours.clear();
            grid.for_each_near(p, radius, |j| {
                if let Some(other) = bodies[j].2.filter(|&o| o < agents)
                    && other != slot
                    && (bodies[j].0 - p).length() <= radius
                {
                    neighbours.push(other as u32);
                }
            });
            // Nearest first (ties by slot), so "the k nearest" is a prefix of the list.
            let cars = &self.cars;
            let distance = |j: &u32| {
                cars[*j as usize]
                    .as_ref()
                    .map_or(f32::INFINITY, |c| (c.kin.position - p).length())
            };
            neighbours.sort_unstable_by(|a, b| distance(a).total_cmp(&distance(b)).then(a.cmp(b)));
            let motion = |kin: &Kinematics| lcf_inputs::Motion {
                position: kin.position.into(),
                velocity: (Vec2::from_angle(kin.heading) * kin.speed).into(),
            };
            features.copy_from_slice(&lcf_inputs::neighbourhood_features(
                motion(&car.kin),
                neighbours
                    .iter()
                    .filter_map(|&j| cars[j as usize].as_ref().map(|c| motion(&c.kin))),
                radius,
            ));
            self.neighbour_ids.extend_from_slice(neighbours);
            self.neighbour_offsets[slot + 1] = self.neighbour_ids.len() as u32;
        }
    }
}

#[cfg(test)]
impl Scene {
    /// Removes every car and obstacle and restarts the horizon (test set-up).
    pub(super) fn clear(&mut self) {
        self.steps = 0;
        self.cars.iter_mut().for_each(|c| *c = None);
        self.obstacles.clear();
        self.refresh();
    }

    /// Puts a car in `slot` on `route`, `progress` metres along it, `lateral` metres left of the
    /// centre line, heading along the lane plus `heading_offset`.
    pub(super) fn place(
        &mut self,
        slot: usize,
        route: usize,
        progress: f32,
        lateral: f32,
        heading_offset: f32,
        speed: f32,
    ) {
        let r = &self.network.routes()[route];
        let i = r.offsets.iter().rposition(|&o| o <= progress).unwrap_or(0);
        let lane = &self.network.lanes()[r.lanes[i]];
        let s = progress - r.offsets[i];
        let heading = lane.heading(s);
        let position = lane.point(s) + Vec2::from_angle(heading).perp() * lateral;
        let mut car = self.spawn_car(0, 0.0);
        car.route = route;
        car.lane_index = 0;
        car.kin = Kinematics::new(position, heading + heading_offset, speed)
            .with_dynamics(car.kin.dynamics);
        track_route(&mut car, self.network.as_ref());
        car.progress = progress;
        self.cars[slot] = Some(car);
        self.refresh();
    }
}

/// What a car's observation is made of besides the car: the road and every body on it.
struct Surroundings<'a> {
    network: &'a dyn RoadNetwork,
    /// (position, heading, slot) of every body, indexed by `grid`.
    bodies: &'a [(Vec2, f32, Option<usize>)],
    grid: &'a Grid,
    lidar_range: f32,
}

impl Surroundings<'_> {
    /// Writes the observation of `car` (in `slot`) into `row`; `near` and `lidar` are scratch.
    fn observe(
        &self,
        slot: usize,
        car: &Car,
        row: &mut [f32],
        near: &mut Vec<usize>,
        lidar: &mut [f32],
    ) {
        let at = RoutePosition {
            route: &self.network.routes()[car.route],
            lane_index: car.lane_index,
            s: car.s,
            lateral: car.lateral,
        };
        observation::write_state(row, &car.kin, &at, self.network.lanes());
        let (p, range, bodies) = (car.kin.position, self.lidar_range, self.bodies);
        near.clear();
        self.grid.for_each_near(p, range + BOUNDING_RADIUS, |j| {
            if bodies[j].2 != Some(slot) {
                near.push(j);
            }
        });
        lidar::scan(
            p,
            car.kin.heading,
            range,
            near.iter().map(|&j| (bodies[j].0, bodies[j].1)),
            lidar,
        );
        debug_assert_eq!(row.len() - LIDAR_OFFSET, lidar.len());
        observation::write_lidar(row, lidar, range);
    }
}

fn jitter(rng: &mut ChaCha8Rng, amplitude: f32) -> f32 {
    if amplitude > 0.0 {
        rng.gen_range(-amplitude..=amplitude)
    } else {
        0.0
    }
}

/// Updates the car's lane, lane coordinates and route progress from its position.
fn track_route(car: &mut Car, network: &dyn RoadNetwork) {
    let route = &network.routes()[car.route];
    loop {
        let lane = &network.lanes()[route.lanes[car.lane_index]];
        let (s, lateral) = lane.project(car.kin.position);
        if s > lane.length() && car.lane_index + 1 < route.lanes.len() {
            car.lane_index += 1;
            continue;
        }
        car.s = s;
        car.lateral = lateral;
        car.progress = route.offsets[car.lane_index] + s;
        return;
    }
}
