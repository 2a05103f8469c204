//! The launcher's restart policy, pure: what `rfcl train` does when a child exits or stops
//! answering. No processes and no clock here: the supervisor feeds it deaths and silences with
//! the run's wall time and acts on its decisions.
//!
//! * A dead curriculum server or learner is restarted after a backoff (1, 2, 4, ... s, at most
//!   30 s); more than [`SERVICE_RESTARTS_MAX`] deaths of one service within
//!   [`SERVICE_RESTART_WINDOW_S`] mean it cannot run, and the run stops.
//! * An actor that exits with success is finished (the curriculum hands out no more leases); one
//!   that dies is respawned at once, up to [`ACTOR_RESPAWNS_MAX`] deaths within
//!   [`ACTOR_RESPAWN_WINDOW_S`].
//! * A service that lives but does not answer is said to be silent after a while and killed at
//!   `service.hang_timeout_s`, to be restarted as a dead one.
use std::collections::BTreeMap;

/// A service that dies more often than this within the window cannot run: the run stops.
pub const SERVICE_RESTARTS_MAX: usize = 3;
pub const SERVICE_RESTART_WINDOW_S: f64 = 600.0;
/// The same for one actor.
pub const ACTOR_RESPAWNS_MAX: usize = 5;
pub const ACTOR_RESPAWN_WINDOW_S: f64 = 120.0;

/// The two services `rfcl train` restarts when they die.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Service {
    Curriculum,
    Learner,
}

impl Service {
    /// The child's name, which is also its binary's.
    pub fn name(self) -> &'static str {
        match self {
            Service::Curriculum => "curriculum-server",
            Service::Learner => "learner",
        }
    }

    /// What it restarts from.
    pub fn saved_state(self) -> &'static str {
        match self {
            Service::Curriculum => "snapshot",
            Service::Learner => "checkpoint",
        }
    }
}

/// What to do with a service that died.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ServiceDecision {
    /// Start it again after this many seconds.
    Restart { delay_s: u64 },
    /// It died this many times within the window: stop the run.
    GiveUp { deaths: usize },
}

/// What to do with an actor that exited.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ActorDecision {
    /// Exited with success: not respawned.
    Finished,
    Respawn,
    /// It keeps dying: stop the run.
    GiveUp,
}

/// The deaths seen so far and the limits they are held to.
#[derive(Debug, Clone)]
pub struct RestartPolicy {
    services: RespawnLimiter,
    actors: RespawnLimiter,
}

impl Default for RestartPolicy {
    fn default() -> Self {
        Self {
            services: RespawnLimiter::new(SERVICE_RESTARTS_MAX, SERVICE_RESTART_WINDOW_S),
            actors: RespawnLimiter::new(ACTOR_RESPAWNS_MAX, ACTOR_RESPAWN_WINDOW_S),
        }
    }
}

impl RestartPolicy {
    /// `service` died (or failed to start again) at run wall time `now`.
    pub fn service_died(&mut self, service: Service, now: f64) -> ServiceDecision {
        let id = service as u32;
        let recent = self.services.recent(id, now);
        if self.services.allow(id, now) {
            ServiceDecision::Restart {
                delay_s: restart_delay_s(recent),
            }
        } else {
            ServiceDecision::GiveUp { deaths: recent + 1 }
        }
    }

    /// Actor `id` exited at run wall time `now`, with success or not.
    pub fn actor_exited(&mut self, id: u32, success: bool, now: f64) -> ActorDecision {
        if success {
            ActorDecision::Finished
        } else if self.actors.allow(id, now) {
            ActorDecision::Respawn
        } else {
            ActorDecision::GiveUp
        }
    }
}

/// Seconds to wait before restarting a service that has already been restarted `recent` times
/// within the limiter's window: 1, 2, 4, ... capped at 30, so a crash loop does not spin.
pub fn restart_delay_s(recent: usize) -> u64 {
    1u64.checked_shl(recent as u32).unwrap_or(u64::MAX).min(30)
}

/// At most `max` deaths of one process within `window_s` seconds.
#[derive(Debug, Clone)]
pub struct RespawnLimiter {
    max: usize,
    window_s: f64,
    deaths: BTreeMap<u32, Vec<f64>>,
}

impl RespawnLimiter {
    pub fn new(max: usize, window_s: f64) -> Self {
        Self {
            max,
            window_s,
            deaths: BTreeMap::new(),
        }
    }

    /// Deaths of `id` within the window before `now`.
    pub fn recent(&self, id: u32, now: f64) -> usize {
        self.deaths.get(&id).map_or(0, |d| {
            d.iter().filter(|&&t| now - t < self.window_s).count()
        })
    }

    /// Records a death of `id` at `now`; true when it may be started again.
    pub fn allow(&mut self, id: u32, now: f64) -> bool {
        let deaths = self.deaths.entry(id).or_default();
        deaths.retain(|t| now - t < self.window_s);
        deaths.push(now);
        deaths.len() <= self.max
    }
}

