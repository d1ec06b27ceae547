//! `actor render`: one episode of the pure simulator, driven by the scripted autopilot or by a
//! checkpoint's policy (its deterministic action: a Gaussian's mean, a Q-policy's greedy grid
//! point, so a replay is deterministic), drawn frame by frame
//! and written as an animated GIF (or a video: `crate::video`) and optionally one PNG per frame.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use anyhow::{Context, bail, ensure};
use rand::RngCore;

use junction_common::any_policy;
use junction_common::lcf::LcfDistribution;
use junction_common::policy::{Policy, PolicyMeta};
use junction_core::config::ScenarioConfig;
use junction_core::episode::Outcome;
use junction_core::lcf_inputs;
use junction_core::spec::{ACTION_DIM, OBS_LAYOUT_VERSION};

use crate::lcf_column::blob_distribution;
use junction_sim::Scene;
use junction_sim::autopilot::{CRUISE_SPEED_MPS, autopilot_actions};
use junction_sim::render::{Flashes, Frame, Renderer};

/// The file holding a checkpoint's policy weights (see the learner's checkpoint layout).
const POLICY_FILE: &str = "policy.safetensors";
/// Checkpoint directories are named `ckpt-<version>`.
const CHECKPOINT_PREFIX: &str = "ckpt-";
/// Steps a finished car stays marked (at least one frame is shown whatever `--every`).
const FLASH_STEPS: u64 = 5;
/// Speed of NeuQuant colour reduction for frames with more than 256 colours (1 best, 30
/// fastest); the renderer's flat colours rarely need it.
const QUANTISE_SPEED: i32 = 10;

/// Who chooses the actions.
pub enum Driver {
    /// The scripted pure-pursuit driver of `actor bench`.
    Autopilot,
    /// A trained policy's deterministic action for every agent.
    Policy(PolicyDriver),
}

/// A decoded policy and what it observes beyond the scene: a CoPO policy sees the mean angle
/// μ of its LCF distribution for every agent, the deterministic counterpart of each agent
/// drawing its own φ as in training.
pub struct PolicyDriver {
    pub policy: Box<dyn Policy>,
    pub lcf: Option<LcfDistribution>,
}

impl Driver {
    /// Fills `out` with `[steer, throttle_brake]` for every slot (zeros for empty ones): a
    /// policy's deterministic action, or, given `explore`, a draw from its distribution (as
    /// actors act in training) with every random choice taken from `explore`.
    pub fn actions(
        &self,
        scene: &Scene,
        out: &mut [f32],
        explore: Option<&mut dyn RngCore>,
    ) -> anyhow::Result<()> {
        let policy = match self {
            Driver::Autopilot => {
                autopilot_actions(scene, CRUISE_SPEED_MPS, out);
                return Ok(());
            }
            Driver::Policy(driver) => driver,
        };
        out.fill(0.0);
        let obs_dim = scene.obs_dim();
        let slots: Vec<usize> = (0..scene.slots()).filter(|&s| scene.alive()[s]).collect();
        if slots.is_empty() {
            return Ok(());
        }
        let phi = policy.lcf.map(|d| lcf_inputs::phi_observation(d.mean_deg));
        let mut batch = Vec::with_capacity(slots.len() * policy.policy.obs_dim());
        for &slot in &slots {
            batch.extend_from_slice(&scene.observations()[slot * obs_dim..(slot + 1) * obs_dim]);
            batch.extend(phi);
        }
        let actions = match explore {
            Some(rng) => policy
                .policy
                .sample(&batch, rng)
                .map(|(actions, _)| actions),
            None => policy.policy.deterministic(&batch),
        }
        .context("policy inference")?;
        for (row, &slot) in slots.iter().enumerate() {
            out[slot * ACTION_DIM..(slot + 1) * ACTION_DIM]
                .copy_from_slice(&actions[row * ACTION_DIM..(row + 1) * ACTION_DIM]);
        }
        Ok(())
    }
}

/// A checkpoint's policy, ready to drive.
pub struct LoadedPolicy {
    pub driver: Driver,
    /// The policy file it was read from.
    pub file: PathBuf,
    /// The policy version (learner updates) it was saved at.
    pub version: u64,
}

