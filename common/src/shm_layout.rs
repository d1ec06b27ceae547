//! The shared-memory form of a [`RolloutFragment`]: one contiguous buffer that an actor writes
//! straight into a loaned iceoryx2 sample and the learner reads in place, with no serialiser
//! in between. A fixed header says what follows; the structure-of-arrays payload is the
//! fragment's own arrays, copied as they are.
//!
//! Layout version 2. Numbers are in the host's byte order (shared memory never leaves the
//! host); offsets in bytes:
//!
//! | offset | type | field |
//! |---|---|---|
//! | 0 | `[u8; 4]` | magic `JNCF` |
//! | 4 | u32 | layout version ([`LAYOUT_VERSION`]) |
//! | 8 | u32 | header bytes ([`HEADER_BYTES`]) |
//! | 12 | u32 | reserved, 0 |
//! | 16 | u64 | total bytes, header included |
//! | 24 | u64 | sequence |
//! | 32 | u64 | behaviour policy version |
//! | 40 | u32 × 10 | steps, agents, obs_dim, action_dim, LCF features per cell, neighbour ids, episodes, human episodes, actor id bytes, scenario bytes |
//! | 80 | f32 | simulated seconds |
//! | 84 | u32 | scene episodes |
//! | 88 | u32 × 2 | reserved, 0 |
//!
//! Then, in this order, with `cells = steps × agents`: f32 `obs[cells × obs_dim]`,
//! `actions[cells × action_dim]`, `log_probs[cells]`, `rewards[cells]`, `costs[cells]`,
//! `bootstrap_obs[agents × obs_dim]`, `lcf_features[cells × features]`; u32
//! `neighbour_offsets[cells + 1]`, `neighbour_ids[n]`; episodes and human episodes, 8 words
//! each (outcome u32, length u32, total reward f32, mean |accel| f32, max |accel| f32,
//! collisions u32, energy kJ f32, total cost f32); scene episodes, 5 u32 each (steps,
//! successes, crashes, out of road, timeouts); bytes `dones[cells]`, `alive[cells]` (0 or 1),
//! the actor id and the scenario name (UTF-8); zeros up to a multiple of 8 bytes.
//!
//! Version 2 added the scene episodes (version 1 had three reserved words at offset 84).
//!
//! The decoder trusts nothing: it checks the magic, the version, that the header's sizes are
//! within [`crate::fragment`]'s bounds and add up to exactly the buffer's length, that reserved
//! and padding bytes are 0, and then runs [`RolloutFragment::validate`] (NaN, flags, slot
//! invariants); whatever it accepts encodes back to the same bytes. Change the layout only with
//! a new [`LAYOUT_VERSION`].

use std::mem::MaybeUninit;

use crate::fragment::{FragmentError, RolloutFragment, flags};
use junction_core::episode::{EpisodeStats, Outcome, SceneEpisodeStats};
use junction_core::lcf_inputs;
use junction_core::spec::MAX_NAME_BYTES;

pub const MAGIC: [u8; 4] = *b"JNCF";
/// Version of this layout; a learner refuses (and counts) fragments of any other.
pub const LAYOUT_VERSION: u32 = 2;
pub const HEADER_BYTES: usize = 96;
/// Words per episode record.
const EPISODE_WORDS: usize = 8;
/// Words per scene-episode record.
const SCENE_EPISODE_WORDS: usize = 5;

/// Why a buffer was refused; [`LayoutError::reason`] is the bounded label used in metrics.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LayoutError {
    #[error("not a fragment in the shared-memory layout: {0}")]
    Malformed(String),
    #[error(
        "shared-memory layout version {got} is not supported (this build reads version {expected})"
    )]
    Version { got: u32, expected: u32 },
    #[error(transparent)]
    Fragment(#[from] FragmentError),
    #[error("the fragment needs a buffer of {needed} bytes, not {got}")]
    BufferSize { needed: usize, got: usize },
}

