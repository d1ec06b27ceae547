//! Top-down pictures of a scene for `actor render`: pure functions from the simulator's state
//! to an RGBA frame buffer. Rasterised here (filled convex polygons, thick lines, rings; no
//! anti-aliasing) so a frame holds a few flat colours, which map onto an exact GIF palette and
//! let tests check pixels by colour.

use parry2d::math::Vec2;

use junction_core::episode::Outcome;
use junction_core::spec::LIDAR_OFFSET;

use crate::lane::{Lane, LaneShape};
use crate::network::RoadNetwork;
use crate::{Scene, StepResult, VehicleView};

pub type Rgba = [u8; 4];

pub const GRASS: Rgba = [52, 84, 58, 255];
pub const ROAD: Rgba = [72, 72, 78, 255];
/// Dashed lines between lanes of one direction and the solid outer road edge.
pub const LANE_LINE: Rgba = [225, 225, 225, 255];
/// The solid line on the driver's left (right-hand traffic: the centre line).
pub const CENTRE_LINE: Rgba = [236, 190, 60, 255];
/// Connector centre lines inside a junction: where the routes go.
pub const GUIDE: Rgba = [98, 98, 106, 255];
pub const AGENT: Rgba = [70, 140, 245, 255];
/// The agent whose lidar is drawn.
pub const LIDAR_AGENT: Rgba = [0, 215, 215, 255];
/// A human-driven (non-connected) car.
pub const HUMAN: Rgba = [210, 210, 200, 255];
/// A crashed car left on the road as an obstacle.
pub const OBSTACLE: Rgba = [140, 36, 36, 255];
pub const WINDSCREEN: Rgba = [24, 28, 40, 255];
pub const FLASH_SUCCESS: Rgba = [80, 225, 100, 255];
pub const FLASH_CRASH: Rgba = [255, 120, 0, 255];
pub const FLASH_OUT_OF_ROAD: Rgba = [235, 70, 235, 255];
const BEAM_MISS: Rgba = [255, 255, 255, 40];
const BEAM_HIT: Rgba = [255, 235, 60, 160];
const LEGEND_PANEL: Rgba = [28, 30, 34, 255];

/// Empty space around the road network, as a fraction of its extent on each side.
const MARGIN: f32 = 0.04;
/// Lane markings: width, dash and gap lengths (metres).
const MARKING_WIDTH_M: f32 = 0.2;
const DASH_M: f32 = 3.0;
const GAP_M: f32 = 3.0;
/// Longest straight piece used to draw a curved line (metres).
const CURVE_STEP_M: f32 = 1.0;
/// Frames the legend and ring sizes are designed for (pixels).
const DESIGN_SIZE: f32 = 640.0;
/// Headings tried per pixel when painting the road: `on_road` also checks the direction of
/// travel, and every part of the road is drivable in one of these.
const SURFACE_HEADINGS: usize = 8;

/// An RGBA image, row-major, top row first.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    width: usize,
    height: usize,
    pixels: Vec<u8>,
}