/// The driver for `--checkpoint PATH` (a checkpoint or run directory, or a policy file) on
/// `scenario`: the one place a command turns a checkpoint into something that acts.
pub fn policy_driver(path: &Path, scenario: &ScenarioConfig) -> anyhow::Result<LoadedPolicy> {
    let file = policy_file(path)?;
    let bytes = std::fs::read(&file).with_context(|| format!("reading {}", file.display()))?;
    let (driver, meta) = load_policy(&bytes, scenario)
        .with_context(|| format!("loading the policy in {}", file.display()))?;
    Ok(LoadedPolicy {
        driver: Driver::Policy(driver),
        file,
        version: meta.version,
    })
}

/// `policy.safetensors` of a checkpoint directory, of the newest checkpoint of a run directory
/// (`<run>/checkpoints/ckpt-N/`) or of a checkpoints directory, or `path` itself if it is a file.
pub fn policy_file(path: &Path) -> anyhow::Result<PathBuf> {
    if path.is_file() {
        return Ok(path.to_path_buf());
    }
    if path.join(POLICY_FILE).is_file() {
        return Ok(path.join(POLICY_FILE));
    }
    let checkpoints = if path.join("checkpoints").is_dir() {
        path.join("checkpoints")
    } else {
        path.to_path_buf()
    };
    let entries = std::fs::read_dir(&checkpoints)
        .with_context(|| format!("reading checkpoint directory {}", checkpoints.display()))?;
    let newest = entries
        .flatten()
        .filter_map(|entry| {
            let name = entry.file_name().to_string_lossy().into_owned();
            let version: u64 = name.strip_prefix(CHECKPOINT_PREFIX)?.parse().ok()?;
            let file = entry.path().join(POLICY_FILE);
            file.is_file().then_some((version, file))
        })
        .max_by_key(|(version, _)| *version);
    match newest {
        Some((_, file)) => Ok(file),
        None => bail!(
            "{} holds no {POLICY_FILE}, nor any {CHECKPOINT_PREFIX}N/{POLICY_FILE}",
            path.display()
        ),
    }
}

/// Decodes a policy blob and checks it was trained on this scenario's observations (and, for
/// CoPO, its LCF angle).
pub fn load_policy(
    bytes: &[u8],
    scenario: &ScenarioConfig,
) -> anyhow::Result<(PolicyDriver, PolicyMeta)> {
    let (policy, meta) =
        any_policy::decode(bytes, tch::Device::Cpu).context("decoding policy weights")?;
    let lcf = blob_distribution(bytes).context("reading the policy's LCF distribution")?;
    let columns = lcf.map_or(0, |_| LcfDistribution::OBS_COLUMNS);
    ensure!(
        meta.obs_layout_version == OBS_LAYOUT_VERSION,
        "the policy (v{}) was trained on observation layout {}, this actor produces layout {}",
        meta.version,
        meta.obs_layout_version,
        OBS_LAYOUT_VERSION
    );
    ensure!(
        policy.obs_dim() == scenario.obs_dim() + columns,
        "the policy (v{}) expects {} observation values, but scenario {:?} produces {} \
         ({} lidar beams){}",
        meta.version,
        policy.obs_dim(),
        scenario.name,
        scenario.obs_dim(),
        scenario.sensors.lidar_beams,
        if columns > 0 {
            " and CoPO's LCF angle one more"
        } else {
            ""
        }
    );
    ensure!(
        policy.action_dim() == ACTION_DIM,
        "the policy (v{}) outputs {} action values, the simulator takes {ACTION_DIM}",
        meta.version,
        policy.action_dim()
    );
    Ok((PolicyDriver { policy, lcf }, meta))
}

/// What to simulate and draw.
#[derive(Debug, Clone)]
pub struct ReplayOptions {
    pub seed: u64,
    /// Decision steps to simulate.
    pub steps: u64,
    /// Draw every `every`-th step.
    pub every: u64,
    pub width: usize,
    pub height: usize,
    /// Draw the lidar of the agent in this slot (nothing while the slot is empty).
    pub lidar_slot: Option<usize>,
}

/// What an episode produced, printed by `actor render`.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ReplaySummary {
    pub frames: u64,
    pub steps: u64,
    /// Finished agent episodes by outcome.
    pub outcomes: BTreeMap<&'static str, u64>,
}

