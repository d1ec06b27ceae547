//! TensorBoard event files in the run directory, so `tensorboard --logdir runs/` shows a run
//! while it trains, as researchers are used to from Stable-Baselines3, RLlib, Sample Factory
//! and CleanRL. The scalars are the values of each `progress.jsonl` line ([`Scalars::of`]),
//! written at the same moment, so the two agree; the step is the agent-steps consumed.
//!
//! The file format is TensorFlow's: TFRecord framing (little-endian length, its masked
//! CRC32C, the data, its masked CRC32C) of `tensorflow.Event` protobufs, the first holding
//! the file version. The few messages needed are defined here with prost (field numbers from
//! TensorFlow's `event.proto` and `summary.proto`).

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use prost::Message;

use junction_common::lcf::NEIGHBOUR_BUCKETS;
use junction_core::config::{AlgoKind, RunConfig, SafetyMode};

use super::progress::ProgressLine;

/// What every event file starts with (TensorFlow's current event format).
const FILE_VERSION: &str = "brain.Event:2";

#[derive(Clone, PartialEq, prost::Message)]
pub struct Event {
    #[prost(double, tag = "1")]
    pub wall_time: f64,
    #[prost(int64, tag = "2")]
    pub step: i64,
    #[prost(oneof = "EventWhat", tags = "3, 5")]
    pub what: Option<EventWhat>,
}

#[derive(Clone, PartialEq, prost::Oneof)]
pub enum EventWhat {
    #[prost(string, tag = "3")]
    FileVersion(String),
    #[prost(message, tag = "5")]
    Summary(Summary),
}

#[derive(Clone, PartialEq, prost::Message)]
pub struct Summary {
    #[prost(message, repeated, tag = "1")]
    pub value: Vec<SummaryValue>,
}

/// `Summary.Value` with the one member of its `value` oneof used here. Optional, so that a
/// value of 0 is still written (proto3 drops plain fields at their default, and TensorBoard
/// skips a value whose oneof is unset).
#[derive(Clone, PartialEq, prost::Message)]
pub struct SummaryValue {
    #[prost(string, tag = "1")]
    pub tag: String,
    #[prost(float, optional, tag = "2")]
    pub simple_value: Option<f32>,
}

#[derive(Debug, thiserror::Error)]
#[error("TensorBoard event file {path}: {source}")]
pub struct TensorBoardError {
    path: PathBuf,
    source: std::io::Error,
}

/// TFRecord's checksum: CRC32C, rotated and offset so that a CRC of data holding CRCs is
/// not degenerate.
fn masked_crc(data: &[u8]) -> u32 {
    let crc = crc32c::crc32c(data);
    crc.rotate_right(15).wrapping_add(0xa282_ead8)
}

/// One TFRecord: length, masked CRC of the length, data, masked CRC of the data.
fn write_record(out: &mut impl Write, data: &[u8]) -> std::io::Result<()> {
    let length = (data.len() as u64).to_le_bytes();
    out.write_all(&length)?;
    out.write_all(&masked_crc(&length).to_le_bytes())?;
    out.write_all(data)?;
    out.write_all(&masked_crc(data).to_le_bytes())
}

/// An event file being appended to; every [`EventWriter::scalars`] is flushed at once so
/// TensorBoard sees it while the run goes on.
pub struct EventWriter {
    file: BufWriter<File>,
    path: PathBuf,
}

impl EventWriter {
    /// Creates `dir/events.out.tfevents.<unix seconds>.<host>.<pid>` (the name TensorBoard
    /// looks for; a resumed run adds a file of its own) and writes the file version.
    pub fn create(dir: &Path, unix_s: f64) -> Result<EventWriter, TensorBoardError> {
        let path = dir.join(format!(
            "events.out.tfevents.{}.{}.{}",
            unix_s as u64,
            hostname(),
            std::process::id()
        ));
        let file = File::create(&path).map_err(|source| TensorBoardError {
            path: path.clone(),
            source,
        })?;
        let mut writer = EventWriter {
            file: BufWriter::new(file),
            path,
        };
        writer.write(&Event {
            wall_time: unix_s,
            step: 0,
            what: Some(EventWhat::FileVersion(FILE_VERSION.into())),
        })?;
        Ok(writer)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// One event holding every `(tag, value)` at `step`.
    pub fn scalars(
        &mut self,
        step: u64,
        wall_time: f64,
        values: &[(String, f64)],
    ) -> Result<(), TensorBoardError> {
        let summary = Summary {
            value: values
                .iter()
                .map(|(tag, value)| SummaryValue {
                    tag: tag.clone(),
                    simple_value: Some(*value as f32),
                })
                .collect(),
        };
        self.write(&Event {
            wall_time,
            step: i64::try_from(step).unwrap_or(i64::MAX),
            what: Some(EventWhat::Summary(summary)),
        })
    }

    fn write(&mut self, event: &Event) -> Result<(), TensorBoardError> {
        write_record(&mut self.file, &event.encode_to_vec())
            .and_then(|()| self.file.flush())
            .map_err(|source| TensorBoardError {
                path: self.path.clone(),
                source,
            })
    }
}

/// The host name, as TensorFlow puts it in event file names ("localhost" if unknown).
fn hostname() -> String {
    let mut buffer = [0u8; 256];
    // SAFETY: gethostname writes at most `len` bytes into the buffer we own.
    let ok = unsafe { libc::gethostname(buffer.as_mut_ptr().cast(), buffer.len()) } == 0;
    let end = buffer.iter().position(|&b| b == 0).unwrap_or(buffer.len());
    match std::str::from_utf8(&buffer[..end]) {
        Ok(name) if ok && !name.is_empty() => name.replace(['/', '.'], "-"),
        _ => "localhost".into(),
    }
}

/// Which scalars a run has: those of its algorithm and options only, so TensorBoard shows no
/// flat zero lines for things the run does not do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Scalars {
    dqn: bool,
    kl_penalty: bool,
    lagrangian: bool,
}

