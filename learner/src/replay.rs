//! Replay (spec 5.5, 6.2, 4.2, 12.7): the online and offline buffers, the interleaved 50/50
//! sampling, demos as offline transitions (with `data_action_scale`, spec 6.4 / deviation 1) and
//! the stage transition.
//!
//! A buffer is a preallocated ring with one flat `f32` storage per field. The reference keeps one
//! ring of ceil(C / num_envs) slots per env, written in lockstep, and samples (time slot, env)
//! pairs uniformly; with actors reporting asynchronously (deviation 4) one ring of C slots over all
//! envs gives the same uniform distribution over the stored transitions.
use crate::batch::HostBatch;
use crate::error::{LearnerError, Result};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rfcl_core::demo::Demo;
use rfcl_core::transition::RecordView;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::ops::Range;

/// Rows per checkpoint segment: a checkpoint writes a buffer as one file per segment of this many
/// rows and rewrites only the segments pushed into since the last one (see [`crate::checkpoint`]).
/// 16,384 rows are 1.2 MB of PointMaze records and 6.2 MB of paper-size ones (obs 42, action 8):
/// small enough that a checkpoint after a minute of a run writes little more than that minute's
/// rows, large enough that a full 1M-row buffer is 62 files.
pub const SEGMENT_ROWS: usize = 1 << 14;

/// A checkpoint file that holds a segment's rows exactly as they are in the buffer now.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct SegmentFile {
    /// File name inside the checkpoint directory.
    pub file: String,
    pub rows: usize,
    pub bytes: u64,
    /// CRC-32C of the file's bytes.
    pub crc32c: u32,
}

/// One replay ring of transitions `(s, a, r, mask, s′)`.
#[derive(Debug, Clone)]
pub struct ReplayBuffer {
    name: &'static str,
    obs_dim: usize,
    action_dim: usize,
    capacity: usize,
    obs: Vec<f32>,
    action: Vec<f32>,
    reward: Vec<f32>,
    mask: Vec<f32>,
    next_obs: Vec<f32>,
    len: usize,
    /// The slot the next push writes.
    cursor: usize,
    /// Rows per checkpoint segment.
    segment_rows: usize,
    /// Per segment, the checkpoint file holding its current rows; `None` once a push changed it
    /// (or it was never saved). Moves with the buffer, so a buffer renamed at the stage
    /// transition still knows its files.
    saved: Vec<Option<SegmentFile>>,
}

impl ReplayBuffer {
    /// Allocates the whole ring now (zeroed; pages are committed as they are first written).
    pub fn new(
        name: &'static str,
        capacity: usize,
        obs_dim: usize,
        action_dim: usize,
    ) -> Result<Self> {
        if capacity == 0 || obs_dim == 0 || action_dim == 0 {
            return Err(LearnerError::Config(format!(
                "{name} replay buffer: capacity {capacity}, obs_dim {obs_dim} and action_dim {action_dim} must be positive"
            )));
        }
        Ok(Self {
            name,
            obs_dim,
            action_dim,
            capacity,
            obs: vec![0.0; capacity * obs_dim],
            action: vec![0.0; capacity * action_dim],
            reward: vec![0.0; capacity],
            mask: vec![0.0; capacity],
            next_obs: vec![0.0; capacity * obs_dim],
            len: 0,
            cursor: 0,
            segment_rows: SEGMENT_ROWS,
            saved: vec![None; capacity.div_ceil(SEGMENT_ROWS)],
        })
    }

    /// Bytes one stored transition takes: obs, next obs, action, reward and mask, all f32.
    pub fn record_bytes(obs_dim: usize, action_dim: usize) -> usize {
        4 * (2 * obs_dim + action_dim + 2)
    }

    /// Bytes allocated for the storage: capacity × [`record_bytes`](Self::record_bytes).
    pub fn bytes(&self) -> usize {
        4 * (self.obs.len()
            + self.action.len()
            + self.reward.len()
            + self.mask.len()
            + self.next_obs.len())
    }

