//! The learner's last word: its counters when it stops cleanly, written to
//! `RUN_DIR/learner_final.json` after the training thread has ended and the ingest is closed.
//! Every figure is from that one moment, so the transport counts cover the env steps. A learner
//! that ends the run by itself (the curriculum server's stop rule) can no longer answer Health;
//! this is how `rfcl train`'s summary gets its final counts.
use serde::{Deserialize, Serialize};

/// The file in the learner's run directory.
pub const FINAL_COUNTERS_FILE: &str = "learner_final.json";

/// The learner's counters at one moment: what its Health reply carries, and what it writes when
/// it stops.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct LearnerCounts {
    /// Env steps received in all (a resumed learner counts on from its checkpoint), critic
    /// updates and the last policy version.
    pub env_steps: u64,
    pub updates: u64,
    pub policy_version: u64,
    /// Transition records taken in per transport by this process, records missing between an
    /// actor's shared-memory frames, and batches refused as malformed.
    pub shm_records: u64,
    pub grpc_records: u64,
    pub shm_lost_records: u64,
    pub refused_batches: u64,
    /// Records dropped because their stage epoch had ended (over the whole run, like
    /// `env_steps`), and records this process took in but never used because it stopped first.
    #[serde(default)]
    pub dropped_stale_epoch: u64,
    #[serde(default)]
    pub unused_records: u64,
}

/// The file's content: the counts, and the learner process that wrote them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct FinalCounters {
    /// A file from an earlier process is not this one's.
    pub pid: u32,
    #[serde(flatten)]
    pub counts: LearnerCounts,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The counts sit beside the pid in the file, one flat JSON object.
    #[test]
    fn the_file_is_one_flat_object() {
        let last = FinalCounters {
            pid: 7,
            counts: LearnerCounts {
                env_steps: 100,
                shm_records: 100,
                ..LearnerCounts::default()
            },
        };
        let json = serde_json::to_value(last).unwrap();
        assert_eq!(
            (json["pid"].as_u64(), json["env_steps"].as_u64()),
            (Some(7), Some(100))
        );
        assert_eq!(serde_json::from_value::<FinalCounters>(json).unwrap(), last);
    }
}