impl LayoutError {
    pub fn reason(&self) -> &'static str {
        match self {
            LayoutError::Malformed(_) => "decode",
            LayoutError::Version { .. } => "version",
            LayoutError::Fragment(e) => e.reason(),
            LayoutError::BufferSize { .. } => "shape",
        }
    }
}

/// The header's counts: everything that sizes the payload.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Counts {
    steps: usize,
    agents: usize,
    obs_dim: usize,
    action_dim: usize,
    features: usize,
    neighbour_ids: usize,
    episodes: usize,
    human_episodes: usize,
    actor_id_bytes: usize,
    scenario_bytes: usize,
    scene_episodes: usize,
}

impl Counts {
    fn of(f: &RolloutFragment) -> Self {
        Counts {
            steps: f.steps,
            agents: f.agents,
            obs_dim: f.obs_dim,
            action_dim: f.action_dim,
            features: lcf_inputs::FEATURES,
            neighbour_ids: f.neighbour_ids.len(),
            episodes: f.episodes.len(),
            human_episodes: f.human_episodes.len(),
            actor_id_bytes: f.actor_id.len(),
            scenario_bytes: f.scenario.len(),
            scene_episodes: f.scene_episodes.len(),
        }
    }

    /// Total bytes of a buffer with these counts; `None` if that does not fit in a `usize`.
    fn total_bytes(&self) -> Option<usize> {
        let cells = self.steps.checked_mul(self.agents)?;
        let words = [
            cells.checked_mul(self.obs_dim)?,
            cells.checked_mul(self.action_dim)?,
            cells.checked_mul(3)?,
            self.agents.checked_mul(self.obs_dim)?,
            cells.checked_mul(self.features)?,
            cells.checked_add(1)?,
            self.neighbour_ids,
            self.episodes.checked_mul(EPISODE_WORDS)?,
            self.human_episodes.checked_mul(EPISODE_WORDS)?,
            self.scene_episodes.checked_mul(SCENE_EPISODE_WORDS)?,
        ]
        .into_iter()
        .try_fold(0usize, usize::checked_add)?;
        let bytes = cells
            .checked_mul(2)?
            .checked_add(self.actor_id_bytes)?
            .checked_add(self.scenario_bytes)?;
        HEADER_BYTES
            .checked_add(words.checked_mul(4)?)?
            .checked_add(bytes)?
            .checked_next_multiple_of(8)
    }
}

/// Bytes the shared-memory form of `fragment` takes: the size of the sample to loan.
pub fn encoded_len(fragment: &RolloutFragment) -> Result<usize, LayoutError> {
    fragment.check_shape(None)?;
    for (field, name) in [
        ("actor_id", &fragment.actor_id),
        ("scenario", &fragment.scenario),
    ] {
        if name.len() > MAX_NAME_BYTES {
            return Err(FragmentError::Shape(format!(
                "{field} has {} bytes (at most {MAX_NAME_BYTES})",
                name.len()
            ))
            .into());
        }
    }
    Counts::of(fragment)
        .total_bytes()
        .ok_or_else(|| FragmentError::Shape("the fragment is too large to address".into()).into())
}

/// Bytes of a fragment of these dimensions in which every slot lists every other slot as a
/// neighbour at every step and finishes one episode, with 64-byte names: what a publisher
/// reserves per sample (a larger fragment makes it grow; 0 if the sizes are absurd).
pub fn capacity_hint(steps: usize, agents: usize, obs_dim: usize, action_dim: usize) -> usize {
    let cells = steps.saturating_mul(agents);
    Counts {
        steps,
        agents,
        obs_dim,
        action_dim,
        features: lcf_inputs::FEATURES,
        neighbour_ids: cells.saturating_mul(agents.saturating_sub(1)),
        episodes: agents,
        human_episodes: 0,
        actor_id_bytes: 64,
        scenario_bytes: 64,
        scene_episodes: 1,
    }
    .total_bytes()
    .unwrap_or(0)
}