impl Frame {
    pub fn new(width: usize, height: usize, colour: Rgba) -> Frame {
        Frame {
            width,
            height,
            pixels: colour.repeat(width * height),
        }
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    /// RGBA bytes, 4 per pixel.
    pub fn pixels(&self) -> &[u8] {
        &self.pixels
    }

    pub fn pixel(&self, x: usize, y: usize) -> Rgba {
        let i = 4 * (y * self.width + x);
        [
            self.pixels[i],
            self.pixels[i + 1],
            self.pixels[i + 2],
            self.pixels[i + 3],
        ]
    }

    /// Paints one pixel; a colour with alpha < 255 is blended over what is there.
    fn put(&mut self, x: usize, y: usize, colour: Rgba) {
        let i = 4 * (y * self.width + x);
        let alpha = u16::from(colour[3]);
        for (out, &over) in self.pixels[i..i + 3].iter_mut().zip(&colour[..3]) {
            *out = ((u16::from(over) * alpha + u16::from(*out) * (255 - alpha)) / 255) as u8;
        }
        self.pixels[i + 3] = 255;
    }

    /// Fills the convex polygon `points` (pixel coordinates, either winding): every pixel
    /// whose centre lies inside.
    pub fn fill_convex(&mut self, points: &[[f32; 2]], colour: Rgba) {
        let (top, bottom) = points
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), p| {
                (a.min(p[1]), b.max(p[1]))
            });
        if !(top.is_finite() && bottom.is_finite()) {
            return;
        }
        let first_row = (top - 0.5).ceil().max(0.0) as usize;
        let end_row = ((bottom - 0.5).ceil().max(0.0) as usize).min(self.height);
        for y in first_row..end_row {
            let yc = y as f32 + 0.5;
            let (mut left, mut right) = (f32::INFINITY, f32::NEG_INFINITY);
            for (k, p) in points.iter().enumerate() {
                let q = points[(k + 1) % points.len()];
                if (p[1] <= yc) != (q[1] <= yc) {
                    let x = p[0] + (yc - p[1]) * (q[0] - p[0]) / (q[1] - p[1]);
                    left = left.min(x);
                    right = right.max(x);
                }
            }
            if left > right {
                continue;
            }
            let first = (left - 0.5).ceil().max(0.0) as usize;
            let end = ((right - 0.5).ceil().max(0.0) as usize).min(self.width);
            for x in first..end {
                self.put(x, y, colour);
            }
        }
    }

    /// A straight line `thickness` pixels wide (at least one) from `a` to `b`.
    pub fn line(&mut self, a: [f32; 2], b: [f32; 2], thickness: f32, colour: Rgba) {
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        let length = dx.hypot(dy);
        if length < 1e-6 {
            return;
        }
        let half = thickness.max(1.0) / 2.0;
        let (nx, ny) = (-dy / length * half, dx / length * half);
        self.fill_convex(
            &[
                [a[0] + nx, a[1] + ny],
                [b[0] + nx, b[1] + ny],
                [b[0] - nx, b[1] - ny],
                [a[0] - nx, a[1] - ny],
            ],
            colour,
        );
    }

    /// A circle of `radius` pixels, `thickness` pixels wide; a thickness of twice the radius
    /// gives a disc.
    pub fn ring(&mut self, centre: [f32; 2], radius: f32, thickness: f32, colour: Rgba) {
        let half = thickness.max(1.0) / 2.0;
        let reach = radius + half;
        let rows = (centre[1] - reach).floor().max(0.0) as usize
            ..((centre[1] + reach).ceil().max(0.0) as usize).min(self.height);
        let columns = (centre[0] - reach).floor().max(0.0) as usize
            ..((centre[0] + reach).ceil().max(0.0) as usize).min(self.width);
        for y in rows {
            for x in columns.clone() {
                let d = (x as f32 + 0.5 - centre[0]).hypot(y as f32 + 0.5 - centre[1]);
                if (d - radius).abs() <= half {
                    self.put(x, y, colour);
                }
            }
        }
    }
}

/// Maps world metres (y up) to pixels (y down) with one scale for both axes, centred on the
/// road network so it fills the frame whatever the scenario's size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View {
    centre: Vec2,
    /// Pixels per metre.
    scale: f32,
    width: usize,
    height: usize,
}

impl View {
    /// Fits the road network (lane centre lines widened to their drivable edges), with a
    /// margin, into `width` × `height` pixels.
    pub fn fit(network: &dyn RoadNetwork, width: usize, height: usize) -> View {
        let (mut low, mut high) = (Vec2::splat(f32::INFINITY), Vec2::splat(f32::NEG_INFINITY));
        for lane in network.lanes() {
            for s in samples(lane, 0.0, lane.length()) {
                for lateral in [lane.left_edge, -lane.right_edge] {
                    let p = offset_point(lane, s, lateral);
                    low = low.min(p);
                    high = high.max(p);
                }
            }
        }
        if !(low.is_finite() && high.is_finite()) {
            (low, high) = (Vec2::splat(-1.0), Vec2::splat(1.0));
        }
        let extent = (high - low).max(Vec2::splat(1.0)) * (1.0 + 2.0 * MARGIN);
        View {
            centre: (low + high) / 2.0,
            scale: (width as f32 / extent.x).min(height as f32 / extent.y),
            width,
            height,
        }
    }

