//! `junction._native`: the simulator (`junction-sim`) for Python. Scenes step in Rust with the
//! GIL released and hand back whole NumPy arrays per step (one copy out of the scenes' own
//! buffers, no Python object per agent); the Python package (`python/junction`) builds the
//! PettingZoo, Gymnasium and vector environments on top. Also here: scenario loading with
//! `--set`'s names and errors, LCF neighbourhoods for the MetaDrive actor, the evaluation
//! report `actor eval` writes, and the policy network's tanh (`junction.policy`).

use numpy::ndarray::{Array2, Array3};
use numpy::{
    IntoPyArray, PyArray1, PyReadonlyArray1, PyReadonlyArray2, PyReadwriteArrayDyn,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyIndexError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use junction_core::activation;
use junction_core::config::{ConfigError as RustConfigError, Layer, RunConfig, ScenarioConfig};
use junction_core::episode::{EpisodeStats, Outcome, SceneEpisodeStats};
use junction_core::evaluation::{EVAL_FORMAT, EvalActions, EvalReport, EvalTally, TrainingInfo};
use junction_core::lcf_inputs::{self, Motion};
use junction_core::scenarios;
use junction_core::spec::ACTION_DIM;
use junction_sim::render::{Flashes, Renderer};
use junction_sim::{Scene, SimError};

pyo3::create_exception!(
    _native,
    ConfigError,
    PyValueError,
    "A scenario or override the simulator refuses; the message is `learner --set`'s."
);

fn config_error(e: RustConfigError) -> PyErr {
    ConfigError::new_err(e.to_string())
}

fn sim_error(e: SimError) -> PyErr {
    ConfigError::new_err(e.to_string())
}

/// Steps a finish stays drawn in `render` (half a second at 0.1 s steps, as `actor render`).
const FLASH_STEPS: u32 = 5;

/// A validated scenario: the `[scenario]` section of a run configuration.
#[pyclass(frozen, module = "junction._native")]
struct Scenario {
    config: ScenarioConfig,
}

#[pymethods]
impl Scenario {
    #[getter]
    fn name(&self) -> &str {
        &self.config.name
    }

    /// Learning-agent slots of a scene (after the traffic preset).
    #[getter]
    fn slots(&self) -> usize {
        self.config.agent_count()
    }

    #[getter]
    fn obs_dim(&self) -> usize {
        self.config.obs_dim()
    }

    /// The scenario as TOML, every key written out (what a learner sends its actors).
    #[getter]
    fn toml(&self) -> String {
        self.config.to_toml()
    }

    fn __repr__(&self) -> String {
        format!(
            "Scenario({:?}, slots={}, obs_dim={})",
            self.config.name,
            self.config.agent_count(),
            self.config.obs_dim()
        )
    }
}

/// A shipped scenario by name (or a scenario file) with `section.key=value` overrides, loaded
/// and validated exactly as `learner serve --scenario NAME --set ...` does.
#[pyfunction]
fn load_scenario(name_or_path: &str, overrides: Vec<String>) -> PyResult<Scenario> {
    let text = scenarios::text(name_or_path).map_err(config_error)?;
    scenario_from_layers(&text, &overrides)
}

/// A scenario given as TOML (e.g. a learner's `RegisterReply.scenario_toml`), over the
/// defaults, with overrides.
#[pyfunction]
fn scenario_from_toml(text: &str, overrides: Vec<String>) -> PyResult<Scenario> {
    scenario_from_layers(text, &overrides)
}

fn scenario_from_layers(text: &str, overrides: &[String]) -> PyResult<Scenario> {
    let layers: Vec<Layer> = std::iter::once(Layer::Scenario(text))
        .chain(overrides.iter().map(|o| Layer::Set(o)))
        .collect();
    let config = RunConfig::from_layers(&layers).map_err(config_error)?;
    Ok(Scenario {
        config: config.scenario,
    })
}

/// `num_scenes` scenes of one scenario stepped together; every array is
/// `[scene, slot, ...]`. Scene k is `Scene::new(scenario, seed + k)`.
#[pyclass(module = "junction._native")]
struct VectorEnv {
    config: ScenarioConfig,
    scenes: Vec<Scene>,
    /// The agent id in each (scene, slot), −1 when empty: ids count from 0 in every scene
    /// episode, in the order cars appear, as MetaDrive names its agents.
    ids: Vec<i64>,
    next_id: Vec<i64>,
    /// (size, renderer) per scene, built on the first `render` of that size.
    renderers: Vec<Option<((usize, usize), Renderer)>>,
    flashes: Vec<Flashes>,
}

impl VectorEnv {
    fn slots(&self) -> usize {
        self.config.agent_count()
    }

    fn build(&mut self, seed: u64) -> PyResult<()> {
        self.scenes = (0..self.next_id.len())
            .map(|k| Scene::new(&self.config, seed.wrapping_add(k as u64)))
            .collect::<Result<_, _>>()
            .map_err(sim_error)?;
        self.flashes = vec![Flashes::new(FLASH_STEPS); self.scenes.len()];
        self.number_new_scene_episodes(&vec![true; self.scenes.len()]);
        Ok(())
    }

    /// Gives every car of the scenes in `started` a fresh id, from 0.
    fn number_new_scene_episodes(&mut self, started: &[bool]) {
        let slots = self.slots();
        for (k, scene) in self.scenes.iter().enumerate() {
            if !started[k] {
                continue;
            }
            self.next_id[k] = 0;
            for (slot, &alive) in scene.alive().iter().enumerate() {
                self.ids[k * slots + slot] = if alive {
                    self.next_id[k] += 1;
                    self.next_id[k] - 1
                } else {
                    -1
                };
            }
        }
    }

    /// The state every step and reset returns: observations, alive mask, ids, S_N.
    fn state<'py>(&self, py: Python<'py>, out: &Bound<'py, PyDict>) -> PyResult<()> {
        let (n, slots, dim) = (self.scenes.len(), self.slots(), self.config.obs_dim());
        let mut obs = Vec::with_capacity(n * slots * dim);
        let mut alive = Vec::with_capacity(n * slots);
        let mut lcf = Vec::with_capacity(n * slots * lcf_inputs::FEATURES);
        for scene in &self.scenes {
            obs.extend_from_slice(scene.observations());
            alive.extend_from_slice(scene.alive());
            lcf.extend_from_slice(scene.lcf_features());
        }
        out.set_item("obs", array3(py, obs, (n, slots, dim))?)?;
        out.set_item("alive", array2(py, alive, (n, slots))?)?;
        out.set_item("agent_ids", array2(py, self.ids.clone(), (n, slots))?)?;
        out.set_item(
            "lcf_features",
            array3(py, lcf, (n, slots, lcf_inputs::FEATURES))?,
        )?;
        Ok(())
    }

    fn scene(&self, index: usize) -> PyResult<&Scene> {
        self.scenes.get(index).ok_or_else(|| {
            PyIndexError::new_err(format!(
                "scene {index} out of range: the environment has {} scenes",
                self.scenes.len()
            ))
        })
    }
}