/// Simulates `options.steps` steps and calls `on_frame(step, frame)` for the scene at steps
/// 0, every, 2·every, … ≤ steps: frames are streamed, never all held in memory.
pub fn run(
    scenario: &ScenarioConfig,
    driver: &Driver,
    options: &ReplayOptions,
    mut on_frame: impl FnMut(u64, &Frame) -> anyhow::Result<()>,
) -> anyhow::Result<ReplaySummary> {
    ensure!(options.every > 0, "--every must be at least 1");
    let mut scene = Scene::new(scenario, options.seed).context("building the scene")?;
    let renderer = Renderer::new(scene.network(), options.width, options.height);
    let lifetime = FLASH_STEPS.max(options.every);
    let mut flashes = Flashes::new(u32::try_from(lifetime).unwrap_or(u32::MAX));
    let mut actions = vec![0.0f32; scene.slots() * ACTION_DIM];
    let mut summary = ReplaySummary {
        frames: 0,
        steps: options.steps,
        outcomes: Outcome::ALL.iter().map(|o| (o.label(), 0)).collect(),
    };
    for step in 0..=options.steps {
        if step % options.every == 0 {
            let frame = renderer.draw(&scene, flashes.live(), options.lidar_slot);
            on_frame(step, &frame).with_context(|| format!("writing the frame of step {step}"))?;
            summary.frames += 1;
        }
        if step == options.steps {
            break;
        }
        driver.actions(&scene, &mut actions, None)?;
        let result = scene.step(&actions);
        for episode in &result.finished {
            *summary
                .outcomes
                .entry(episode.stats.outcome.label())
                .or_default() += 1;
        }
        flashes.record(result);
    }
    Ok(summary)
}

/// An animated GIF written frame by frame, looping forever.
pub struct GifWriter {
    encoder: gif::Encoder<BufWriter<File>>,
    width: u16,
    height: u16,
    /// Frame duration in hundredths of a second (GIF's unit).
    delay_cs: u16,
}

impl GifWriter {
    /// `frame_seconds` is the simulated time between frames, so the GIF plays in real time.
    pub fn create(
        path: &Path,
        width: usize,
        height: usize,
        frame_seconds: f32,
    ) -> anyhow::Result<GifWriter> {
        let (Ok(w), Ok(h)) = (u16::try_from(width), u16::try_from(height)) else {
            bail!("a GIF is at most 65535 pixels wide and high, not {width}×{height}");
        };
        let file = File::create(path).with_context(|| format!("creating {}", path.display()))?;
        let mut encoder = gif::Encoder::new(BufWriter::new(file), w, h, &[])
            .with_context(|| format!("writing {}", path.display()))?;
        encoder
            .set_repeat(gif::Repeat::Infinite)
            .context("writing the GIF header")?;
        Ok(GifWriter {
            encoder,
            width: w,
            height: h,
            delay_cs: (frame_seconds * 100.0)
                .round()
                .clamp(1.0, f32::from(u16::MAX)) as u16,
        })
    }

    pub fn write(&mut self, frame: &Frame) -> anyhow::Result<()> {
        ensure!(
            (frame.width(), frame.height()) == (usize::from(self.width), usize::from(self.height)),
            "frame of {}×{} in a GIF of {}×{}",
            frame.width(),
            frame.height(),
            self.width,
            self.height
        );
        let mut gif_frame = match indexed(frame) {
            Some((palette, indices)) => {
                gif::Frame::from_palette_pixels(self.width, self.height, indices, palette, None)
            }
            None => {
                let mut rgba = frame.pixels().to_vec();
                gif::Frame::from_rgba_speed(self.width, self.height, &mut rgba, QUANTISE_SPEED)
            }
        };
        gif_frame.delay = self.delay_cs;
        self.encoder
            .write_frame(&gif_frame)
            .context("encoding a GIF frame")
    }

    /// Writes the trailer and flushes the file.
    pub fn finish(self) -> anyhow::Result<()> {
        let mut writer = self.encoder.into_inner().context("finishing the GIF")?;
        writer.flush().context("flushing the GIF")
    }
}