    pub fn name(&self) -> &'static str {
        self.name
    }
    pub fn len(&self) -> usize {
        self.len
    }
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
    pub fn capacity(&self) -> usize {
        self.capacity
    }
    pub fn obs_dim(&self) -> usize {
        self.obs_dim
    }
    pub fn action_dim(&self) -> usize {
        self.action_dim
    }

    /// Appends one transition, overwriting the oldest once full.
    pub fn push(
        &mut self,
        obs: &[f32],
        action: &[f32],
        reward: f32,
        mask: f32,
        next_obs: &[f32],
    ) -> Result<()> {
        self.check_dims(obs.len(), action.len(), next_obs.len())?;
        let (d, a, i) = (self.obs_dim, self.action_dim, self.cursor);
        self.obs[i * d..(i + 1) * d].copy_from_slice(obs);
        self.action[i * a..(i + 1) * a].copy_from_slice(action);
        self.next_obs[i * d..(i + 1) * d].copy_from_slice(next_obs);
        self.reward[i] = reward;
        self.mask[i] = mask;
        self.advance();
        Ok(())
    }

    /// Appends one transition record (rfcl-core's wire layout), copying its fields straight into
    /// the ring.
    pub fn push_record(&mut self, record: &RecordView<'_>) -> Result<()> {
        let layout = record.layout();
        self.check_dims(layout.obs_dim, layout.action_dim, layout.obs_dim)?;
        let (d, a, i) = (self.obs_dim, self.action_dim, self.cursor);
        record.obs_into(&mut self.obs[i * d..(i + 1) * d])?;
        record.action_into(&mut self.action[i * a..(i + 1) * a])?;
        record.next_obs_into(&mut self.next_obs[i * d..(i + 1) * d])?;
        self.reward[i] = record.reward();
        self.mask[i] = record.mask();
        self.advance();
        Ok(())
    }

    /// Appends all T steps of a demo as (obs_t, a_t · scale, r_t = success_t, mask 1, obs_{t+1})
    /// (spec 6.2); `action_scale` is [`data_action_scale`]'s s, `None` = unscaled.
    pub fn push_demo(&mut self, demo: &Demo, action_scale: Option<&[f32]>) -> Result<()> {
        let mut action = vec![0.0; self.action_dim];
        for t in 0..demo.len() {
            action.copy_from_slice(demo.action_row(t));
            if let Some(scale) = action_scale {
                action.iter_mut().zip(scale).for_each(|(a, s)| *a *= s);
            }
            let reward = if demo.success[t] { 1.0 } else { 0.0 };
            self.push(demo.obs_row(t), &action, reward, 1.0, demo.obs_row(t + 1))?;
        }
        Ok(())
    }

    /// Empties the ring: cursor 0, storage zeroed (spec 4.2).
    pub fn clear(&mut self) {
        for field in [
            &mut self.obs,
            &mut self.action,
            &mut self.reward,
            &mut self.mask,
            &mut self.next_obs,
        ] {
            field.fill(0.0);
        }
        self.len = 0;
        self.cursor = 0;
        self.saved.fill(None);
    }

    /// Appends stored transition `i` to `out`.
    fn copy_row(&self, i: usize, out: &mut HostBatch) {
        let (d, a) = (self.obs_dim, self.action_dim);
        out.obs.extend_from_slice(&self.obs[i * d..(i + 1) * d]);
        out.action
            .extend_from_slice(&self.action[i * a..(i + 1) * a]);
        out.reward.push(self.reward[i]);
        out.mask.push(self.mask[i]);
        out.next_obs
            .extend_from_slice(&self.next_obs[i * d..(i + 1) * d]);
    }

    /// A uniformly drawn stored transition's slot (with replacement).
    fn draw(&self, rng: &mut ChaCha8Rng) -> usize {
        rng.random_range(0..self.len)
    }

    fn advance(&mut self) {
        self.saved[self.cursor / self.segment_rows] = None;
        self.cursor = (self.cursor + 1) % self.capacity;
        self.len = (self.len + 1).min(self.capacity);
    }

    fn check_dims(&self, obs: usize, action: usize, next_obs: usize) -> Result<()> {
        if obs != self.obs_dim || next_obs != self.obs_dim || action != self.action_dim {
            return Err(LearnerError::Shape(format!(
                "{} replay buffer stores obs {} / action {}, got obs {obs} / action {action} / next_obs {next_obs}",
                self.name, self.obs_dim, self.action_dim
            )));
        }
        Ok(())
    }
}

impl fmt::Display for ReplayBuffer {
    /// e.g. `online replay: 1200/1000000 transitions × 376 B = 376.0 MB`
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} replay: {}/{} transitions × {} B = {:.1} MB",
            self.name,
            self.len,
            self.capacity,
            Self::record_bytes(self.obs_dim, self.action_dim),
            self.bytes() as f64 / 1e6
        )
    }
}