/// Writes `fragment` into `out`, which must be exactly [`encoded_len`] bytes (a loaned sample);
/// on `Ok` every byte of `out` has been written.
pub fn encode_into(
    fragment: &RolloutFragment,
    out: &mut [MaybeUninit<u8>],
) -> Result<(), LayoutError> {
    let needed = encoded_len(fragment)?;
    if out.len() != needed {
        return Err(LayoutError::BufferSize {
            needed,
            got: out.len(),
        });
    }
    let counts = Counts::of(fragment);
    let mut w = Writer { out, at: 0 };
    w.bytes(&MAGIC);
    w.u32(LAYOUT_VERSION);
    w.u32(HEADER_BYTES as u32);
    w.u32(0);
    w.u64(needed as u64);
    w.u64(fragment.sequence);
    w.u64(fragment.behaviour_version);
    // check_shape and MAX_NAME_BYTES bound every count far below u32::MAX, except the
    // neighbour and episode counts, which the total size bounds (a fragment over 16 GiB could
    // not be loaned).
    for count in [
        counts.steps,
        counts.agents,
        counts.obs_dim,
        counts.action_dim,
        counts.features,
        counts.neighbour_ids,
        counts.episodes,
        counts.human_episodes,
        counts.actor_id_bytes,
        counts.scenario_bytes,
    ] {
        w.u32(u32::try_from(count).map_err(|_| {
            FragmentError::Shape(format!("a count of {count} does not fit the header"))
        })?);
    }
    w.bytes(&fragment.sim_seconds.to_ne_bytes());
    w.u32(
        u32::try_from(counts.scene_episodes)
            .map_err(|_| FragmentError::Shape("too many scene episodes for the header".into()))?,
    );
    w.bytes(&[0; 8]);
    for values in [
        &fragment.obs,
        &fragment.actions,
        &fragment.log_probs,
        &fragment.rewards,
        &fragment.costs,
        &fragment.bootstrap_obs,
        &fragment.lcf_features,
    ] {
        w.bytes(bytemuck::cast_slice(values));
    }
    w.bytes(bytemuck::cast_slice(&fragment.neighbour_offsets));
    w.bytes(bytemuck::cast_slice(&fragment.neighbour_ids));
    for e in fragment.episodes.iter().chain(&fragment.human_episodes) {
        w.u32(e.outcome as u32);
        w.u32(e.length);
        for v in [e.total_reward, e.mean_abs_accel, e.max_abs_accel] {
            w.bytes(&v.to_ne_bytes());
        }
        w.u32(e.collisions);
        for v in [e.energy_kj, e.total_cost] {
            w.bytes(&v.to_ne_bytes());
        }
    }
    for e in &fragment.scene_episodes {
        for v in [e.steps, e.successes, e.crashes, e.out_of_road, e.timeouts] {
            w.u32(v);
        }
    }
    w.bytes(bytemuck::cast_slice(&fragment.dones));
    w.bytes(bytemuck::cast_slice(&fragment.alive));
    w.bytes(fragment.actor_id.as_bytes());
    w.bytes(fragment.scenario.as_bytes());
    let padding = needed - w.at;
    w.bytes(&[0; 8][..padding]);
    Ok(())
}

/// The shared-memory form of `fragment` in a new buffer (tests, benchmarks, fuzzing; the
/// transport encodes into the loaned sample with [`encode_into`]).
pub fn encode(fragment: &RolloutFragment) -> Result<Vec<u8>, LayoutError> {
    let len = encoded_len(fragment)?;
    let mut buffer = Vec::with_capacity(len);
    encode_into(fragment, &mut buffer.spare_capacity_mut()[..len])?;
    // SAFETY: encode_into returned Ok, so it wrote all `len` bytes of the spare capacity.
    unsafe { buffer.set_len(len) };
    Ok(buffer)
}

/// Sequential writer over the loaned bytes. Its callers size `out` with [`encoded_len`] from
/// the same counts they write, so a write past the end is a bug in this file, not bad input.
struct Writer<'a> {
    out: &'a mut [MaybeUninit<u8>],
    at: usize,
}