    pub fn to_pixel(&self, p: Vec2) -> [f32; 2] {
        [
            (p.x - self.centre.x) * self.scale + self.width as f32 / 2.0,
            self.height as f32 / 2.0 - (p.y - self.centre.y) * self.scale,
        ]
    }

    /// The world point at the centre of pixel (x, y).
    pub fn to_world(&self, x: usize, y: usize) -> Vec2 {
        Vec2::new(
            (x as f32 + 0.5 - self.width as f32 / 2.0) / self.scale + self.centre.x,
            (self.height as f32 / 2.0 - (y as f32 + 0.5)) / self.scale + self.centre.y,
        )
    }

    /// Pixels per metre.
    pub fn scale(&self) -> f32 {
        self.scale
    }
}

/// A car that just finished, marked for a few steps where its episode ended.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Flash {
    pub vehicle: VehicleView,
    pub outcome: Outcome,
    /// Steps since the finish.
    pub age: u32,
}

/// The flashes to draw: finishes of the last `lifetime` steps (timeouts are not marked: at
/// the scene's horizon every car times out at once).
#[derive(Debug, Clone)]
pub struct Flashes {
    live: Vec<Flash>,
    lifetime: u32,
}

impl Flashes {
    pub fn new(lifetime: u32) -> Flashes {
        Flashes {
            live: Vec::new(),
            lifetime: lifetime.max(1),
        }
    }

    /// Ages the flashes by one step and adds this step's finishes.
    pub fn record(&mut self, result: &StepResult) {
        for flash in &mut self.live {
            flash.age += 1;
        }
        let lifetime = self.lifetime;
        self.live.retain(|f| f.age < lifetime);
        self.live.extend(
            result
                .finished
                .iter()
                .filter(|e| e.stats.outcome != Outcome::Timeout)
                .map(|e| Flash {
                    vehicle: e.vehicle,
                    outcome: e.stats.outcome,
                    age: 0,
                }),
        );
    }

    pub fn live(&self) -> &[Flash] {
        &self.live
    }
}

/// Draws scenes of one road network: the grass, road and markings are drawn once, every
/// frame starts from a copy of them.
pub struct Renderer {
    view: View,
    background: Frame,
}

impl Renderer {
    pub fn new(network: &dyn RoadNetwork, width: usize, height: usize) -> Renderer {
        let view = View::fit(network, width, height);
        let mut background = Frame::new(width, height, GRASS);
        paint_road(&mut background, &view, network);
        paint_markings(&mut background, &view, network);
        paint_legend(&mut background);
        Renderer { view, background }
    }

    pub fn view(&self) -> &View {
        &self.view
    }

    /// The scene now: cars (agents, crashed obstacles), the finishes in `flashes`, and the
    /// lidar of the agent in `lidar_slot` (if that slot holds a car).
    pub fn draw(&self, scene: &Scene, flashes: &[Flash], lidar_slot: Option<usize>) -> Frame {
        let mut frame = self.background.clone();
        let view = &self.view;
        if let Some(slot) = lidar_slot {
            paint_lidar(&mut frame, view, scene, slot);
        }
        for vehicle in scene.vehicles() {
            let colour = match vehicle.slot {
                None if vehicle.human => HUMAN,
                None => OBSTACLE,
                Some(slot) if Some(slot) == lidar_slot => LIDAR_AGENT,
                Some(_) => AGENT,
            };
            paint_car(&mut frame, view, &vehicle, colour);
        }
        for flash in flashes {
            let colour = match flash.outcome {
                Outcome::Success => FLASH_SUCCESS,
                Outcome::Crash => FLASH_CRASH,
                Outcome::OutOfRoad | Outcome::Timeout => FLASH_OUT_OF_ROAD,
            };
            paint_car(&mut frame, view, &flash.vehicle, colour);
            // A ring that widens as the flash ages, so a finish catches the eye.
            let radius = flash.vehicle.length * (0.7 + 0.25 * flash.age as f32) * view.scale();
            let thickness = (0.5 * view.scale()).max(2.0);
            frame.ring(
                view.to_pixel(flash.vehicle.position),
                radius,
                thickness,
                colour,
            );
        }
        frame
    }
}

