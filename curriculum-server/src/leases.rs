//! The lease table: every reset lease handed out, until it is reported or expires.
//!
//! It makes reports exactly-once: a lease is applied on its first report; a repeat is acknowledged
//! and changes nothing; a report of an expired, unknown or other-epoch lease is refused, counted and
//! changes nothing. A report is also checked against its lease before it closes it: only the
//! actor that holds the lease may report it, and the episode cannot be longer than the lease's
//! time limit; such a refusal leaves the lease open for its real holder. Pure logic: time is
//! passed in, so tests control it.
//!
//! Lease ids are handed out in order, so the table needs no memory of reported leases: an id below
//! the next one that is neither open nor expired was reported. Only expired ids are remembered
//! (they are rare), up to a bound.
use std::collections::{BTreeSet, HashMap};

use serde::{Deserialize, Serialize};

/// What a lease was handed out for; returned when its report is accepted.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LeaseGrant<A> {
    pub lease_id: u64,
    pub actor_id: u32,
    pub stage_epoch: u64,
    /// Seconds (server clock) at which it was handed out.
    pub issued_at: f64,
    pub assignment: A,
}

/// Why a report was not applied.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ReportRefusal {
    #[error("lease {0} was already reported; nothing changed")]
    Duplicate(u64),
    #[error("lease {0} expired before its report arrived; nothing changed")]
    Expired(u64),
    #[error("lease {0} is unknown to this curriculum server")]
    Unknown(u64),
    #[error(
        "lease {lease_id} belongs to stage epoch {lease_epoch}, the report says {report_epoch}"
    )]
    EpochMismatch {
        lease_id: u64,
        lease_epoch: u64,
        report_epoch: u64,
    },
    #[error(
        "EpisodeReport.actor_id: lease {lease_id} is held by actor {holder}, the report says actor \
         {reporter}; only the holder may report it (the lease stays open)"
    )]
    NotHolder {
        lease_id: u64,
        holder: u32,
        reporter: u32,
    },
    #[error(
        "EpisodeReport.length: {length} steps, but lease {lease_id} allows at most {time_limit} \
         (its time limit); nothing changed and the lease stays open"
    )]
    OverTimeLimit {
        lease_id: u64,
        length: u32,
        time_limit: u32,
    },
}

/// Counts of refused reports, by cause (shown on the dashboard and in /metrics).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RefusalCounts {
    pub duplicate: u64,
    pub expired: u64,
    pub unknown: u64,
    pub epoch_mismatch: u64,
    /// Reports from an actor that does not hold the lease. Absent in older snapshots.
    #[serde(default)]
    pub not_holder: u64,
    /// Reports of episodes longer than their lease's time limit. Absent in older snapshots.
    #[serde(default)]
    pub over_time_limit: u64,
}

/// What a report claims, checked against its lease before the lease is closed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReportClaim {
    pub lease_id: u64,
    pub stage_epoch: u64,
    pub actor_id: u32,
    /// Env steps of the episode.
    pub length: u32,
}

/// Open leases and the ids of expired ones.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LeaseTable<A> {
    next_id: u64,
    open: HashMap<u64, LeaseGrant<A>>,
    expired: BTreeSet<u64>,
    expired_capacity: usize,
    pub expired_total: u64,
    pub refusals: RefusalCounts,
}

impl<A: Clone> LeaseTable<A> {
    /// `expired_capacity`: how many expired lease ids are remembered; a report of an older expired
    /// lease is refused as a duplicate instead of as expired (it changes nothing either way).
    pub fn new(expired_capacity: usize) -> Self {
        Self {
            next_id: 1,
            open: HashMap::new(),
            expired: BTreeSet::new(),
            expired_capacity: expired_capacity.max(1),
            expired_total: 0,
            refusals: RefusalCounts::default(),
        }
    }

    /// Hands out a new lease id (ids start at 1; 0 is never a lease).
    pub fn grant(
        &mut self,
        actor_id: u32,
        stage_epoch: u64,
        now: f64,
        assignment: A,
    ) -> &LeaseGrant<A> {
        let lease_id = self.next_id;
        self.next_id += 1;
        self.open.entry(lease_id).or_insert(LeaseGrant {
            lease_id,
            actor_id,
            stage_epoch,
            issued_at: now,
            assignment,
        })
    }

