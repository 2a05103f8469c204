//! The transition record: ONE fixed little-endian binary layout, shared by the shared-memory
//! (iceoryx2) and the gRPC (`TransitionBatch.records`) transports (docs/DESIGN.md, "The path of a transition").
//!
//! A record carries one environment step `(obs, action, reward, next_obs, mask)` together with the
//! stage epoch it was collected in (the learner drops late transitions of an old epoch, spec 4),
//! the actor id and the policy version that acted (the learner reports policy lag). `next_obs` is
//! the true final observation at an episode end; `mask` is 0 on a true termination and 1
//! otherwise (spec 5.6).
//!
//! # Layout
//!
//! For `D = obs_dim` and `A = action_dim`, every number little-endian:
//!
//! | offset            | bytes | field            | type  |
//! |-------------------|-------|------------------|-------|
//! | 0                 | 8     | `stage_epoch`    | `u64` |
//! | 8                 | 8     | `policy_version` | `u64` |
//! | 16                | 4     | `actor_id`       | `u32` |
//! | 20                | 4     | `reward`         | `f32` |
//! | 24                | 4     | `mask`           | `f32` |
//! | 28                | 4     | padding (zero)   |       |
//! | 32                | 4·D   | `obs`            | `f32` × D |
//! | 32 + 4·D          | 4·A   | `action`         | `f32` × A |
//! | 32 + 4·D + 4·A    | 4·D   | `next_obs`       | `f32` × D |
//! | 32 + 8·D + 4·A    | 0 or 4 | padding (zero) to the next multiple of 8 |  |
//!
//! So [`RecordLayout::record_bytes`] = `32 + 4·(2·D + A)` rounded up to a multiple of 8, and
//! every record of a batch (records back to back, no separators) starts 8-byte aligned relative to
//! the batch. Obs 42 / action 8 gives 400 bytes. Readers ignore the padding bytes; writers zero
//! them. Nothing here needs the buffer itself to be aligned: fields are read with `from_le_bytes`.

use thiserror::Error;

/// One environment step as the learner stores it (docs/DESIGN.md, "The path of a transition").
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Transition {
    pub obs: Vec<f32>,
    pub action: Vec<f32>,
    pub reward: f32,
    /// The true next observation (the final one at an episode end, not the reset's).
    pub next_obs: Vec<f32>,
    /// 0 on a true termination, 1 otherwise (spec 5.6).
    pub mask: f32,
    pub stage_epoch: u64,
    pub actor_id: u32,
    pub policy_version: u64,
}

/// A record of the wrong size, or a transition or buffer that does not fit the layout.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum RecordError {
    #[error(
        "transition record is {got} bytes, expected {expected} (obs_dim {obs_dim}, action_dim {action_dim})"
    )]
    RecordLength {
        expected: usize,
        got: usize,
        obs_dim: usize,
        action_dim: usize,
    },
    #[error(
        "transition batch of {got} bytes is not a whole number of {record_bytes}-byte records (obs_dim {obs_dim}, action_dim {action_dim})"
    )]
    BatchLength {
        got: usize,
        record_bytes: usize,
        obs_dim: usize,
        action_dim: usize,
    },
    #[error(
        "output buffer is {got} bytes, expected {records} records × {record_bytes} = {expected} bytes (obs_dim {obs_dim}, action_dim {action_dim})"
    )]
    OutputLength {
        expected: usize,
        got: usize,
        records: usize,
        record_bytes: usize,
        obs_dim: usize,
        action_dim: usize,
    },
    #[error("transition {field} has {got} values, expected {dim_name} {expected}")]
    Dim {
        field: &'static str,
        dim_name: &'static str,
        expected: usize,
        got: usize,
    },
}

/// The record layout for one pair of dims (see the module docs for the bytes).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct RecordLayout {
    pub obs_dim: usize,
    pub action_dim: usize,
}

const STAGE_EPOCH: usize = 0;
const POLICY_VERSION: usize = 8;
const ACTOR_ID: usize = 16;
const REWARD: usize = 20;
const MASK: usize = 24;

impl RecordLayout {
    /// Bytes before `obs`: the fixed header fields and their padding.
    pub const HEADER_BYTES: usize = 32;

    pub fn new(obs_dim: usize, action_dim: usize) -> Self {
        Self {
            obs_dim,
            action_dim,
        }
    }

    /// Bytes of one record, a multiple of 8. The replay states its memory as capacity × this.
    pub fn record_bytes(&self) -> usize {
        let unpadded = Self::HEADER_BYTES + 4 * (2 * self.obs_dim + self.action_dim);
        unpadded.next_multiple_of(8)
    }

