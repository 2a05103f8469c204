//! Who is on which host, and what a run's shared-memory services are called.
//!
//! Services are named per run *and* per learner session (`rfcl/<run name>/<run id>/...`), so two
//! runs on one host never mix, not even two runs of the same config, and a restarted learner never
//! receives samples meant for its predecessor. Node names carry the run name only
//! (`rfcl/<run name>/<role>`), so a restarted process finds the dead nodes its run left behind.
use std::collections::hash_map::RandomState;
use std::hash::{BuildHasher, Hasher};
use std::os::unix::fs::MetadataExt;
use std::time::{SystemTime, UNIX_EPOCH};

/// Longest run name kept in a service name (iceoryx2 names are bounded; the id keeps them unique).
const MAX_RUN_NAME: usize = 64;

/// The iceoryx2 service names of one learner session.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ServiceNames {
    /// Transition batches, actors → learner.
    pub transitions: String,
    /// Policy versions, learner → actors.
    pub policy: String,
}

impl ServiceNames {
    pub fn new(run_name: &str, run_id: &str) -> Self {
        let base = format!("rfcl/{}/{}", sanitize(run_name), sanitize(run_id));
        Self {
            transitions: format!("{base}/transitions"),
            policy: format!("{base}/policy"),
        }
    }
}

/// `rfcl/<run name>/<role>`: the node name of one process role of a run.
pub fn node_name(run_name: &str, role: &str) -> String {
    format!("{}{}", node_prefix(run_name), sanitize(role))
}

/// What every node name of a run starts with.
pub fn node_prefix(run_name: &str) -> String {
    format!("rfcl/{}/", sanitize(run_name))
}

/// A fresh id for one learner session: 16 hex digits from the process id, the clock and the
/// process's random hasher keys (no two sessions on a host share one in practice).
pub fn new_run_id() -> String {
    let mut h = RandomState::new().build_hasher();
    h.write_u32(std::process::id());
    h.write_u128(
        SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos()),
    );
    format!("{:016x}", h.finish())
}

/// This host's identity for choosing a transport: the machine id, the kernel's boot id and the
/// device of `/dev/shm`. Two processes share iceoryx2 shared memory only when all three match: the
/// boot id alone is the same in every container on a host, but each container usually has its own
/// `/dev/shm` mount. Parts that cannot be read are left empty (the actor then also checks that the
/// service opens).
pub fn host_identity() -> String {
    let read = |path: &str| {
        std::fs::read_to_string(path)
            .map(|s| s.trim().to_string())
            .unwrap_or_default()
    };
    let shm_dev = std::fs::metadata("/dev/shm")
        .map(|m| m.dev().to_string())
        .unwrap_or_default();
    format!(
        "machine-id={} boot-id={} shm-dev={}",
        read("/etc/machine-id"),
        read("/proc/sys/kernel/random/boot_id"),
        shm_dev
    )
}

/// Keeps `[A-Za-z0-9_.-]`, replaces anything else with `_`, and bounds the length.
fn sanitize(s: &str) -> String {
    let mut out: String = s
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.') {
                c
            } else {
                '_'
            }
        })
        .take(MAX_RUN_NAME)
        .collect();
    if out.is_empty() {
        out.push('_');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_per_run_and_session_and_safe() {
        let a = ServiceNames::new("pointmaze test/1", "00ff");
        assert_eq!(a.transitions, "rfcl/pointmaze_test_1/00ff/transitions");
        assert_eq!(a.policy, "rfcl/pointmaze_test_1/00ff/policy");
        assert_ne!(a, ServiceNames::new("pointmaze test/1", "00fe"));
        assert_eq!(node_name("run", "actor-3"), "rfcl/run/actor-3");
        assert!(node_name("run", "x").starts_with(&node_prefix("run")));
        assert_eq!(ServiceNames::new("", "").policy, "rfcl/_/_/policy");
    }

    #[test]
    fn run_ids_differ_and_the_host_identity_is_stable() {
        let (a, b) = (new_run_id(), new_run_id());
        assert_eq!(a.len(), 16);
        assert_ne!(a, b);
        assert_eq!(host_identity(), host_identity());
        assert!(host_identity().contains("boot-id="));
    }
}