/// `s` from `from` to `to` at most `CURVE_STEP_M` apart, both ends included.
fn samples(lane: &Lane, from: f32, to: f32) -> impl Iterator<Item = f32> {
    let pieces = match lane.shape {
        LaneShape::Straight { .. } => 1,
        LaneShape::Arc { .. } => ((to - from) / CURVE_STEP_M).ceil().max(1.0) as usize,
    };
    (0..=pieces).map(move |k| from + (to - from) * k as f32 / pieces as f32)
}

/// The point `lateral` metres left of the lane's centre line at `s`.
fn offset_point(lane: &Lane, s: f32, lateral: f32) -> Vec2 {
    lane.point(s) + Vec2::from_angle(lane.heading(s)).perp() * lateral
}

/// Road colour on every pixel whose centre is drivable in some direction.
fn paint_road(frame: &mut Frame, view: &View, network: &dyn RoadNetwork) {
    let headings: Vec<f32> = (0..SURFACE_HEADINGS)
        .map(|k| k as f32 * std::f32::consts::TAU / SURFACE_HEADINGS as f32)
        .collect();
    for y in 0..frame.height {
        for x in 0..frame.width {
            let p = view.to_world(x, y);
            if headings.iter().any(|&h| network.on_road(p, h)) {
                frame.put(x, y, ROAD);
            }
        }
    }
}

/// Lane markings from the lane geometry. Lanes inside a junction (connectors: the middle of
/// some route) get a faint centre line showing where routes go; the others get a dashed line
/// between lanes, a solid line at the road's outer edge and a solid centre line on the
/// driver's left where the drivable road ends.
fn paint_markings(frame: &mut Frame, view: &View, network: &dyn RoadNetwork) {
    let lanes = network.lanes();
    let mut connector = vec![false; lanes.len()];
    for route in network.routes() {
        if let [_, middle @ .., _] = route.lanes.as_slice() {
            middle.iter().for_each(|&l| connector[l] = true);
        }
    }
    let thickness = MARKING_WIDTH_M * view.scale();
    // A lane edge closer than this to the drivable edge is a road boundary.
    let boundary = |edge: f32, lane: &Lane| (edge - lane.width / 2.0).abs() < 0.05;
    for (id, lane) in lanes.iter().enumerate() {
        let half = lane.width / 2.0;
        if connector[id] {
            stroke_dashed(frame, view, lane, 0.0, 1.0, GUIDE);
            continue;
        }
        if boundary(lane.right_edge, lane) {
            stroke(
                frame,
                view,
                lane,
                -half,
                0.0,
                lane.length(),
                thickness,
                LANE_LINE,
            );
        } else {
            stroke_dashed(frame, view, lane, -half, thickness, LANE_LINE);
        }
        // A left edge that is not a boundary is the right edge of the neighbouring lane.
        if boundary(lane.left_edge, lane) {
            stroke(
                frame,
                view,
                lane,
                half,
                0.0,
                lane.length(),
                thickness,
                CENTRE_LINE,
            );
        }
    }
}

/// A line `lateral` metres left of the lane's centre line, from `s = from` to `s = to`.
#[allow(clippy::too_many_arguments)]
fn stroke(
    frame: &mut Frame,
    view: &View,
    lane: &Lane,
    lateral: f32,
    from: f32,
    to: f32,
    thickness: f32,
    colour: Rgba,
) {
    let mut previous: Option<[f32; 2]> = None;
    for s in samples(lane, from, to) {
        let p = view.to_pixel(offset_point(lane, s, lateral));
        if let Some(q) = previous {
            frame.line(q, p, thickness, colour);
        }
        previous = Some(p);
    }
}

fn stroke_dashed(
    frame: &mut Frame,
    view: &View,
    lane: &Lane,
    lateral: f32,
    thickness: f32,
    colour: Rgba,
) {
    let mut from = 0.0;
    while from < lane.length() {
        let to = (from + DASH_M).min(lane.length());
        stroke(frame, view, lane, lateral, from, to, thickness, colour);
        from += DASH_M + GAP_M;
    }
}