/// Neighbour lists in CSR form: offsets (one per slot, plus one) and neighbour ids.
type Csr<'py> = (Bound<'py, PyArray1<u32>>, Bound<'py, PyArray1<u32>>);

/// What one scene's step produced, collected without the GIL.
struct SceneStep {
    rewards: Vec<f32>,
    costs: Vec<f32>,
    dones: Vec<bool>,
    /// (slot, stats, final observation) of every agent episode that ended.
    finished: Vec<(usize, EpisodeStats, Vec<f32>)>,
    scene_episode: Option<SceneEpisodeStats>,
}

#[pymethods]
impl VectorEnv {
    #[new]
    fn new(scenario: &Scenario, num_scenes: usize, seed: u64) -> PyResult<Self> {
        if num_scenes == 0 {
            return Err(PyValueError::new_err("num_scenes must be at least 1"));
        }
        let config = scenario.config.clone();
        let slots = config.agent_count();
        let mut env = VectorEnv {
            scenes: Vec::new(),
            ids: vec![-1; num_scenes * slots],
            next_id: vec![0; num_scenes],
            renderers: (0..num_scenes).map(|_| None).collect(),
            flashes: Vec::new(),
            config,
        };
        env.build(seed)?;
        Ok(env)
    }

    #[getter]
    fn num_scenes(&self) -> usize {
        self.scenes.len()
    }