impl Writer<'_> {
    fn bytes(&mut self, bytes: &[u8]) {
        self.out[self.at..self.at + bytes.len()].write_copy_of_slice(bytes);
        self.at += bytes.len();
    }

    fn u32(&mut self, v: u32) {
        self.bytes(&v.to_ne_bytes());
    }

    fn u64(&mut self, v: u64) {
        self.bytes(&v.to_ne_bytes());
    }
}

/// Reads and validates a fragment from its shared-memory form; `expected_dims` pins
/// (obs_dim, action_dim) as in [`RolloutFragment::validate`].
pub fn decode(
    bytes: &[u8],
    expected_dims: Option<(usize, usize)>,
) -> Result<RolloutFragment, LayoutError> {
    let malformed = |msg: String| Err(LayoutError::Malformed(msg));
    if bytes.len() < HEADER_BYTES {
        return malformed(format!(
            "{} bytes cannot hold the {HEADER_BYTES}-byte header",
            bytes.len()
        ));
    }
    let mut r = Reader { bytes, at: 0 };
    if r.take(4)? != MAGIC {
        return malformed("wrong magic bytes".into());
    }
    let version = r.u32()?;
    if version != LAYOUT_VERSION {
        return Err(LayoutError::Version {
            got: version,
            expected: LAYOUT_VERSION,
        });
    }
    let header_bytes = r.u32()?;
    if header_bytes as usize != HEADER_BYTES {
        return malformed(format!(
            "header of {header_bytes} bytes, layout {LAYOUT_VERSION} has {HEADER_BYTES}"
        ));
    }
    let reserved = r.u32()?;
    let total = r.u64()?;
    if total != bytes.len() as u64 {
        return malformed(format!(
            "the header announces {total} bytes, the buffer holds {} (truncated or padded)",
            bytes.len()
        ));
    }
    let sequence = r.u64()?;
    let behaviour_version = r.u64()?;
    let mut count = || r.u32().map(|v| v as usize);
    let mut counts = Counts {
        steps: count()?,
        agents: count()?,
        obs_dim: count()?,
        action_dim: count()?,
        features: count()?,
        neighbour_ids: count()?,
        episodes: count()?,
        human_episodes: count()?,
        actor_id_bytes: count()?,
        scenario_bytes: count()?,
        scene_episodes: 0,
    };
    let sim_seconds = r.f32()?;
    counts.scene_episodes = r.u32()? as usize;
    if reserved != 0 || r.take(8)?.iter().any(|&b| b != 0) {
        return malformed("reserved header bytes must be 0".into());
    }
    // The dimensions' bounds first, so no size computed below can be absurd.
    RolloutFragment::check_dims(
        (
            counts.steps,
            counts.agents,
            counts.obs_dim,
            counts.action_dim,
        ),
        expected_dims,
    )?;
    if counts.features != lcf_inputs::FEATURES {
        return Err(FragmentError::Shape(format!(
            "{} LCF features per cell, expected {}",
            counts.features,
            lcf_inputs::FEATURES
        ))
        .into());
    }
    if counts.actor_id_bytes > MAX_NAME_BYTES || counts.scenario_bytes > MAX_NAME_BYTES {
        return malformed(format!("names longer than {MAX_NAME_BYTES} bytes"));
    }
    if counts.total_bytes() != Some(bytes.len()) {
        return malformed(format!(
            "the header's sizes add up to {:?} bytes, the buffer holds {}",
            counts.total_bytes(),
            bytes.len()
        ));
    }
    let cells = counts.steps * counts.agents;
    let obs = r.f32s(cells * counts.obs_dim)?;
    let actions = r.f32s(cells * counts.action_dim)?;
    let log_probs = r.f32s(cells)?;
    let rewards = r.f32s(cells)?;
    let costs = r.f32s(cells)?;
    let bootstrap_obs = r.f32s(counts.agents * counts.obs_dim)?;
    let lcf_features = r.f32s(cells * counts.features)?;
    let neighbour_offsets = r.u32s(cells + 1)?;
    let neighbour_ids = r.u32s(counts.neighbour_ids)?;
    let episodes = r.episodes(counts.episodes)?;
    let human_episodes = r.episodes(counts.human_episodes)?;
    let scene_episodes = r.scene_episodes(counts.scene_episodes)?;
    let dones = flags("dones", r.take(cells)?)?;
    let alive = flags("alive", r.take(cells)?)?;
    let actor_id = r.text("actor id", counts.actor_id_bytes)?;
    let scenario = r.text("scenario", counts.scenario_bytes)?;
    if r.take(bytes.len() - r.at)?.iter().any(|&b| b != 0) {
        return malformed("padding bytes must be 0".into());
    }
    let fragment = RolloutFragment {
        actor_id,
        sequence,
        behaviour_version,
        scenario,
        steps: counts.steps,
        agents: counts.agents,
        obs_dim: counts.obs_dim,
        action_dim: counts.action_dim,
        obs,
        actions,
        log_probs,
        rewards,
        costs,
        dones,
        alive,
        bootstrap_obs,
        neighbour_offsets,
        neighbour_ids,
        lcf_features,
        episodes,
        human_episodes,
        scene_episodes,
        sim_seconds,
    };
    fragment.validate(expected_dims)?;
    Ok(fragment)
}