    /// Closes an open lease on its report, or says why the report must change nothing.
    /// `time_limit` says how many steps an episode of the lease may take.
    pub fn take_for_report(
        &mut self,
        claim: ReportClaim,
        time_limit: impl FnOnce(&LeaseGrant<A>) -> u32,
    ) -> Result<LeaseGrant<A>, ReportRefusal> {
        let lease_id = claim.lease_id;
        let refusal = match self.open.get(&lease_id) {
            Some(grant) if grant.stage_epoch != claim.stage_epoch => ReportRefusal::EpochMismatch {
                lease_id,
                lease_epoch: grant.stage_epoch,
                report_epoch: claim.stage_epoch,
            },
            Some(grant) if grant.actor_id != claim.actor_id => ReportRefusal::NotHolder {
                lease_id,
                holder: grant.actor_id,
                reporter: claim.actor_id,
            },
            Some(grant) => {
                let limit = time_limit(grant);
                if claim.length > limit {
                    ReportRefusal::OverTimeLimit {
                        lease_id,
                        length: claim.length,
                        time_limit: limit,
                    }
                } else {
                    return Ok(self.open.remove(&lease_id).expect("present"));
                }
            }
            None if lease_id == 0 || lease_id >= self.next_id => ReportRefusal::Unknown(lease_id),
            None if self.expired.contains(&lease_id) => ReportRefusal::Expired(lease_id),
            None => ReportRefusal::Duplicate(lease_id),
        };
        match refusal {
            ReportRefusal::Duplicate(_) => self.refusals.duplicate += 1,
            ReportRefusal::Expired(_) => self.refusals.expired += 1,
            ReportRefusal::Unknown(_) => self.refusals.unknown += 1,
            ReportRefusal::EpochMismatch { .. } => self.refusals.epoch_mismatch += 1,
            ReportRefusal::NotHolder { .. } => self.refusals.not_holder += 1,
            ReportRefusal::OverTimeLimit { .. } => self.refusals.over_time_limit += 1,
        }
        Err(refusal)
    }

    /// Expires every open lease issued before `now - timeout_s`; returns them.
    pub fn expire(&mut self, now: f64, timeout_s: f64) -> Vec<LeaseGrant<A>> {
        let stale: Vec<u64> = self
            .open
            .values()
            .filter(|g| now - g.issued_at > timeout_s)
            .map(|g| g.lease_id)
            .collect();
        self.close_all(stale)
    }

    fn close_all(&mut self, mut ids: Vec<u64>) -> Vec<LeaseGrant<A>> {
        ids.sort_unstable();
        let expired: Vec<_> = ids
            .into_iter()
            .filter_map(|id| self.open.remove(&id))
            .collect();
        for g in &expired {
            self.expired.insert(g.lease_id);
        }
        while self.expired.len() > self.expired_capacity {
            self.expired.pop_first();
        }
        self.expired_total += expired.len() as u64;
        expired
    }

    pub fn open_count(&self) -> usize {
        self.open.len()
    }

    pub fn open_leases(&self) -> impl Iterator<Item = &LeaseGrant<A>> {
        self.open.values()
    }