    #[getter(slots)]
    fn slot_count(&self) -> usize {
        self.slots()
    }

    #[getter]
    fn obs_dim(&self) -> usize {
        self.config.obs_dim()
    }

    /// Rebuilds every scene from `seed` (scene k from `seed + k`); returns the state.
    fn reset<'py>(&mut self, py: Python<'py>, seed: u64) -> PyResult<Bound<'py, PyDict>> {
        self.build(seed)?;
        let out = PyDict::new(py);
        self.state(py, &out)?;
        Ok(out)
    }

    /// The current state, as `reset` and `step` return it.
    fn observe<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let out = PyDict::new(py);
        self.state(py, &out)?;
        Ok(out)
    }

    /// Steps every scene with `actions` (float32, C-contiguous, `num_scenes × slots × 2`
    /// values; empty slots' actions are ignored). Returns the new state and, for the agents
    /// that acted, rewards, costs, `terminated` / `truncated` (a timeout is a truncation), the
    /// ids they had, their finished episodes (with each one's final observation) and the scene
    /// episodes that ended (their scenes have started afresh).
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        actions: PyReadonlyArray1<'py, f32>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let (n, slots, dim) = (self.scenes.len(), self.slots(), self.config.obs_dim());
        let actions = actions
            .as_slice()
            .map_err(|_| PyValueError::new_err("actions must be a C-contiguous float32 array"))?;
        if actions.len() != n * slots * ACTION_DIM {
            return Err(PyValueError::new_err(format!(
                "actions hold {} values; {n} scenes × {slots} slots × {ACTION_DIM} expected",
                actions.len()
            )));
        }
        let acted_ids = self.ids.clone();
        let was_alive: Vec<bool> = self
            .scenes
            .iter()
            .flat_map(|s| s.alive().iter().copied())
            .collect();
        // Renderers mark finishes for a few steps; only scenes that have been drawn keep them.
        let drawn: Vec<bool> = self.renderers.iter().map(Option::is_some).collect();
        let (scenes, flashes) = (&mut self.scenes, &mut self.flashes);
        let steps: Vec<SceneStep> = py.detach(|| {
            scenes
                .iter_mut()
                .zip(flashes.iter_mut())
                .zip(&drawn)
                .zip(actions.chunks_exact(slots * ACTION_DIM))
                .map(|(((scene, flashes), &drawn), actions)| {
                    let result = scene.step(actions);
                    if drawn {
                        flashes.record(result);
                    }
                    SceneStep {
                        rewards: result.rewards.clone(),
                        costs: result.costs.clone(),
                        dones: result.dones.clone(),
                        finished: result
                            .finished
                            .iter()
                            .map(|e| (e.slot, e.stats, e.observation.clone()))
                            .collect(),
                        scene_episode: result.scene_episode,
                    }
                })
                .collect()
        });

        // New ids: a slot holds a new car when it is alive now and was empty or ended.
        let started: Vec<bool> = steps.iter().map(|s| s.scene_episode.is_some()).collect();
        for (k, scene) in self.scenes.iter().enumerate() {
            if started[k] {
                continue;
            }
            for (slot, &alive) in scene.alive().iter().enumerate() {
                let cell = k * slots + slot;
                if !alive {
                    self.ids[cell] = -1;
                } else if !was_alive[cell] || steps[k].dones[slot] {
                    self.ids[cell] = self.next_id[k];
                    self.next_id[k] += 1;
                }
            }
        }
        self.number_new_scene_episodes(&started);

        let mut rewards = Vec::with_capacity(n * slots);
        let mut costs = Vec::with_capacity(n * slots);
        let mut terminated = vec![false; n * slots];
        let mut truncated = vec![false; n * slots];
        let mut outcome = vec![-1i8; n * slots];
        let finished_count: usize = steps.iter().map(|s| s.finished.len()).sum();
        let mut f_scene = Vec::with_capacity(finished_count);
        let mut f_slot = Vec::with_capacity(finished_count);
        let mut f_id = Vec::with_capacity(finished_count);
        let mut f_outcome = Vec::with_capacity(finished_count);
        let mut f_length = Vec::with_capacity(finished_count);
        let mut f_reward = Vec::with_capacity(finished_count);
        let mut f_cost = Vec::with_capacity(finished_count);
        let mut f_collisions = Vec::with_capacity(finished_count);
        let mut f_obs = Vec::with_capacity(finished_count * dim);
        let mut scene_episodes = Vec::new();
        for (k, s) in steps.into_iter().enumerate() {
            rewards.extend_from_slice(&s.rewards);
            costs.extend_from_slice(&s.costs);
            for (slot, stats, observation) in s.finished {
                let cell = k * slots + slot;
                outcome[cell] = stats.outcome as i8;
                if stats.outcome == Outcome::Timeout {
                    truncated[cell] = true;
                } else {
                    terminated[cell] = true;
                }
                f_scene.push(k as i64);
                f_slot.push(slot as i64);
                f_id.push(acted_ids[cell]);
                f_outcome.push(stats.outcome as i8);
                f_length.push(i64::from(stats.length));
                f_reward.push(stats.total_reward);
                f_cost.push(stats.total_cost);
                f_collisions.push(i64::from(stats.collisions));
                f_obs.extend_from_slice(&observation);
            }
            if let Some(e) = s.scene_episode {
                scene_episodes.extend([
                    k as i64,
                    i64::from(e.steps),
                    i64::from(e.successes),
                    i64::from(e.crashes),
                    i64::from(e.out_of_road),
                    i64::from(e.timeouts),
                ]);
            }
        }
        let out = PyDict::new(py);
        self.state(py, &out)?;
        out.set_item("acted_ids", array2(py, acted_ids, (n, slots))?)?;
        out.set_item("rewards", array2(py, rewards, (n, slots))?)?;
        out.set_item("costs", array2(py, costs, (n, slots))?)?;
        out.set_item("terminated", array2(py, terminated, (n, slots))?)?;
        out.set_item("truncated", array2(py, truncated, (n, slots))?)?;
        out.set_item("outcome", array2(py, outcome, (n, slots))?)?;
        let finished = PyDict::new(py);
        finished.set_item("scene", PyArray1::from_vec(py, f_scene))?;
        finished.set_item("slot", PyArray1::from_vec(py, f_slot))?;
        finished.set_item("agent_id", PyArray1::from_vec(py, f_id))?;
        finished.set_item("outcome", PyArray1::from_vec(py, f_outcome))?;
        finished.set_item("length", PyArray1::from_vec(py, f_length))?;
        finished.set_item("total_reward", PyArray1::from_vec(py, f_reward))?;
        finished.set_item("total_cost", PyArray1::from_vec(py, f_cost))?;
        finished.set_item("collisions", PyArray1::from_vec(py, f_collisions))?;
        finished.set_item("observation", array2(py, f_obs, (finished_count, dim))?)?;
        out.set_item("finished", finished)?;
        let ended = scene_episodes.len() / 6;
        out.set_item("scene_episodes", array2(py, scene_episodes, (ended, 6))?)?;
        Ok(out)
    }

    /// Neighbour lists of scene `scene` (CSR: the neighbours of slot i are
    /// `ids[offsets[i]:offsets[i + 1]]`, nearest first).
    fn neighbours<'py>(&self, py: Python<'py>, scene: usize) -> PyResult<Csr<'py>> {
        let (offsets, ids) = self.scene(scene)?.neighbours();
        Ok((
            PyArray1::from_slice(py, offsets),
            PyArray1::from_slice(py, ids),
        ))
    }

    /// Scene `scene` from above as RGB, `height × width × 3` bytes (`actor render`'s
    /// picture: agents blue, human drivers grey, wrecks dark red, finishes ringed).
    fn render<'py>(
        &mut self,
        py: Python<'py>,
        scene: usize,
        width: usize,
        height: usize,
    ) -> PyResult<Bound<'py, PyAny>> {
        if !(16..=4096).contains(&width) || !(16..=4096).contains(&height) {
            return Err(PyValueError::new_err(format!(
                "render size {width}×{height}: each side must be 16 to 4096 pixels"
            )));
        }
        self.scene(scene)?;
        let renderer = match &self.renderers[scene] {
            Some((size, renderer)) if *size == (width, height) => renderer,
            _ => {
                let renderer = Renderer::new(self.scenes[scene].network(), width, height);
                &self.renderers[scene].insert(((width, height), renderer)).1
            }
        };
        let frame = renderer.draw(&self.scenes[scene], self.flashes[scene].live(), None);
        let rgb: Vec<u8> = frame
            .pixels()
            .chunks_exact(4)
            .flat_map(|p| [p[0], p[1], p[2]])
            .collect();
        Ok(array3(py, rgb, (height, width, 3))?.into_any())
    }
}