/// Sequential reader; every read is bounds-checked, so a lying header is an error, not a panic.
struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], LayoutError> {
        let end = self
            .at
            .checked_add(n)
            .filter(|&end| end <= self.bytes.len());
        let Some(end) = end else {
            return Err(LayoutError::Malformed(format!(
                "truncated: {n} bytes wanted at offset {}, the buffer holds {}",
                self.at,
                self.bytes.len()
            )));
        };
        let slice = &self.bytes[self.at..end];
        self.at = end;
        Ok(slice)
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], LayoutError> {
        let mut out = [0; N];
        out.copy_from_slice(self.take(N)?);
        Ok(out)
    }

    fn u32(&mut self) -> Result<u32, LayoutError> {
        self.array().map(u32::from_ne_bytes)
    }

    fn u64(&mut self) -> Result<u64, LayoutError> {
        self.array().map(u64::from_ne_bytes)
    }

    fn f32(&mut self) -> Result<f32, LayoutError> {
        self.array().map(f32::from_ne_bytes)
    }

    /// `n` values copied out of the (possibly unaligned) buffer in one go.
    fn f32s(&mut self, n: usize) -> Result<Vec<f32>, LayoutError> {
        let mut values = vec![0f32; n];
        bytemuck::cast_slice_mut::<f32, u8>(&mut values).copy_from_slice(self.take(n * 4)?);
        Ok(values)
    }

    fn u32s(&mut self, n: usize) -> Result<Vec<u32>, LayoutError> {
        let mut values = vec![0u32; n];
        bytemuck::cast_slice_mut::<u32, u8>(&mut values).copy_from_slice(self.take(n * 4)?);
        Ok(values)
    }

    fn episodes(&mut self, n: usize) -> Result<Vec<EpisodeStats>, LayoutError> {
        (0..n)
            .map(|index| {
                let code = self.u32()?;
                let outcome = Outcome::from_code(code).ok_or_else(|| {
                    FragmentError::Invariant(format!("episode {index} has unknown outcome {code}"))
                })?;
                Ok(EpisodeStats {
                    outcome,
                    length: self.u32()?,
                    total_reward: self.f32()?,
                    mean_abs_accel: self.f32()?,
                    max_abs_accel: self.f32()?,
                    collisions: self.u32()?,
                    energy_kj: self.f32()?,
                    total_cost: self.f32()?,
                })
            })
            .collect()
    }

    fn scene_episodes(&mut self, n: usize) -> Result<Vec<SceneEpisodeStats>, LayoutError> {
        (0..n)
            .map(|_| {
                Ok(SceneEpisodeStats {
                    steps: self.u32()?,
                    successes: self.u32()?,
                    crashes: self.u32()?,
                    out_of_road: self.u32()?,
                    timeouts: self.u32()?,
                })
            })
            .collect()
    }

    fn text(&mut self, what: &str, n: usize) -> Result<String, LayoutError> {
        std::str::from_utf8(self.take(n)?)
            .map(str::to_string)
            .map_err(|e| LayoutError::Malformed(format!("the {what} is not UTF-8: {e}")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fragment::tests::sample;

    fn put_u32(bytes: &mut [u8], offset: usize, v: u32) {
        bytes[offset..offset + 4].copy_from_slice(&v.to_ne_bytes());
    }

    #[test]
    fn round_trip_is_lossless_and_equals_the_protobuf_form() {
        use prost::Message;
        let fragment = sample();
        let bytes = encode(&fragment).unwrap();
        assert_eq!(bytes.len(), encoded_len(&fragment).unwrap());
        assert_eq!(bytes.len() % 8, 0);
        assert_eq!(&bytes[..4], b"JNCF");
        let via_shm = decode(&bytes, Some((4, 2))).unwrap();
        let wire = fragment.clone().into_proto().encode_to_vec();
        let via_grpc = RolloutFragment::from_proto(
            crate::proto::RolloutFragment::decode(wire.as_slice()).unwrap(),
            Some((4, 2)),
        )
        .unwrap();
        assert_eq!(via_shm, fragment);
        assert_eq!(via_shm, via_grpc);
    }

    #[test]
    fn unaligned_buffers_decode() {
        let fragment = sample();
        let bytes = encode(&fragment).unwrap();
        let mut shifted = vec![0u8; bytes.len() + 1];
        shifted[1..].copy_from_slice(&bytes);
        assert_eq!(decode(&shifted[1..], None).unwrap(), fragment);
    }

    #[test]
    fn every_truncation_is_a_clear_error() {
        let bytes = encode(&sample()).unwrap();
        for len in 0..bytes.len() {
            let err = decode(&bytes[..len], None).unwrap_err();
            assert_eq!(err.reason(), "decode", "cut at {len}: {err}");
        }
        let mut longer = bytes.clone();
        longer.extend_from_slice(&[0; 8]);
        assert_eq!(decode(&longer, None).unwrap_err().reason(), "decode");
    }

    #[test]
    fn other_versions_and_foreign_bytes_are_refused() {
        let mut bytes = encode(&sample()).unwrap();
        // Version 1 (before scene episodes) and any other are refused, not misread.
        for other in [1, LAYOUT_VERSION + 1] {
            put_u32(&mut bytes, 4, other);
            assert_eq!(
                decode(&bytes, None).unwrap_err(),
                LayoutError::Version {
                    got: other,
                    expected: LAYOUT_VERSION
                }
            );
        }
        let mut bytes = encode(&sample()).unwrap();
        bytes[0] = b'X';
        assert_eq!(decode(&bytes, None).unwrap_err().reason(), "decode");
        for reserved in [12, 90] {
            let mut bytes = encode(&sample()).unwrap();
            bytes[reserved] = 1;
            assert_eq!(decode(&bytes, None).unwrap_err().reason(), "decode");
        }
        let mut bytes = encode(&sample()).unwrap();
        let last = bytes.len() - 1; // padding: the sample's names end before it
        bytes[last] = 1;
        assert_eq!(decode(&bytes, None).unwrap_err().reason(), "decode");
        assert_eq!(decode(&[0; 200], None).unwrap_err().reason(), "decode");
    }

    #[test]
    fn absurd_header_sizes_are_refused_before_allocating() {
        // Huge dimensions fail the bounds, huge counts the length check: no allocation is
        // attempted for either (a 4 G-element Vec would abort the test).
        for (offset, value, reason) in [
            (40, u32::MAX, "shape"),  // steps
            (44, 0, "shape"),         // agents
            (48, u32::MAX, "shape"),  // obs_dim
            (56, 6, "shape"),         // LCF features per cell
            (60, u32::MAX, "decode"), // neighbour ids
            (64, u32::MAX, "decode"), // episodes
            (72, u32::MAX, "decode"), // actor id bytes
        ] {
            let mut bytes = encode(&sample()).unwrap();
            put_u32(&mut bytes, offset, value);
            let err = decode(&bytes, None).unwrap_err();
            assert_eq!(err.reason(), reason, "offset {offset}: {err}");
        }
        // Dimensions other than the run's.
        let bytes = encode(&sample()).unwrap();
        assert_eq!(decode(&bytes, Some((91, 2))).unwrap_err().reason(), "shape");
    }

    #[test]
    fn content_is_validated_like_the_protobuf_form() {
        let fragment = sample();
        let cells = fragment.steps * fragment.agents;
        let obs_start = HEADER_BYTES;
        let mut bytes = encode(&fragment).unwrap();
        bytes[obs_start + 8..obs_start + 12].copy_from_slice(&f32::NAN.to_ne_bytes());
        assert_eq!(
            decode(&bytes, None).unwrap_err(),
            LayoutError::Fragment(FragmentError::NonFinite {
                field: "obs",
                index: 2
            })
        );
        // The flag bytes start after all 4-byte words.
        let len = bytes.len();
        let text = fragment.actor_id.len() + fragment.scenario.len();
        let unpadded = HEADER_BYTES
            + 4 * (cells * (4 + 2 + 3 + 5)
                + fragment.agents * 4
                + cells
                + 1
                + fragment.neighbour_ids.len()
                + 8 * 2
                + 5 * fragment.scene_episodes.len())
            + 2 * cells
            + text;
        assert_eq!(len, unpadded.next_multiple_of(8));
        let dones = unpadded - text - 2 * cells;
        let mut bytes = encode(&fragment).unwrap();
        bytes[dones + 1] = 2;
        assert_eq!(decode(&bytes, None).unwrap_err().reason(), "invariant");
        let mut bytes = encode(&fragment).unwrap();
        bytes[dones + cells + 3] = 0; // slot 1 vanishes at step 1 without being done
        assert_eq!(decode(&bytes, None).unwrap_err().reason(), "invariant");
        let mut bytes = encode(&fragment).unwrap();
        bytes[unpadded - text] = 0xff; // the actor id is no longer UTF-8
        assert_eq!(decode(&bytes, None).unwrap_err().reason(), "decode");
        let episodes = dones - 4 * (8 * 2 + 5);
        let mut bytes = encode(&fragment).unwrap();
        put_u32(&mut bytes, episodes, 9); // unknown outcome
        assert_eq!(decode(&bytes, None).unwrap_err().reason(), "invariant");
    }

    #[test]
    fn encoder_refuses_inconsistent_fragments_and_wrong_buffers() {
        let mut broken = sample();
        broken.rewards.pop();
        assert_eq!(encode(&broken).unwrap_err().reason(), "shape");
        let mut long_name = sample();
        long_name.actor_id = "x".repeat(MAX_NAME_BYTES + 1);
        assert_eq!(encode(&long_name).unwrap_err().reason(), "shape");
        let fragment = sample();
        let mut buffer = vec![MaybeUninit::uninit(); encoded_len(&fragment).unwrap() + 8];
        assert!(matches!(
            encode_into(&fragment, &mut buffer),
            Err(LayoutError::BufferSize { .. })
        ));
    }

    #[test]
    fn corrupted_buffers_never_panic() {
        let valid = encode(&sample()).unwrap();
        // A small deterministic fuzz: flip bytes at pseudo-random places (the cargo-fuzz
        // target in fuzz/ does this at scale).
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let mut accepted = 0;
        for _ in 0..20_000 {
            let mut bytes = valid.clone();
            for _ in 0..1 + next() % 4 {
                let at = (next() as usize) % bytes.len();
                bytes[at] = next() as u8;
            }
            if decode(&bytes, None).is_ok() {
                accepted += 1;
            }
        }
        // Flips inside float payloads (finite values stay finite) decode fine; the rest fail.
        assert!(accepted > 0 && accepted < 20_000, "{accepted}");
    }
}