    fn action_offset(&self) -> usize {
        Self::HEADER_BYTES + 4 * self.obs_dim
    }

    fn next_obs_offset(&self) -> usize {
        self.action_offset() + 4 * self.action_dim
    }

    /// Writes `t` into `out`, which must be exactly [`record_bytes`](Self::record_bytes) long.
    pub fn encode(&self, t: &Transition, out: &mut [u8]) -> Result<(), RecordError> {
        self.check_record_len(out.len())?;
        self.check_dims(t)?;
        out[STAGE_EPOCH..STAGE_EPOCH + 8].copy_from_slice(&t.stage_epoch.to_le_bytes());
        out[POLICY_VERSION..POLICY_VERSION + 8].copy_from_slice(&t.policy_version.to_le_bytes());
        out[ACTOR_ID..ACTOR_ID + 4].copy_from_slice(&t.actor_id.to_le_bytes());
        out[REWARD..REWARD + 4].copy_from_slice(&t.reward.to_le_bytes());
        out[MASK..MASK + 4].copy_from_slice(&t.mask.to_le_bytes());
        out[MASK + 4..Self::HEADER_BYTES].fill(0);
        let action_at = self.action_offset();
        let next_obs_at = self.next_obs_offset();
        let end = next_obs_at + 4 * self.obs_dim;
        put_f32s(&mut out[Self::HEADER_BYTES..action_at], &t.obs);
        put_f32s(&mut out[action_at..next_obs_at], &t.action);
        put_f32s(&mut out[next_obs_at..end], &t.next_obs);
        out[end..].fill(0);
        Ok(())
    }

    /// Reads one record into a new [`Transition`].
    pub fn decode(&self, bytes: &[u8]) -> Result<Transition, RecordError> {
        Ok(self.view(bytes)?.to_transition())
    }

    /// A zero-copy view of one record.
    pub fn view<'a>(&self, bytes: &'a [u8]) -> Result<RecordView<'a>, RecordError> {
        self.check_record_len(bytes.len())?;
        Ok(RecordView {
            layout: *self,
            bytes,
        })
    }

    /// Writes `transitions` back to back into `out`, which must be exactly
    /// `transitions.len() × record_bytes` long.
    pub fn encode_batch(
        &self,
        transitions: &[Transition],
        out: &mut [u8],
    ) -> Result<(), RecordError> {
        let record_bytes = self.record_bytes();
        let expected = transitions.len() * record_bytes;
        if out.len() != expected {
            return Err(RecordError::OutputLength {
                expected,
                got: out.len(),
                records: transitions.len(),
                record_bytes,
                obs_dim: self.obs_dim,
                action_dim: self.action_dim,
            });
        }
        transitions
            .iter()
            .zip(out.chunks_exact_mut(record_bytes))
            .try_for_each(|(t, chunk)| self.encode(t, chunk))
    }

    /// Reads every record of a batch.
    pub fn decode_batch(&self, bytes: &[u8]) -> Result<Vec<Transition>, RecordError> {
        Ok(self
            .view_batch(bytes)?
            .map(|view| view.to_transition())
            .collect())
    }

    /// Zero-copy views of every record of a batch, in order.
    pub fn view_batch<'a>(
        &self,
        bytes: &'a [u8],
    ) -> Result<impl ExactSizeIterator<Item = RecordView<'a>> + 'a, RecordError> {
        let record_bytes = self.record_bytes();
        if !bytes.len().is_multiple_of(record_bytes) {
            return Err(RecordError::BatchLength {
                got: bytes.len(),
                record_bytes,
                obs_dim: self.obs_dim,
                action_dim: self.action_dim,
            });
        }
        let layout = *self;
        Ok(bytes
            .chunks_exact(record_bytes)
            .map(move |bytes| RecordView { layout, bytes }))
    }

    fn check_record_len(&self, got: usize) -> Result<(), RecordError> {
        let expected = self.record_bytes();
        if got == expected {
            Ok(())
        } else {
            Err(RecordError::RecordLength {
                expected,
                got,
                obs_dim: self.obs_dim,
                action_dim: self.action_dim,
            })
        }
    }

    fn check_dims(&self, t: &Transition) -> Result<(), RecordError> {
        let fields: [(&'static str, &'static str, usize, usize); 3] = [
            ("obs", "obs_dim", self.obs_dim, t.obs.len()),
            ("action", "action_dim", self.action_dim, t.action.len()),
            ("next_obs", "obs_dim", self.obs_dim, t.next_obs.len()),
        ];
        match fields
            .into_iter()
            .find(|&(_, _, expected, got)| expected != got)
        {
            Some((field, dim_name, expected, got)) => Err(RecordError::Dim {
                field,
                dim_name,
                expected,
                got,
            }),
            None => Ok(()),
        }
    }
}