fn array2<'py, T: numpy::Element>(
    py: Python<'py>,
    values: Vec<T>,
    shape: (usize, usize),
) -> PyResult<Bound<'py, numpy::PyArray2<T>>> {
    Array2::from_shape_vec(shape, values)
        .map(|a| a.into_pyarray(py))
        .map_err(|e| PyValueError::new_err(e.to_string()))
}

fn array3<'py, T: numpy::Element>(
    py: Python<'py>,
    values: Vec<T>,
    shape: (usize, usize, usize),
) -> PyResult<Bound<'py, numpy::PyArray3<T>>> {
    Array3::from_shape_vec(shape, values)
        .map(|a| a.into_pyarray(py))
        .map_err(|e| PyValueError::new_err(e.to_string()))
}

/// Neighbourhoods of cars given by position and velocity (`n × 2` each, metres and m/s):
/// for every car the others within `radius`, nearest first (ties by index), as the
/// simulator ships them, and their S_N features. Returns ((offsets `n + 1`, ids), features
/// `n × 5`). The MetaDrive actor computes its fragments' neighbours with it.
#[pyfunction]
fn neighbourhoods<'py>(
    py: Python<'py>,
    positions: PyReadonlyArray2<'py, f32>,
    velocities: PyReadonlyArray2<'py, f32>,
    radius: f32,
) -> PyResult<(Csr<'py>, Bound<'py, numpy::PyArray2<f32>>)> {
    let shape = positions.shape().to_vec();
    if shape.len() != 2 || shape[1] != 2 || velocities.shape() != shape.as_slice() {
        return Err(PyValueError::new_err(
            "positions and velocities must both be n × 2 arrays",
        ));
    }
    if !(radius >= 0.0 && radius.is_finite()) {
        return Err(PyValueError::new_err("radius must be a finite number >= 0"));
    }
    let p = positions.as_array();
    let v = velocities.as_array();
    let n = shape[0];
    let motion = |i: usize| Motion {
        position: [p[[i, 0]], p[[i, 1]]],
        velocity: [v[[i, 0]], v[[i, 1]]],
    };
    let mut offsets = Vec::with_capacity(n + 1);
    let mut ids = Vec::new();
    let mut features = Vec::with_capacity(n * lcf_inputs::FEATURES);
    offsets.push(0u32);
    for i in 0..n {
        let me = motion(i);
        let distance = |j: usize| {
            let o = motion(j);
            (o.position[0] - me.position[0]).hypot(o.position[1] - me.position[1])
        };
        let mut near: Vec<usize> = (0..n)
            .filter(|&j| j != i && distance(j) <= radius)
            .collect();
        near.sort_by(|&a, &b| distance(a).total_cmp(&distance(b)).then(a.cmp(&b)));
        features.extend(lcf_inputs::neighbourhood_features(
            me,
            near.iter().map(|&j| motion(j)),
            radius,
        ));
        ids.extend(near.iter().map(|&j| j as u32));
        offsets.push(ids.len() as u32);
    }
    Ok((
        (PyArray1::from_vec(py, offsets), PyArray1::from_vec(py, ids)),
        array2(py, features, (n, lcf_inputs::FEATURES))?,
    ))
}