/// The body as an oriented rectangle, with a dark windscreen towards the front.
fn paint_car(frame: &mut Frame, view: &View, vehicle: &VehicleView, colour: Rgba) {
    let forward = Vec2::from_angle(vehicle.heading);
    let left = forward.perp();
    let quad = |back: f32, front: f32, half_width: f32| {
        [
            vehicle.position + forward * front + left * half_width,
            vehicle.position + forward * back + left * half_width,
            vehicle.position + forward * back - left * half_width,
            vehicle.position + forward * front - left * half_width,
        ]
        .map(|p| view.to_pixel(p))
    };
    let (half_length, half_width) = (vehicle.length / 2.0, vehicle.width / 2.0);
    frame.fill_convex(&quad(-half_length, half_length, half_width), colour);
    frame.fill_convex(
        &quad(0.2 * half_length, 0.6 * half_length, 0.8 * half_width),
        WINDSCREEN,
    );
}

/// The lidar beams of the agent in `slot`, read back from its observation (beam 0 straight
/// ahead, counter-clockwise): faint where nothing is in range, bright up to a hit.
fn paint_lidar(frame: &mut Frame, view: &View, scene: &Scene, slot: usize) {
    let Some(ego) = scene.vehicles().find(|v| v.slot == Some(slot)) else {
        return;
    };
    let (obs_dim, range) = (scene.obs_dim(), scene.config().sensors.lidar_range);
    let beams = &scene.observations()[slot * obs_dim + LIDAR_OFFSET..(slot + 1) * obs_dim];
    let step = std::f32::consts::TAU / beams.len() as f32;
    let origin = view.to_pixel(ego.position);
    let dot = (0.4 * view.scale()).max(1.5);
    for (b, &fraction) in beams.iter().enumerate() {
        let end = ego.position + Vec2::from_angle(ego.heading + b as f32 * step) * fraction * range;
        let end = view.to_pixel(end);
        if fraction < 1.0 {
            frame.line(origin, end, 1.0, BEAM_HIT);
            frame.ring(end, dot / 2.0, dot, BEAM_HIT);
        } else {
            frame.line(origin, end, 1.0, BEAM_MISS);
        }
    }
}