/// A borrowed record of exactly [`RecordLayout::record_bytes`] bytes. Header fields are read on
/// demand; the vectors are copied into caller slices, so reading allocates nothing.
#[derive(Debug, Clone, Copy)]
pub struct RecordView<'a> {
    layout: RecordLayout,
    bytes: &'a [u8],
}

impl RecordView<'_> {
    pub fn layout(&self) -> RecordLayout {
        self.layout
    }

    /// The record's bytes.
    pub fn as_bytes(&self) -> &[u8] {
        self.bytes
    }

    pub fn stage_epoch(&self) -> u64 {
        u64::from_le_bytes(self.array(STAGE_EPOCH))
    }

    pub fn policy_version(&self) -> u64 {
        u64::from_le_bytes(self.array(POLICY_VERSION))
    }

    pub fn actor_id(&self) -> u32 {
        u32::from_le_bytes(self.array(ACTOR_ID))
    }

    pub fn reward(&self) -> f32 {
        f32::from_le_bytes(self.array(REWARD))
    }

    pub fn mask(&self) -> f32 {
        f32::from_le_bytes(self.array(MASK))
    }

    /// Copies `obs` into `out` (length `obs_dim`).
    pub fn obs_into(&self, out: &mut [f32]) -> Result<(), RecordError> {
        let (start, end) = (RecordLayout::HEADER_BYTES, self.layout.action_offset());
        self.copy_into("obs", "obs_dim", start, end, out)
    }

    /// Copies `action` into `out` (length `action_dim`).
    pub fn action_into(&self, out: &mut [f32]) -> Result<(), RecordError> {
        let (start, end) = (self.layout.action_offset(), self.layout.next_obs_offset());
        self.copy_into("action", "action_dim", start, end, out)
    }

    /// Copies `next_obs` into `out` (length `obs_dim`).
    pub fn next_obs_into(&self, out: &mut [f32]) -> Result<(), RecordError> {
        let start = self.layout.next_obs_offset();
        let end = start + 4 * self.layout.obs_dim;
        self.copy_into("next_obs", "obs_dim", start, end, out)
    }

    /// Copies the whole record into a new [`Transition`].
    pub fn to_transition(&self) -> Transition {
        let (action_at, next_obs_at) = (self.layout.action_offset(), self.layout.next_obs_offset());
        let end = next_obs_at + 4 * self.layout.obs_dim;
        Transition {
            obs: f32s(&self.bytes[RecordLayout::HEADER_BYTES..action_at]).collect(),
            action: f32s(&self.bytes[action_at..next_obs_at]).collect(),
            reward: self.reward(),
            next_obs: f32s(&self.bytes[next_obs_at..end]).collect(),
            mask: self.mask(),
            stage_epoch: self.stage_epoch(),
            actor_id: self.actor_id(),
            policy_version: self.policy_version(),
        }
    }

    fn array<const N: usize>(&self, offset: usize) -> [u8; N] {
        self.bytes[offset..offset + N]
            .try_into()
            .expect("a view spans a whole record")
    }

    fn copy_into(
        &self,
        field: &'static str,
        dim_name: &'static str,
        start: usize,
        end: usize,
        out: &mut [f32],
    ) -> Result<(), RecordError> {
        let src = &self.bytes[start..end];
        let expected = src.len() / 4;
        if out.len() != expected {
            return Err(RecordError::Dim {
                field,
                dim_name,
                expected,
                got: out.len(),
            });
        }
        for (value, read) in out.iter_mut().zip(f32s(src)) {
            *value = read;
        }
        Ok(())
    }
}

/// The little-endian `f32`s of `bytes` (a multiple of 4 long).
fn f32s(bytes: &[u8]) -> impl Iterator<Item = f32> + '_ {
    bytes
        .chunks_exact(4)
        .map(|chunk| f32::from_le_bytes(chunk.try_into().expect("4 bytes")))
}

fn put_f32s(out: &mut [u8], values: &[f32]) {
    for (chunk, value) in out.chunks_exact_mut(4).zip(values) {
        chunk.copy_from_slice(&value.to_le_bytes());
    }
}