/// The encoding of CoPO's LCF angle φ (degrees) as an observation value.
#[pyfunction]
fn phi_observation(phi_deg: f32) -> f32 {
    lcf_inputs::phi_observation(phi_deg)
}

/// `actor eval`'s report from finished episodes: `episodes` is `n × 8` (outcome code, length,
/// total reward, mean and max |accel|, collisions, energy kJ, total cost), `scene_episodes`
/// `m × 5` (steps, successes, crashes, out of road, timeouts); `meta` holds the report's
/// other fields (`policy`, `policy_version`, `training`, `scenario`, `seed`, `scenes`,
/// `episodes_requested`, `after_horizon`, `wall_s`). Returns the JSON, the CSV and the table,
/// byte for byte what `actor eval` writes and prints for the same episodes.
#[pyfunction]
fn eval_report(
    episodes: PyReadonlyArray2<'_, f64>,
    scene_episodes: PyReadonlyArray2<'_, i64>,
    collisions: u64,
    scene_steps: u64,
    sim_seconds: f64,
    meta: &str,
) -> PyResult<(String, String, String)> {
    let bad = |what: &str| PyValueError::new_err(what.to_string());
    let e = episodes.as_array();
    if e.ncols() != 8 && e.nrows() > 0 {
        return Err(bad("episodes must be an n × 8 array"));
    }
    let count = |x: f64| -> PyResult<u32> {
        (x >= 0.0 && x <= f64::from(u32::MAX) && x.fract() == 0.0)
            .then_some(x as u32)
            .ok_or_else(|| bad("episode lengths and counts must be whole numbers >= 0"))
    };
    let mut stats = Vec::with_capacity(e.nrows());
    for row in e.rows() {
        let outcome = Outcome::from_code(count(row[0])?)
            .ok_or_else(|| bad("an episode's outcome code must be 0 to 3"))?;
        stats.push(EpisodeStats {
            outcome,
            length: count(row[1])?,
            total_reward: row[2] as f32,
            mean_abs_accel: row[3] as f32,
            max_abs_accel: row[4] as f32,
            collisions: count(row[5])?,
            energy_kj: row[6] as f32,
            total_cost: row[7] as f32,
        });
    }
    let s = scene_episodes.as_array();
    if s.ncols() != 5 && s.nrows() > 0 {
        return Err(bad("scene_episodes must be an m × 5 array"));
    }
    let field = |x: i64| u32::try_from(x).map_err(|_| bad("scene episode counts must be >= 0"));
    let scenes = s
        .rows()
        .into_iter()
        .map(|r| {
            Ok(SceneEpisodeStats {
                steps: field(r[0])?,
                successes: field(r[1])?,
                crashes: field(r[2])?,
                out_of_road: field(r[3])?,
                timeouts: field(r[4])?,
            })
        })
        .collect::<PyResult<Vec<_>>>()?;
    let tally = EvalTally {
        episodes: stats,
        collisions,
        scene_steps,
        sim_seconds,
        scene_episodes: scenes,
        endings: Default::default(),
    };
    let meta: serde_json::Value =
        serde_json::from_str(meta).map_err(|e| bad(&format!("meta is not JSON: {e}")))?;
    let training: TrainingInfo = serde_json::from_value(meta["training"].clone())
        .map_err(|e| bad(&format!("meta.training: {e}")))?;
    let after_horizon = serde_json::from_value(meta["after_horizon"].clone())
        .map_err(|e| bad(&format!("meta.after_horizon: {e}")))?;
    let text = |key: &str| -> PyResult<String> {
        meta[key]
            .as_str()
            .map(str::to_string)
            .ok_or_else(|| bad(&format!("meta.{key} must be a string")))
    };
    let number = |key: &str| -> PyResult<u64> {
        meta[key]
            .as_u64()
            .ok_or_else(|| bad(&format!("meta.{key} must be a whole number >= 0")))
    };
    let seed = number("seed")?;
    let report = EvalReport {
        format: EVAL_FORMAT.to_string(),
        policy: text("policy")?,
        policy_version: number("policy_version")?,
        training,
        scenario: text("scenario")?,
        seed,
        scenes: number("scenes")? as usize,
        episodes_requested: number("episodes_requested")?,
        episodes: tally.episodes.len() as u64,
        outcomes: tally.outcomes(),
        endings: tally.endings.clone(),
        scene_steps: tally.scene_steps,
        sim_seconds: tally.sim_seconds,
        collisions: tally.collisions,
        scene_episodes: tally.scene_episodes.len() as u64,
        after_horizon,
        actions: EvalActions::Mean,
        metrics: tally.metrics(seed),
        wall_s: meta["wall_s"]
            .as_f64()
            .ok_or_else(|| bad("meta.wall_s must be a number"))?,
    };
    let json =
        serde_json::to_string_pretty(&report).map_err(|e| PyValueError::new_err(e.to_string()))?;
    Ok((json + "\n", report.to_csv(), report.to_table()))
}

