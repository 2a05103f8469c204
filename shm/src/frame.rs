//! The bytes of one shared-memory sample: a small fixed header, then the payload.
//!
//! Pure code, no shared memory: the same functions frame a sample in the writer and read it in the
//! reader, and are unit tested here.
//!
//! # Transition frame (actor → learner)
//!
//! Little-endian, 48 header bytes, then `count` records in rfcl-core's `RecordLayout` (the exact
//! bytes of `TransitionBatch.records` on the gRPC path):
//!
//! | offset | bytes | field            | why |
//! |--------|-------|------------------|-----|
//! | 0      | 4     | magic `RFCT`     | a sample of another format is refused, never misread |
//! | 4      | 2     | format version 1 | |
//! | 6      | 2     | zero (reserved)  | a frame that sets them is refused |
//! | 8      | 4     | `actor_id`       | as `TransitionBatch.actor_id` |
//! | 12     | 4     | `obs_dim`        | checked against the run's, as on gRPC |
//! | 16     | 4     | `action_dim`     | |
//! | 20     | 4     | `count`          | records in the frame |
//! | 24     | 8     | `publisher`      | random per publisher (one actor process run) |
//! | 32     | 8     | `seq`            | frames this publisher sent before this one |
//! | 40     | 8     | `records_before` | records this publisher sent before this frame |
//!
//! `seq` and `records_before` let the learner prove that nothing was lost between a publisher and
//! itself: a gap is counted (records, exactly) and logged, never silent.
//!
//! # Policy frame (learner → actors)
//!
//! Little-endian, 24 header bytes (`RFCP`, format version, zero (reserved, checked as above),
//! `version` u64, `learner_env_steps` u64), then the safetensors bytes of the actor network
//! (`docs/POLICY.md`), the same bytes as `PolicyWeights.safetensors` on the gRPC path.
use thiserror::Error;

const TRANSITION_MAGIC: [u8; 4] = *b"RFCT";
const POLICY_MAGIC: [u8; 4] = *b"RFCP";
const FORMAT_VERSION: u16 = 1;

/// Bytes before the records of a transition frame (a multiple of 8, so records stay 8-aligned).
pub const TRANSITION_HEADER_BYTES: usize = 48;
/// Bytes before the safetensors of a policy frame.
pub const POLICY_HEADER_BYTES: usize = 24;

/// A frame that is not what its reader expects.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum FrameError {
    #[error("{kind} frame of {got} bytes is shorter than its {expected}-byte header")]
    Short {
        kind: &'static str,
        got: usize,
        expected: usize,
    },
    #[error("{kind} frame starts with {got:?}, expected the magic {expected:?}")]
    Magic {
        kind: &'static str,
        got: [u8; 4],
        expected: [u8; 4],
    },
    #[error("{kind} frame has format version {got}, this build reads version {FORMAT_VERSION}")]
    Version { kind: &'static str, got: u16 },
    /// Bytes 6..8 are reserved and written as zero: a frame that sets them is of a format this
    /// build does not know, so it is refused rather than misread.
    #[error("{kind} frame has {got:#06x} in its reserved bytes 6..8, expected zero")]
    Reserved { kind: &'static str, got: u16 },
}

/// The header of a transition frame (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TransitionHeader {
    pub actor_id: u32,
    pub obs_dim: u32,
    pub action_dim: u32,
    pub count: u32,
    pub publisher: u64,
    pub seq: u64,
    pub records_before: u64,
}

impl TransitionHeader {
    /// Writes the header into the first [`TRANSITION_HEADER_BYTES`] of `out`.
    ///
    /// # Panics
    /// When `out` is shorter than the header (a caller bug: frames are sized by the writer).
    pub fn encode(&self, out: &mut [u8]) {
        let out = &mut out[..TRANSITION_HEADER_BYTES];
        out[0..4].copy_from_slice(&TRANSITION_MAGIC);
        out[4..6].copy_from_slice(&FORMAT_VERSION.to_le_bytes());
        out[6..8].fill(0);
        out[8..12].copy_from_slice(&self.actor_id.to_le_bytes());
        out[12..16].copy_from_slice(&self.obs_dim.to_le_bytes());
        out[16..20].copy_from_slice(&self.action_dim.to_le_bytes());
        out[20..24].copy_from_slice(&self.count.to_le_bytes());
        out[24..32].copy_from_slice(&self.publisher.to_le_bytes());
        out[32..40].copy_from_slice(&self.seq.to_le_bytes());
        out[40..48].copy_from_slice(&self.records_before.to_le_bytes());
    }

    /// The header and the record bytes that follow it. The records' length is not checked here:
    /// the learner validates them exactly as it validates a gRPC `TransitionBatch`.
    pub fn decode(frame: &[u8]) -> Result<(Self, &[u8]), FrameError> {
        check_header(
            frame,
            "transition",
            TRANSITION_MAGIC,
            TRANSITION_HEADER_BYTES,
        )?;
        let header = Self {
            actor_id: u32_at(frame, 8),
            obs_dim: u32_at(frame, 12),
            action_dim: u32_at(frame, 16),
            count: u32_at(frame, 20),
            publisher: u64_at(frame, 24),
            seq: u64_at(frame, 32),
            records_before: u64_at(frame, 40),
        };
        Ok((header, &frame[TRANSITION_HEADER_BYTES..]))
    }
}