    /// Leases handed out so far.
    pub fn granted_total(&self) -> u64 {
        self.next_id - 1
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A report by actor 0 of a 1-step episode; every lease allows 100 steps.
    fn take<A: Clone>(
        t: &mut LeaseTable<A>,
        lease_id: u64,
        stage_epoch: u64,
    ) -> Result<LeaseGrant<A>, ReportRefusal> {
        let claim = ReportClaim {
            lease_id,
            stage_epoch,
            actor_id: 0,
            length: 1,
        };
        t.take_for_report(claim, |_| 100)
    }

    #[test]
    fn only_the_holder_may_report_and_no_longer_than_the_time_limit() {
        let mut t = LeaseTable::new(16);
        let id = t.grant(4, 0, 0.0, 20u32).lease_id;
        let claim = ReportClaim {
            lease_id: id,
            stage_epoch: 0,
            actor_id: 4,
            length: 20,
        };
        let limit = |g: &LeaseGrant<u32>| g.assignment;
        let stranger = ReportClaim {
            actor_id: 5,
            ..claim
        };
        assert_eq!(
            t.take_for_report(stranger, limit),
            Err(ReportRefusal::NotHolder {
                lease_id: id,
                holder: 4,
                reporter: 5
            })
        );
        let too_long = ReportClaim {
            length: u32::MAX,
            ..claim
        };
        let refusal = t.take_for_report(too_long, limit).unwrap_err();
        assert_eq!(
            refusal,
            ReportRefusal::OverTimeLimit {
                lease_id: id,
                length: u32::MAX,
                time_limit: 20
            }
        );
        assert!(
            refusal.to_string().contains("EpisodeReport.length")
                && refusal.to_string().contains("at most 20")
        );
        assert_eq!((t.refusals.not_holder, t.refusals.over_time_limit), (1, 1));
        // Both refusals left the lease open: its holder's report of 20 steps applies.
        assert_eq!(t.open_count(), 1);
        assert_eq!(t.take_for_report(claim, limit).unwrap().assignment, 20);
        // Older snapshots have no counts of these refusals.
        let old: RefusalCounts = serde_json::from_str(
            r#"{"duplicate": 1, "expired": 2, "unknown": 3, "epoch_mismatch": 4}"#,
        )
        .unwrap();
        assert_eq!((old.not_holder, old.over_time_limit), (0, 0));
    }

    #[test]
    fn a_report_applies_once_and_a_repeat_changes_nothing() {
        let mut t = LeaseTable::new(16);
        let id = t.grant(0, 0, 0.0, "demo 1").lease_id;
        assert_eq!(id, 1);
        assert_eq!(take(&mut t, id, 0).unwrap().assignment, "demo 1");
        assert_eq!(take(&mut t, id, 0), Err(ReportRefusal::Duplicate(id)));
        assert_eq!(t.refusals.duplicate, 1);
        assert_eq!(t.open_count(), 0);
    }

    #[test]
    fn expired_unknown_and_other_epoch_reports_are_refused_and_counted() {
        let mut t = LeaseTable::new(16);
        let old = t.grant(0, 0, 0.0, ()).lease_id;
        let fresh = t.grant(0, 0, 9.0, ()).lease_id;
        let expired = t.expire(10.5, 5.0);
        assert_eq!(
            expired.iter().map(|g| g.lease_id).collect::<Vec<_>>(),
            vec![old]
        );
        assert_eq!(take(&mut t, old, 0), Err(ReportRefusal::Expired(old)));
        assert_eq!(take(&mut t, 99, 0), Err(ReportRefusal::Unknown(99)));
        assert_eq!(
            take(&mut t, fresh, 1),
            Err(ReportRefusal::EpochMismatch {
                lease_id: fresh,
                lease_epoch: 0,
                report_epoch: 1
            })
        );
        // The refused report left the lease open: the right report still applies.
        assert!(take(&mut t, fresh, 0).is_ok());
        assert_eq!(
            t.refusals,
            RefusalCounts {
                duplicate: 0,
                expired: 1,
                unknown: 1,
                epoch_mismatch: 1,
                not_holder: 0,
                over_time_limit: 0,
            }
        );
        assert_eq!(t.expired_total, 1);
    }

    #[test]
    fn expired_memory_is_bounded_and_reported_ids_need_none() {
        let mut t = LeaseTable::new(2);
        for _ in 0..3 {
            t.grant(0, 0, 0.0, ());
        }
        assert_eq!(t.expire(10.0, 1.0).len(), 3);
        // Lease 1 fell out of the expired memory: refused as a duplicate; it still changes nothing.
        assert_eq!(take(&mut t, 1, 0), Err(ReportRefusal::Duplicate(1)));
        assert_eq!(take(&mut t, 3, 0), Err(ReportRefusal::Expired(3)));
        for _ in 0..10_000 {
            let id = t.grant(0, 0, 0.0, ()).lease_id;
            take(&mut t, id, 0).unwrap();
        }
        assert_eq!(take(&mut t, 4, 0), Err(ReportRefusal::Duplicate(4)));
        assert_eq!(take(&mut t, 0, 0), Err(ReportRefusal::Unknown(0)));
        let next = t.granted_total() + 1;
        assert_eq!(take(&mut t, next, 0), Err(ReportRefusal::Unknown(next)));
        let bytes = serde_json::to_string(&t).unwrap().len();
        assert!(bytes < 300, "no per-report memory: {bytes} bytes");
    }
}