/// Each value of a contiguous float32 array replaced by its tanh, in place: the policy
/// network's activation exactly as the Rust actor and learner compute it, which `torch.tanh`
/// is not to the last bit.
#[pyfunction]
fn tanh_(mut values: PyReadwriteArrayDyn<'_, f32>) -> PyResult<()> {
    let values = values
        .as_slice_mut()
        .map_err(|_| PyValueError::new_err("tanh_ needs a contiguous float32 array"))?;
    activation::tanh(values);
    Ok(())
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("ConfigError", m.py().get_type::<ConfigError>())?;
    m.add("ACTION_DIM", ACTION_DIM)?;
    m.add("LCF_FEATURES", lcf_inputs::FEATURES)?;
    m.add(
        "OBS_LAYOUT_VERSION",
        junction_core::spec::OBS_LAYOUT_VERSION,
    )?;
    m.add(
        "SHIPPED_SCENARIOS",
        scenarios::SHIPPED
            .iter()
            .map(|(n, _)| *n)
            .collect::<Vec<_>>(),
    )?;
    m.add_class::<Scenario>()?;
    m.add_class::<VectorEnv>()?;
    m.add_function(wrap_pyfunction!(load_scenario, m)?)?;
    m.add_function(wrap_pyfunction!(scenario_from_toml, m)?)?;
    m.add_function(wrap_pyfunction!(neighbourhoods, m)?)?;
    m.add_function(wrap_pyfunction!(phi_observation, m)?)?;
    m.add_function(wrap_pyfunction!(eval_report, m)?)?;
    m.add_function(wrap_pyfunction!(tanh_, m)?)?;
    Ok(())
}
