//! The lease table: every reset lease handed out, until it is reported or expires.
//!
//! It makes reports exactly-once: a lease is applied on its first report; a repeat is acknowledged
//! and changes nothing; a report of an expired, unknown or other-epoch lease is refused, counted and
//! changes nothing. Pure logic: time is passed in, so tests control it.
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
}

/// Counts of refused reports, by cause (shown on the dashboard and in /metrics).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RefusalCounts {
    pub duplicate: u64,
    pub expired: u64,
    pub unknown: u64,
    pub epoch_mismatch: u64,
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
    pub fn take_for_report(
        &mut self,
        lease_id: u64,
        report_epoch: u64,
    ) -> Result<LeaseGrant<A>, ReportRefusal> {
        let refusal = match self.open.get(&lease_id) {
            Some(grant) if grant.stage_epoch != report_epoch => ReportRefusal::EpochMismatch {
                lease_id,
                lease_epoch: grant.stage_epoch,
                report_epoch,
            },
            Some(_) => return Ok(self.open.remove(&lease_id).expect("present")),
            None if lease_id == 0 || lease_id >= self.next_id => ReportRefusal::Unknown(lease_id),
            None if self.expired.contains(&lease_id) => ReportRefusal::Expired(lease_id),
            None => ReportRefusal::Duplicate(lease_id),
        };
        match refusal {
            ReportRefusal::Duplicate(_) => self.refusals.duplicate += 1,
            ReportRefusal::Expired(_) => self.refusals.expired += 1,
            ReportRefusal::Unknown(_) => self.refusals.unknown += 1,
            ReportRefusal::EpochMismatch { .. } => self.refusals.epoch_mismatch += 1,
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

    #[test]
    fn a_report_applies_once_and_a_repeat_changes_nothing() {
        let mut t = LeaseTable::new(16);
        let id = t.grant(3, 0, 0.0, "demo 1").lease_id;
        assert_eq!(id, 1);
        assert_eq!(t.take_for_report(id, 0).unwrap().assignment, "demo 1");
        assert_eq!(t.take_for_report(id, 0), Err(ReportRefusal::Duplicate(id)));
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
        assert_eq!(t.take_for_report(old, 0), Err(ReportRefusal::Expired(old)));
        assert_eq!(t.take_for_report(99, 0), Err(ReportRefusal::Unknown(99)));
        assert_eq!(
            t.take_for_report(fresh, 1),
            Err(ReportRefusal::EpochMismatch {
                lease_id: fresh,
                lease_epoch: 0,
                report_epoch: 1
            })
        );
        // The refused report left the lease open: the right report still applies.
        assert!(t.take_for_report(fresh, 0).is_ok());
        assert_eq!(
            t.refusals,
            RefusalCounts {
                duplicate: 0,
                expired: 1,
                unknown: 1,
                epoch_mismatch: 1
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
        assert_eq!(t.take_for_report(1, 0), Err(ReportRefusal::Duplicate(1)));
        assert_eq!(t.take_for_report(3, 0), Err(ReportRefusal::Expired(3)));
        for _ in 0..10_000 {
            let id = t.grant(0, 0, 0.0, ()).lease_id;
            t.take_for_report(id, 0).unwrap();
        }
        assert_eq!(t.take_for_report(4, 0), Err(ReportRefusal::Duplicate(4)));
        assert_eq!(t.take_for_report(0, 0), Err(ReportRefusal::Unknown(0)));
        assert_eq!(
            t.take_for_report(t.granted_total() + 1, 0),
            Err(ReportRefusal::Unknown(t.granted_total() + 1))
        );
        assert_eq!(
            serde_json::to_string(&t).unwrap().len() < 300,
            true,
            "no per-report memory"
        );
    }
}