/// A text-free legend in the top-left corner: one car swatch per colour, in the order
/// driving agent, human driver, crashed (obstacle), arrived, crashed just now, left the road.
fn paint_legend(frame: &mut Frame) {
    let unit = frame.width.min(frame.height) as f32 / DESIGN_SIZE;
    let swatches = [
        AGENT,
        HUMAN,
        OBSTACLE,
        FLASH_SUCCESS,
        FLASH_CRASH,
        FLASH_OUT_OF_ROAD,
    ];
    let (pad, length, width, gap) = (6.0 * unit, 18.0 * unit, 8.0 * unit, 8.0 * unit);
    let panel_right = 2.0 * pad + swatches.len() as f32 * (length + gap) - gap;
    let panel_bottom = 2.0 * pad + width;
    frame.fill_convex(
        &[
            [0.0, 0.0],
            [panel_right, 0.0],
            [panel_right, panel_bottom],
            [0.0, panel_bottom],
        ],
        LEGEND_PANEL,
    );
    for (k, colour) in swatches.into_iter().enumerate() {
        let x = pad + k as f32 * (length + gap);
        frame.fill_convex(
            &[
                [x, pad],
                [x + length, pad],
                [x + length, pad + width],
                [x, pad + width],
            ],
            colour,
        );
        let screen = x + 0.6 * length;
        frame.fill_convex(
            &[
                [screen, pad + 0.1 * width],
                [screen + 0.2 * length, pad + 0.1 * width],
                [screen + 0.2 * length, pad + 0.9 * width],
                [screen, pad + 0.9 * width],
            ],
            WINDSCREEN,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use junction_core::episode::{Ending, EpisodeStats, RouteStage};
    use junction_core::scenarios;

    use crate::FinishedEpisode;
    use crate::autopilot::{CRUISE_SPEED_MPS, autopilot_actions};

    fn intersection(seed: u64) -> Scene {
        Scene::new(&scenarios::load("intersection").unwrap(), seed).unwrap()
    }

    fn pixel_at(frame: &Frame, view: &View, p: Vec2) -> Rgba {
        let [x, y] = view.to_pixel(p);
        frame.pixel(x as usize, y as usize)
    }

    /// A point on the body behind the windscreen.
    fn body_point(v: &VehicleView) -> Vec2 {
        v.position - Vec2::from_angle(v.heading) * (0.25 * v.length)
    }

    #[test]
    fn human_drivers_have_their_own_colour() {
        let mut config = scenarios::load("intersection").unwrap();
        config.humans.share = 0.25;
        let scene = Scene::new(&config, 3).unwrap();
        let renderer = Renderer::new(scene.network(), 640, 640);
        let frame = renderer.draw(&scene, &[], None);
        let humans: Vec<VehicleView> = scene.vehicles().filter(|v| v.human).collect();
        assert_eq!(humans.len(), 10);
        for car in &humans {
            let colour = pixel_at(&frame, renderer.view(), body_point(car));
            assert_eq!(colour, HUMAN, "{car:?}");
        }
    }

    #[test]
    fn cars_lanes_and_grass_land_on_their_pixels() {
        let scene = intersection(3);
        let renderer = Renderer::new(scene.network(), 640, 640);
        let view = renderer.view();
        let frame = renderer.draw(&scene, &[], None);
        let cars: Vec<VehicleView> = scene.vehicles().collect();
        assert_eq!(cars.len(), 30);
        for car in &cars {
            assert_eq!(pixel_at(&frame, view, body_point(car)), AGENT, "{car:?}");
        }
        // Exit lanes are empty at reset: their centre lines show bare road.
        let network = scene.network();
        let mut exits = 0;
        for route in network.routes() {
            let lane = &network.lanes()[*route.lanes.last().unwrap()];
            let p = lane.point(lane.length() / 2.0);
            // No body reaches it (a car covers at most 2.45 m from its centre).
            assert!(cars.iter().all(|c| (c.position - p).length() > 2.5));
            assert_eq!(pixel_at(&frame, view, p), ROAD, "exit lane centre at {p:?}");
            exits += 1;
        }
        assert_eq!(exits, 16);
        // The solid centre line of the east arm, and grass between the arms.
        let [x, y] = view.to_pixel(Vec2::new(50.0, 0.0));
        let line_rows = (y as usize - 1..=y as usize + 1)
            .filter(|&row| frame.pixel(x as usize, row) == CENTRE_LINE);
        assert_eq!(line_rows.count(), 1, "a one-pixel centre line");
        assert_eq!(pixel_at(&frame, view, Vec2::new(50.0, -50.0)), GRASS);
        assert_eq!(frame.pixel(639, 639), GRASS);
    }

    #[test]
    fn the_view_fits_the_road_network() {
        let scene = intersection(1);
        let view = View::fit(scene.network(), 400, 300);
        let mut low = [f32::INFINITY; 2];
        let mut high = [f32::NEG_INFINITY; 2];
        for lane in scene.network().lanes() {
            for p in [lane.start(), lane.end()] {
                let [x, y] = view.to_pixel(p);
                low = [low[0].min(x), low[1].min(y)];
                high = [high[0].max(x), high[1].max(y)];
            }
        }
        assert!(low[0] >= 0.0 && low[1] >= 0.0 && high[0] <= 400.0 && high[1] <= 300.0);
        // The square network fills the shorter side but for the margin and the road's edge.
        assert!(high[1] - low[1] > 0.85 * 300.0, "{low:?} {high:?}");
        let p = Vec2::new(12.5, -3.0);
        let [x, y] = view.to_pixel(p);
        assert!((view.to_world(x as usize, y as usize) - p).length() < 1.0 / view.scale());
    }

    #[test]
    fn crashed_cars_stay_dark_red_and_finishes_flash() {
        let mut scene = intersection(1);
        let renderer = Renderer::new(scene.network(), 640, 640);
        let mut flashes = Flashes::new(5);
        let mut actions = vec![0.0; scene.slots() * 2];
        let crash = (0..600)
            .find_map(|_| {
                autopilot_actions(&scene, CRUISE_SPEED_MPS, &mut actions);
                let result = scene.step(&actions);
                flashes.record(result);
                result
                    .finished
                    .iter()
                    .find(|e| e.stats.outcome == Outcome::Crash)
                    .map(|e| e.vehicle)
            })
            .expect("the autopilot crashes within 600 steps");
        let wreck = scene
            .vehicles()
            .find(|v| v.slot.is_none() && v.position == crash.position)
            .expect("a crashed car stays as an obstacle");
        let view = renderer.view();
        let plain = renderer.draw(&scene, &[], None);
        assert_eq!(pixel_at(&plain, view, body_point(&wreck)), OBSTACLE);
        let flashing = renderer.draw(&scene, flashes.live(), None);
        assert_eq!(pixel_at(&flashing, view, body_point(&wreck)), FLASH_CRASH);
        // The ring around it, ahead of the car.
        let ring = crash.position + Vec2::from_angle(crash.heading) * 0.7 * crash.length;
        assert_eq!(pixel_at(&flashing, view, ring), FLASH_CRASH);
    }

    #[test]
    fn flashes_last_their_lifetime_and_skip_timeouts() {
        let scene = intersection(1);
        let vehicle = scene.vehicles().next().unwrap();
        let finished = |outcome| FinishedEpisode {
            slot: 0,
            stats: EpisodeStats {
                outcome,
                length: 10,
                total_reward: 0.0,
                mean_abs_accel: 0.0,
                max_abs_accel: 0.0,
                collisions: 0,
                energy_kj: 0.0,
                total_cost: 0.0,
            },
            ending: Ending {
                outcome,
                stage: RouteStage::Exit,
                crash: None,
            },
            vehicle,
            observation: Vec::new(),
        };
        let step = StepResult {
            finished: vec![finished(Outcome::Success), finished(Outcome::Timeout)],
            ..StepResult::default()
        };
        let mut flashes = Flashes::new(3);
        flashes.record(&step);
        assert_eq!(flashes.live().len(), 1);
        assert_eq!(flashes.live()[0].outcome, Outcome::Success);
        for age in 1..3 {
            flashes.record(&StepResult::default());
            assert_eq!(flashes.live()[0].age, age);
        }
        flashes.record(&StepResult::default());
        assert!(flashes.live().is_empty());
    }

    #[test]
    fn lidar_beams_are_drawn_from_the_chosen_agent() {
        let scene = intersection(2);
        let renderer = Renderer::new(scene.network(), 640, 640);
        let plain = renderer.draw(&scene, &[], None);
        let with_lidar = renderer.draw(&scene, &[], Some(0));
        let ego = scene.vehicles().find(|v| v.slot == Some(0)).unwrap();
        assert_eq!(
            pixel_at(&with_lidar, renderer.view(), body_point(&ego)),
            LIDAR_AGENT
        );
        // 72 beams up to 50 m: hundreds of pixels change, only blended over the picture.
        let changed = plain
            .pixels()
            .chunks_exact(4)
            .zip(with_lidar.pixels().chunks_exact(4))
            .filter(|(a, b)| a != b)
            .count();
        assert!(changed > 2000, "{changed} pixels changed");
        // A slot without a car draws nothing extra.
        assert!(renderer.draw(&scene, &[], Some(99)) == plain);
    }

    #[test]
    fn rasteriser_fills_pixel_centres() {
        let mut frame = Frame::new(20, 20, GRASS);
        frame.fill_convex(&[[2.0, 2.0], [12.0, 2.0], [12.0, 12.0], [2.0, 12.0]], ROAD);
        let count = |frame: &Frame, c: Rgba| {
            (0..20)
                .flat_map(|y| (0..20).map(move |x| (x, y)))
                .filter(|&(x, y)| frame.pixel(x, y) == c)
                .count()
        };
        assert_eq!(count(&frame, ROAD), 100);
        assert_eq!(frame.pixel(2, 2), ROAD);
        assert_eq!(frame.pixel(12, 12), GRASS);
        // A horizontal line 2 px thick, 10 px long.
        frame.line([5.0, 16.0], [15.0, 16.0], 2.0, AGENT);
        assert_eq!(count(&frame, AGENT), 20);
        // A disc of radius 3: about π·9 pixels.
        let mut disc = Frame::new(20, 20, GRASS);
        disc.ring([10.0, 10.0], 1.5, 3.0, OBSTACLE);
        let n = count(&disc, OBSTACLE);
        assert!((24..=32).contains(&n), "{n}");
        // Half-transparent colours blend.
        let mut blend = Frame::new(1, 1, [0, 0, 0, 255]);
        blend.put(0, 0, [255, 255, 255, 128]);
        assert_eq!(blend.pixel(0, 0), [128, 128, 128, 255]);
    }
}