/// The online buffer, the optional offline buffer, and the seeded RNG that samples them.
#[derive(Debug, Clone)]
pub struct Replay {
    pub online: ReplayBuffer,
    pub offline: Option<ReplayBuffer>,
    rng: ChaCha8Rng,
}

impl Replay {
    pub fn new(online: ReplayBuffer, offline: Option<ReplayBuffer>, seed: u64) -> Self {
        Self {
            online,
            offline,
            rng: ChaCha8Rng::seed_from_u64(seed),
        }
    }

    /// Spec 5.2 steps 1-2 (and 12.7): `minibatches` × `batch_size` rows for one training
    /// iteration. With an offline buffer, half the rows are drawn uniformly with replacement from
    /// each buffer and interleaved (online, offline, online, …), then split sequentially, so every
    /// minibatch is exactly 50/50; without one, every row comes from the online buffer.
    pub fn sample(&mut self, minibatches: usize, batch_size: usize) -> Result<HostBatch> {
        let rows = minibatches * batch_size;
        let mut out = HostBatch::with_capacity(rows, self.online.obs_dim, self.online.action_dim);
        if self.online.is_empty() {
            return Err(LearnerError::EmptyBuffer("online"));
        }
        match &self.offline {
            None => {
                for _ in 0..rows {
                    self.online
                        .copy_row(self.online.draw(&mut self.rng), &mut out);
                }
            }
            Some(offline) => {
                if offline.is_empty() {
                    return Err(LearnerError::EmptyBuffer("offline"));
                }
                if !batch_size.is_multiple_of(2) {
                    return Err(LearnerError::Config(format!(
                        "sac.batch_size ({batch_size}) must be even to split minibatches 50/50 online/offline"
                    )));
                }
                for _ in 0..rows / 2 {
                    self.online
                        .copy_row(self.online.draw(&mut self.rng), &mut out);
                    offline.copy_row(offline.draw(&mut self.rng), &mut out);
                }
            }
        }
        Ok(out)
    }

    /// Spec 4.2, the buffers at the stage transition. With `as_offline` (the reference's
    /// `load_as_offline_buffer`, default) the offline buffer becomes the stage-1 online buffer's
    /// contents and the demo transitions are dropped; otherwise there is no offline buffer. Unless
    /// `as_online` (`load_as_online_buffer`, default false) keeps it, the online buffer is then
    /// emptied.
    pub fn stage_transition(&mut self, as_offline: bool, as_online: bool) -> Result<()> {
        let capacity = self.online.capacity;
        let (d, a) = (self.online.obs_dim, self.online.action_dim);
        self.offline = match (as_offline, as_online) {
            (true, true) => Some(ReplayBuffer {
                name: "offline",
                ..self.online.clone()
            }),
            (true, false) => {
                let fresh = ReplayBuffer::new("online", capacity, d, a)?;
                Some(ReplayBuffer {
                    name: "offline",
                    ..std::mem::replace(&mut self.online, fresh)
                })
            }
            (false, _) => None,
        };
        if !as_online && !as_offline {
            self.online.clear();
        }
        Ok(())
    }

    /// Bytes allocated by both buffers.
    pub fn bytes(&self) -> usize {
        self.online.bytes() + self.offline.as_ref().map_or(0, ReplayBuffer::bytes)
    }

    /// The sampling RNG (checkpoint it to resume exactly).
    pub fn rng(&self) -> &ChaCha8Rng {
        &self.rng
    }
}

/// Spec 6.4 (`data_action_scale`, deviation 1): the per-dimension action scale s. With
/// mag_d = max |a_d| over all demo actions, s_d = 1 / (mag_d · data_action_scale), except s_d = 1
/// where dimension d ever reaches exactly ±1 or is identically 0. The env is wrapped to [−s, s]
/// (agent action a ↦ env action a / s) and demo actions are stored as a · s, in agent units.
/// Errors unless every demo action is in [−1, 1].
pub fn data_action_scale(
    demos: &[Demo],
    action_dim: usize,
    data_action_scale: f64,
) -> Result<Vec<f32>> {
    let mut magnitude = vec![0.0f32; action_dim];
    let mut hits_bound = vec![false; action_dim];
    for demo in demos {
        for row in demo.actions.chunks_exact(action_dim) {
            for (dim, &value) in row.iter().enumerate() {
                if !(-1.0..=1.0).contains(&value) {
                    return Err(LearnerError::DemoActionRange { dim, value });
                }
                magnitude[dim] = magnitude[dim].max(value.abs());
                hits_bound[dim] |= value.abs() == 1.0;
            }
        }
    }
    Ok(magnitude
        .iter()
        .zip(&hits_bound)
        .map(|(&mag, &hits)| {
            if hits || mag == 0.0 {
                1.0
            } else {
                (1.0 / (f64::from(mag) * data_action_scale)) as f32
            }
        })
        .collect())
}