/// A service whose process lives but does not answer: said once after `warn_after_s`, killed
/// (to be restarted) after `kill_after_s`. Any answer resets it.
#[derive(Debug, Clone, Default)]
pub struct Silence {
    since: Option<f64>,
    warned: bool,
}

/// What [`Silence::silent`] asks the supervisor to do; each carries the seconds of silence.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SilenceAction {
    Wait,
    Warn(f64),
    Kill(f64),
}

impl Silence {
    pub fn answered(&mut self) {
        *self = Self::default();
    }

    /// A call at `now` went unanswered.
    pub fn silent(
        &mut self,
        now: f64,
        warn_after_s: f64,
        kill_after_s: Option<f64>,
    ) -> SilenceAction {
        let since = *self.since.get_or_insert(now);
        let silent_s = now - since;
        if kill_after_s.is_some_and(|kill| silent_s >= kill) {
            *self = Self::default();
            SilenceAction::Kill(silent_s)
        } else if silent_s >= warn_after_s && !self.warned {
            self.warned = true;
            SilenceAction::Warn(silent_s)
        } else {
            SilenceAction::Wait
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_dead_service_is_restarted_with_backoff_until_it_dies_too_often() {
        use ServiceDecision::{GiveUp, Restart};
        let mut p = RestartPolicy::default();
        let (learner, server) = (Service::Learner, Service::Curriculum);
        let deaths = [
            // Three deaths within the window: restarted after 1, 2, 4 s.
            (learner, 100.0, Restart { delay_s: 1 }),
            (learner, 110.0, Restart { delay_s: 2 }),
            (learner, 120.0, Restart { delay_s: 4 }),
            // The other service keeps its own count.
            (server, 125.0, Restart { delay_s: 1 }),
            // The fourth within 600 s stops the run.
            (learner, 130.0, GiveUp { deaths: 4 }),
            // Once the window has passed, the old deaths are forgotten.
            (learner, 800.0, Restart { delay_s: 1 }),
        ];
        for (service, at, decision) in deaths {
            assert_eq!(
                p.service_died(service, at),
                decision,
                "{service:?} at {at} s"
            );
        }
    }

    #[test]
    fn an_actor_that_finished_is_left_and_one_that_keeps_dying_stops_the_run() {
        let mut p = RestartPolicy::default();
        // Success never counts as a death.
        for t in 0..10 {
            assert_eq!(
                p.actor_exited(0, true, f64::from(t)),
                ActorDecision::Finished
            );
        }
        for t in [0.0, 10.0, 20.0, 30.0, 40.0] {
            assert_eq!(p.actor_exited(1, false, t), ActorDecision::Respawn);
        }
        // Another actor is not held to actor 1's deaths.
        assert_eq!(p.actor_exited(2, false, 45.0), ActorDecision::Respawn);
        assert_eq!(p.actor_exited(1, false, 50.0), ActorDecision::GiveUp);
        // Two minutes on, actor 1 may die again.
        assert_eq!(p.actor_exited(1, false, 200.0), ActorDecision::Respawn);
    }

    #[test]
    fn restarts_back_off_doubling_up_to_30_s() {
        assert_eq!(
            [0, 1, 2, 3, 4, 5, 6, 64].map(restart_delay_s),
            [1, 2, 4, 8, 16, 30, 30, 30]
        );
        let mut r = RespawnLimiter::new(3, 600.0);
        assert_eq!(r.recent(0, 0.0), 0);
        r.allow(0, 0.0);
        r.allow(0, 100.0);
        assert_eq!(
            (r.recent(0, 200.0), r.recent(0, 650.0), r.recent(1, 200.0)),
            (2, 1, 0)
        );
    }

    #[test]
    fn silence_warns_once_then_kills_and_an_answer_resets_it() {
        let mut s = Silence::default();
        assert_eq!(s.silent(100.0, 15.0, Some(60.0)), SilenceAction::Wait);
        assert_eq!(s.silent(110.0, 15.0, Some(60.0)), SilenceAction::Wait);
        assert_eq!(s.silent(116.0, 15.0, Some(60.0)), SilenceAction::Warn(16.0));
        assert_eq!(s.silent(130.0, 15.0, Some(60.0)), SilenceAction::Wait);
        // An answer starts the count again.
        s.answered();
        assert_eq!(s.silent(140.0, 15.0, Some(60.0)), SilenceAction::Wait);
        assert_eq!(s.silent(156.0, 15.0, Some(60.0)), SilenceAction::Warn(16.0));
        assert_eq!(s.silent(200.0, 15.0, Some(60.0)), SilenceAction::Kill(60.0));
        // After a kill the restarted service starts with a clean slate; without a timeout it is
        // only ever warned about.
        assert_eq!(s.silent(201.0, 15.0, None), SilenceAction::Wait);
        assert_eq!(s.silent(1_000.0, 15.0, None), SilenceAction::Warn(799.0));
        assert_eq!(s.silent(9_000.0, 15.0, None), SilenceAction::Wait);
    }
}