impl Scalars {
    pub fn new(config: &RunConfig) -> Scalars {
        let dqn = config.learner.algo == AlgoKind::Dqn;
        Scalars {
            dqn,
            kl_penalty: !dqn && config.ppo.kl_coef > 0.0,
            lagrangian: !dqn && config.safety.mode == SafetyMode::Lagrangian,
        }
    }

    /// The tags and values of one progress line, sectioned as SB3 does (`rollout/`,
    /// `train/`, `time/`) plus `lcf/`: the driving metrics of each success definition once
    /// its window holds an episode, the update's diagnostics once there was one.
    pub fn of(&self, line: &ProgressLine) -> Vec<(String, f64)> {
        let mut out: Vec<(String, f64)> = Vec::new();
        let mut put = |tag: &str, value: f64| out.push((tag.to_string(), value));
        put("time/agent_steps_per_s", line.agent_steps_per_s);
        let w = &line.window;
        if w.episodes > 0 {
            put("rollout/success_rate", w.success_rate);
            put("rollout/crash_rate", w.crash_rate);
            put("rollout/out_of_road_rate", w.out_of_road_rate);
            put("rollout/timeout_rate", w.timeout_rate);
            put("rollout/ep_rew_mean", w.mean_reward);
            put("rollout/ep_rew_max", w.max_reward);
            put("rollout/ep_len_mean", w.mean_length);
            put("rollout/ep_len_max", f64::from(w.max_length));
            put("rollout/collisions_per_s", w.collisions_per_s);
        }
        let s = &line.scene_window;
        if s.scene_episodes > 0 {
            put("rollout/success_rate_metadrive", s.success_rate);
            put("rollout/crash_rate_metadrive", s.crash_rate);
            put("rollout/out_of_road_rate_metadrive", s.out_of_road_rate);
            put("rollout/timeout_rate_metadrive", s.timeout_rate);
        }
        if let Some(u) = &line.update {
            put("train/policy_lag_mean", u.lag_mean);
            put("train/policy_lag_max", u.lag_max as f64);
            put("train/grad_norm", u.grad_norm);
            put("train/learning_rate", u.learning_rate);
            if self.dqn {
                put("train/td_loss", u.value_loss);
                put("train/q_mean", u.q_mean);
                put("rollout/exploration_rate", u.epsilon);
            } else {
                put("train/policy_loss", u.policy_loss);
                put("train/value_loss", u.value_loss);
                put("train/entropy", u.entropy);
                put("train/approx_kl", u.approx_kl);
                put("train/clip_fraction", u.clip_fraction);
                put("train/explained_variance", u.explained_variance);
            }
            if self.kl_penalty {
                put("train/kl", u.kl);
                put("train/kl_coef", u.kl_coef);
            }
            if self.lagrangian {
                put("train/lagrange_multiplier", u.lagrange_multiplier);
            }
        }
        if let Some(lcf) = &line.lcf {
            put("lcf/phi_mean_deg", lcf.mean_deg);
            put("lcf/phi_std_deg", lcf.std_deg);
            for bucket in NEIGHBOUR_BUCKETS {
                if let Some(&phi) = lcf.phi_deg_by_neighbours.get(bucket) {
                    put(&format!("lcf/phi_deg_neighbours_{bucket}"), phi);
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::telemetry::progress::{LcfProgress, UpdateProgress};

    /// Reads the records back, checking both checksums of each.
    fn read_records(bytes: &[u8]) -> Vec<Vec<u8>> {
        let mut records = Vec::new();
        let mut rest = bytes;
        while !rest.is_empty() {
            let (length, tail) = rest.split_at(8);
            let crc = u32::from_le_bytes(tail[..4].try_into().unwrap());
            assert_eq!(crc, masked_crc(length), "length checksum");
            let n = u64::from_le_bytes(length.try_into().unwrap()) as usize;
            let (data, tail) = tail[4..].split_at(n);
            let crc = u32::from_le_bytes(tail[..4].try_into().unwrap());
            assert_eq!(crc, masked_crc(data), "data checksum");
            records.push(data.to_vec());
            rest = &tail[4..];
        }
        records
    }

    #[test]
    fn masked_crc_matches_tensorflows() {
        // The CRC32C of "123456789" is 0xe3069283; TensorFlow's crc32c::Mask of it,
        // ((crc >> 15) | (crc << 17)) + 0xa282ead8, is 0xc78ab0e5.
        assert_eq!(masked_crc(b"123456789"), 0xc78a_b0e5);
    }

    #[test]
    fn an_event_file_holds_the_version_then_the_scalars_zeros_included() {
        let dir = std::env::temp_dir().join(format!("junction-tb-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mut writer = EventWriter::create(&dir, 1.5e9).unwrap();
        let name = writer
            .path()
            .file_name()
            .unwrap()
            .to_string_lossy()
            .to_string();
        assert!(
            name.starts_with("events.out.tfevents.1500000000."),
            "{name}"
        );
        let values = [("a/x".to_string(), 0.25), ("a/zero".to_string(), 0.0)];
        writer.scalars(1234, 1.5e9 + 1.0, &values).unwrap();
        let records = read_records(&std::fs::read(writer.path()).unwrap());
        std::fs::remove_dir_all(&dir).unwrap();
        assert_eq!(records.len(), 2);
        let first = Event::decode(records[0].as_slice()).unwrap();
        assert_eq!(
            first.what,
            Some(EventWhat::FileVersion(FILE_VERSION.into()))
        );
        let second = Event::decode(records[1].as_slice()).unwrap();
        assert_eq!((second.step, second.wall_time), (1234, 1.5e9 + 1.0));
        let Some(EventWhat::Summary(summary)) = second.what else {
            panic!("no summary: {second:?}");
        };
        let got: Vec<(&str, Option<f32>)> = summary
            .value
            .iter()
            .map(|v| (v.tag.as_str(), v.simple_value))
            .collect();
        assert_eq!(got, [("a/x", Some(0.25)), ("a/zero", Some(0.0))]);
    }

    fn tags(scalars: &Scalars, line: &ProgressLine) -> Vec<String> {
        scalars.of(line).into_iter().map(|(tag, _)| tag).collect()
    }

    #[test]
    fn each_run_gets_the_scalars_of_its_algorithm_and_options() {
        let mut line = ProgressLine::default();
        let ppo = Scalars {
            dqn: false,
            kl_penalty: false,
            lagrangian: false,
        };
        assert_eq!(tags(&ppo, &line), ["time/agent_steps_per_s"]);
        line.window.episodes = 3;
        line.window.success_rate = 0.5;
        line.scene_window.scene_episodes = 1;
        line.update = Some(UpdateProgress {
            approx_kl: 0.02,
            value_loss: 1.5,
            ..Default::default()
        });
        line.lcf = Some(LcfProgress {
            phi_deg_by_neighbours: [("3-5".to_string(), 12.0)].into(),
            ..Default::default()
        });
        let values = ppo.of(&line);
        let value = |tag: &str| values.iter().find(|(t, _)| t == tag).map(|(_, v)| *v);
        assert_eq!(value("rollout/success_rate"), Some(0.5));
        assert_eq!(value("train/approx_kl"), Some(0.02));
        assert_eq!(value("train/value_loss"), Some(1.5));
        assert_eq!(value("lcf/phi_deg_neighbours_3-5"), Some(12.0));
        assert!(value("rollout/success_rate_metadrive").is_some());
        assert!(value("train/td_loss").is_none() && value("train/kl_coef").is_none());
        assert!(value("lcf/phi_deg_neighbours_0").is_none());

        let dqn = Scalars {
            dqn: true,
            kl_penalty: false,
            lagrangian: false,
        };
        let values = dqn.of(&line);
        let value = |tag: &str| values.iter().find(|(t, _)| t == tag).map(|(_, v)| *v);
        assert_eq!(value("train/td_loss"), Some(1.5));
        assert!(value("rollout/exploration_rate").is_some());
        assert!(value("train/approx_kl").is_none() && value("train/value_loss").is_none());

        let safe = Scalars {
            dqn: false,
            kl_penalty: true,
            lagrangian: true,
        };
        let all = tags(&safe, &line);
        for tag in ["train/kl", "train/kl_coef", "train/lagrange_multiplier"] {
            assert!(all.iter().any(|t| t == tag), "{tag} missing from {all:?}");
        }
    }
}