/// Spec 6.2: the offline buffer of all steps of `demos` (capacity = their total step count),
/// actions multiplied by `action_scale` when given.
pub fn offline_from_demos(demos: &[Demo], action_scale: Option<&[f32]>) -> Result<ReplayBuffer> {
    let first = demos
        .first()
        .ok_or_else(|| LearnerError::Config("no demos to build the offline buffer".into()))?;
    let steps: usize = demos.iter().map(Demo::len).sum();
    let mut buffer = ReplayBuffer::new("offline", steps.max(1), first.obs_dim, first.action_dim)?;
    for demo in demos {
        buffer.push_demo(demo, action_scale)?;
    }
    Ok(buffer)
}

/// Checkpoint access (additive only): the ring's raw
/// storage and position, so a checkpoint can store a buffer and restore it exactly (spec 4.1).
impl ReplayBuffer {
    /// The slot the next push writes; with [`len`](Self::len), the ring's whole position.
    pub fn cursor(&self) -> usize {
        self.cursor
    }

    /// The storage, `capacity` rows per field, in the order obs, action, reward, mask, next_obs.
    pub fn storage(&self) -> [&[f32]; 5] {
        [
            &self.obs,
            &self.action,
            &self.reward,
            &self.mask,
            &self.next_obs,
        ]
    }

    /// Sets the ring's position and hands out its storage (same order as
    /// [`storage`](Self::storage)) for the caller to fill: a checkpoint restore.
    pub fn restore_storage(&mut self, len: usize, cursor: usize) -> Result<[&mut [f32]; 5]> {
        if len > self.capacity || cursor >= self.capacity || (len < self.capacity && cursor != len)
        {
            return Err(LearnerError::Shape(format!(
                "{} replay buffer of capacity {}: cannot restore len {len} with cursor {cursor}",
                self.name, self.capacity
            )));
        }
        self.len = len;
        self.cursor = cursor;
        self.saved.fill(None);
        Ok([
            &mut self.obs,
            &mut self.action,
            &mut self.reward,
            &mut self.mask,
            &mut self.next_obs,
        ])
    }
}

/// Checkpoint segments: which rows a segment holds and which file holds them.
impl ReplayBuffer {
    pub fn segment_rows(&self) -> usize {
        self.segment_rows
    }

    /// Sets the rows per checkpoint segment (the checkpoint's own, on restore; small ones in
    /// tests); forgets which files hold the segments.
    pub fn set_segment_rows(&mut self, rows: usize) -> Result<()> {
        if rows == 0 {
            return Err(LearnerError::Config(format!(
                "{} replay buffer: rows per checkpoint segment must be positive",
                self.name
            )));
        }
        self.segment_rows = rows;
        self.saved = vec![None; self.capacity.div_ceil(rows)];
        Ok(())
    }

    /// Segments holding stored rows.
    pub fn stored_segments(&self) -> usize {
        self.len.div_ceil(self.segment_rows)
    }

    /// The stored rows of segment `k`.
    pub fn segment_range(&self, k: usize) -> Range<usize> {
        let start = (k * self.segment_rows).min(self.len);
        start..((k + 1) * self.segment_rows).min(self.len)
    }

    /// The file that holds segment `k` as it is now, if any.
    pub fn saved_segment(&self, k: usize) -> Option<&SegmentFile> {
        self.saved.get(k).and_then(Option::as_ref)
    }

    /// Records that `file` holds segment `k` as it is now (after a checkpoint committed it).
    pub fn set_saved_segment(&mut self, k: usize, file: SegmentFile) {
        self.saved[k] = Some(file);
    }
}

impl Replay {
    /// Restores the sampling RNG (checkpoint resume).
    pub fn set_rng(&mut self, rng: ChaCha8Rng) {
        self.rng = rng;
    }
}