/// An exact palette and per-pixel indices, if the frame has at most 256 colours.
fn indexed(frame: &Frame) -> Option<(Vec<u8>, Vec<u8>)> {
    let mut index: HashMap<[u8; 3], u8> = HashMap::new();
    let mut palette = Vec::new();
    let mut indices = Vec::with_capacity(frame.width() * frame.height());
    // Runs of one colour are common: remember the last lookup.
    let mut last: Option<([u8; 3], u8)> = None;
    for px in frame.pixels().chunks_exact(4) {
        let rgb = [px[0], px[1], px[2]];
        let i = match last {
            Some((colour, i)) if colour == rgb => i,
            _ => {
                let i = match index.get(&rgb) {
                    Some(&i) => i,
                    None => {
                        let i = u8::try_from(index.len()).ok()?;
                        index.insert(rgb, i);
                        palette.extend_from_slice(&rgb);
                        i
                    }
                };
                last = Some((rgb, i));
                i
            }
        };
        indices.push(i);
    }
    Some((palette, indices))
}

/// Writes `frame` as an RGBA PNG.
pub fn write_png(path: &Path, frame: &Frame) -> anyhow::Result<()> {
    let file = File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let (Ok(w), Ok(h)) = (u32::try_from(frame.width()), u32::try_from(frame.height())) else {
        bail!("frame too large for a PNG");
    };
    let mut encoder = png::Encoder::new(BufWriter::new(file), w, h);
    encoder.set_color(png::ColorType::Rgba);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder
        .write_header()
        .with_context(|| format!("writing {}", path.display()))?;
    writer
        .write_image_data(frame.pixels())
        .with_context(|| format!("writing {}", path.display()))?;
    writer
        .finish()
        .with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use junction_common::policy::GaussianPolicy;
    use junction_common::q_policy::QPolicy;
    use junction_core::action_grid::ActionGrid;
    use junction_core::scenarios;

    /// A fresh directory under the system's temporary directory.
    fn scratch(name: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("junction-replay-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn options(steps: u64, every: u64) -> ReplayOptions {
        ReplayOptions {
            seed: 1,
            steps,
            every,
            width: 96,
            height: 64,
            lidar_slot: Some(0),
        }
    }

    #[test]
    fn gif_of_a_short_episode_decodes_to_its_frames() {
        let dir = scratch("gif");
        let scenario = scenarios::load("intersection").unwrap();
        let path = dir.join("replay.gif");
        let mut gif = GifWriter::create(&path, 96, 64, 0.3).unwrap();
        let mut steps = Vec::new();
        let summary = run(
            &scenario,
            &Driver::Autopilot,
            &options(10, 3),
            |step, frame| {
                steps.push(step);
                if step == 3 {
                    write_png(&dir.join("frame.png"), frame)?;
                }
                gif.write(frame)
            },
        )
        .unwrap();
        gif.finish().unwrap();
        assert_eq!(steps, [0, 3, 6, 9]);
        assert_eq!(summary.frames, 4);

        let mut decoder = gif::DecodeOptions::new()
            .read_info(File::open(&path).unwrap())
            .unwrap();
        assert_eq!((decoder.width(), decoder.height()), (96, 64));
        let mut frames = 0;
        while let Some(frame) = decoder.read_next_frame().unwrap() {
            assert_eq!((frame.width, frame.height, frame.delay), (96, 64, 30));
            frames += 1;
        }
        assert_eq!(frames, 4);

        let png = png::Decoder::new(std::io::BufReader::new(
            File::open(dir.join("frame.png")).unwrap(),
        ))
        .read_info()
        .unwrap();
        assert_eq!((png.info().width, png.info().height), (96, 64));
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn a_copo_policy_observes_its_mean_angle_and_needs_its_distribution() {
        let scenario = scenarios::load("tiny-straight").unwrap();
        let copo = GaussianPolicy::new(
            tch::Device::Cpu,
            scenario.obs_dim() as i64 + 1,
            2,
            &[8],
            0.0,
        );
        let distribution = LcfDistribution {
            mean_deg: 30.0,
            std_deg: 9.0,
        };
        let blob = copo
            .to_bytes_with_metadata(4, distribution.to_metadata())
            .unwrap();
        let (driver, _) = load_policy(&blob, &scenario).unwrap();
        let scene = Scene::new(&scenario, 1).unwrap();
        let mut actions = vec![0.0; scene.slots() * ACTION_DIM];
        Driver::Policy(driver)
            .actions(&scene, &mut actions, None)
            .unwrap();
        // The slot's scene observation with φ = μ appended: (30/90 + 1)/2.
        let mut row = scene.observations()[..scene.obs_dim()].to_vec();
        row.push(lcf_inputs::phi_observation(30.0));
        assert_eq!(actions[..ACTION_DIM], copo.deterministic(&row).unwrap()[..]);
        // The same network without the distribution cannot be fed.
        let Err(error) = load_policy(&copo.to_bytes(4).unwrap(), &scenario) else {
            panic!("a 92-value policy without an LCF distribution was accepted");
        };
        assert!(error.to_string().contains("observation values"), "{error}");
    }

    #[test]
    fn a_policy_drives_and_a_mismatched_one_is_refused() {
        let scenario = scenarios::load("tiny-straight").unwrap();
        let fitting =
            GaussianPolicy::new(tch::Device::Cpu, scenario.obs_dim() as i64, 2, &[8], 0.0);
        let (policy, meta) = load_policy(&fitting.to_bytes(7).unwrap(), &scenario).unwrap();
        assert_eq!(meta.version, 7);
        let summary = run(
            &scenario,
            &Driver::Policy(policy),
            &options(4, 1),
            |_, _| Ok(()),
        )
        .unwrap();
        assert_eq!(summary.frames, 5);

        let other = GaussianPolicy::new(tch::Device::Cpu, 50, 2, &[8], 0.0);
        let Err(error) = load_policy(&other.to_bytes(7).unwrap(), &scenario) else {
            panic!("a 50-value policy does not fit a 91-value scenario");
        };
        assert!(
            error.to_string().contains("expects 50 observation values"),
            "{error}"
        );
    }

    #[test]
    fn a_q_policy_drives_its_greedy_grid_points_even_when_it_explores_in_training() {
        let scenario = scenarios::load("tiny-straight").unwrap();
        let grid = ActionGrid::new(vec![-0.5, 0.0, 0.5], vec![0.0, 1.0]).unwrap();
        let mut q = QPolicy::new(
            tch::Device::Cpu,
            scenario.obs_dim() as i64,
            &[8],
            grid,
            true,
        );
        // Actors would explore on every step; a replay must not.
        q.set_epsilon(1.0);
        let blob = Policy::to_bytes(&q, 3).unwrap();
        let driver = Driver::Policy(load_policy(&blob, &scenario).unwrap().0);
        let scene = Scene::new(&scenario, 1).unwrap();
        let mut actions = vec![0.0; scene.slots() * ACTION_DIM];
        driver.actions(&scene, &mut actions, None).unwrap();
        let obs = &scene.observations()[..scene.obs_dim()];
        assert_eq!(
            &actions[..ACTION_DIM],
            q.deterministic(obs).unwrap().as_slice()
        );
        assert!(q.grid().index_of(&actions[..ACTION_DIM]).is_some());
        let frames = || {
            let mut pixels = Vec::new();
            run(&scenario, &driver, &options(30, 10), |_, frame| {
                pixels.extend_from_slice(frame.pixels());
                Ok(())
            })
            .unwrap();
            pixels
        };
        assert_eq!(frames(), frames(), "a replay is deterministic");
    }

    #[test]
    fn policy_file_finds_the_newest_complete_checkpoint() {
        let run_dir = scratch("run");
        let checkpoints = run_dir.join("checkpoints");
        for (name, with_policy) in [
            ("ckpt-0000000002", true),
            ("ckpt-0000000010", true),
            ("ckpt-0000000011", false),
            (".tmp-0000000012-1", true),
        ] {
            let dir = checkpoints.join(name);
            std::fs::create_dir_all(&dir).unwrap();
            if with_policy {
                std::fs::write(dir.join(POLICY_FILE), b"weights").unwrap();
            }
        }
        let newest = checkpoints.join("ckpt-0000000010").join(POLICY_FILE);
        assert_eq!(policy_file(&run_dir).unwrap(), newest);
        assert_eq!(policy_file(&checkpoints).unwrap(), newest);
        let older = checkpoints.join("ckpt-0000000002");
        assert_eq!(policy_file(&older).unwrap(), older.join(POLICY_FILE));
        assert_eq!(policy_file(&newest).unwrap(), newest);
        assert!(policy_file(&checkpoints.join("ckpt-0000000011")).is_err());
        assert!(policy_file(&run_dir.join("missing")).is_err());
        std::fs::remove_dir_all(run_dir).unwrap();
    }
}