/// The header of a policy frame (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct PolicyHeader {
    pub version: u64,
    pub learner_env_steps: u64,
}

impl PolicyHeader {
    /// Writes the header into the first [`POLICY_HEADER_BYTES`] of `out`.
    ///
    /// # Panics
    /// When `out` is shorter than the header.
    pub fn encode(&self, out: &mut [u8]) {
        let out = &mut out[..POLICY_HEADER_BYTES];
        out[0..4].copy_from_slice(&POLICY_MAGIC);
        out[4..6].copy_from_slice(&FORMAT_VERSION.to_le_bytes());
        out[6..8].fill(0);
        out[8..16].copy_from_slice(&self.version.to_le_bytes());
        out[16..24].copy_from_slice(&self.learner_env_steps.to_le_bytes());
    }

    /// The header and the safetensors bytes that follow it.
    pub fn decode(frame: &[u8]) -> Result<(Self, &[u8]), FrameError> {
        check_header(frame, "policy", POLICY_MAGIC, POLICY_HEADER_BYTES)?;
        let header = Self {
            version: u64_at(frame, 8),
            learner_env_steps: u64_at(frame, 16),
        };
        Ok((header, &frame[POLICY_HEADER_BYTES..]))
    }
}

fn check_header(
    frame: &[u8],
    kind: &'static str,
    magic: [u8; 4],
    header_bytes: usize,
) -> Result<(), FrameError> {
    if frame.len() < header_bytes {
        return Err(FrameError::Short {
            kind,
            got: frame.len(),
            expected: header_bytes,
        });
    }
    let got: [u8; 4] = frame[0..4].try_into().expect("4 bytes");
    if got != magic {
        return Err(FrameError::Magic {
            kind,
            got,
            expected: magic,
        });
    }
    let version = u16::from_le_bytes([frame[4], frame[5]]);
    if version != FORMAT_VERSION {
        return Err(FrameError::Version { kind, got: version });
    }
    let reserved = u16::from_le_bytes([frame[6], frame[7]]);
    if reserved != 0 {
        return Err(FrameError::Reserved {
            kind,
            got: reserved,
        });
    }
    Ok(())
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"))
}

fn u64_at(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().expect("8 bytes"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transition_headers_round_trip_and_keep_the_records() {
        let header = TransitionHeader {
            actor_id: 7,
            obs_dim: 42,
            action_dim: 8,
            count: 3,
            publisher: 0xDEAD_BEEF_0123_4567,
            seq: 11,
            records_before: 704,
        };
        let mut frame = vec![0xAB; TRANSITION_HEADER_BYTES + 5];
        header.encode(&mut frame);
        let (back, records) = TransitionHeader::decode(&frame).unwrap();
        assert_eq!(back, header);
        assert_eq!(records, &[0xAB; 5]);
    }

    #[test]
    fn policy_headers_round_trip() {
        let header = PolicyHeader {
            version: 9,
            learner_env_steps: 12_345,
        };
        let mut frame = vec![1; POLICY_HEADER_BYTES + 3];
        header.encode(&mut frame);
        let (back, weights) = PolicyHeader::decode(&frame).unwrap();
        assert_eq!(back, header);
        assert_eq!(weights, &[1, 1, 1]);
    }

    #[test]
    fn foreign_frames_are_refused_with_what_was_expected() {
        assert!(matches!(
            TransitionHeader::decode(&[0; 10]),
            Err(FrameError::Short { expected: 48, .. })
        ));
        let mut policy = vec![0; POLICY_HEADER_BYTES + TRANSITION_HEADER_BYTES];
        PolicyHeader::default().encode(&mut policy);
        let e = TransitionHeader::decode(&policy).unwrap_err();
        assert!(e.to_string().contains("expected the magic"), "{e}");
        let mut frame = vec![0; TRANSITION_HEADER_BYTES];
        TransitionHeader::default().encode(&mut frame);
        frame[4] = 2;
        assert_eq!(
            TransitionHeader::decode(&frame).unwrap_err(),
            FrameError::Version {
                kind: "transition",
                got: 2
            }
        );
    }

    /// Found by the `shm_frame` fuzz target (fuzz/artifacts/shm_frame/): the reserved bytes were
    /// not checked, so a frame of some other layout decoded as if they were zero.
    #[test]
    fn frames_with_reserved_bytes_set_are_refused() {
        let mut frame = vec![0; TRANSITION_HEADER_BYTES];
        TransitionHeader::default().encode(&mut frame);
        frame[6] = 0xFF;
        frame[7] = 0xFF;
        let e = TransitionHeader::decode(&frame).unwrap_err();
        assert_eq!(
            e,
            FrameError::Reserved {
                kind: "transition",
                got: 0xFFFF
            }
        );
        assert_eq!(
            e.to_string(),
            "transition frame has 0xffff in its reserved bytes 6..8, expected zero"
        );
        let mut policy = vec![0; POLICY_HEADER_BYTES];
        PolicyHeader::default().encode(&mut policy);
        policy[7] = 1;
        assert!(matches!(
            PolicyHeader::decode(&policy),
            Err(FrameError::Reserved {
                kind: "policy",
                got: 0x100
            })
        ));
    }
}
