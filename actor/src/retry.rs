//! Exponential backoff with a deadline: how an actor retries a lost connection before it declares
//! the peer dead (a clear error and a non-zero exit, never a hang). Pure: time is passed in.
use std::time::{Duration, Instant};

/// Delays double from `initial` up to `max`; once the first failure of the current outage is
/// `give_up_after` old, [`Backoff::next_delay`] says to give up. [`Backoff::reset`] after a success
/// ends the outage.
#[derive(Debug, Clone)]
pub struct Backoff {
    initial: Duration,
    max: Duration,
    give_up_after: Duration,
    outage_since: Option<Instant>,
    next: Duration,
    attempts: u32,
}

impl Backoff {
    pub fn new(initial: Duration, max: Duration, give_up_after: Duration) -> Self {
        Self {
            initial,
            max,
            give_up_after,
            outage_since: None,
            next: initial,
            attempts: 0,
        }
    }

    /// The delay before the next attempt after a failure at `now`, or `None` when the outage has
    /// lasted `give_up_after`.
    pub fn next_delay(&mut self, now: Instant) -> Option<Duration> {
        let since = *self.outage_since.get_or_insert(now);
        let elapsed = now.saturating_duration_since(since);
        if elapsed >= self.give_up_after {
            return None;
        }
        let delay = self.next.min(self.give_up_after - elapsed);
        self.next = (self.next * 2).min(self.max);
        self.attempts += 1;
        Some(delay)
    }

    /// Failed attempts in the current outage.
    pub fn attempts(&self) -> u32 {
        self.attempts
    }

    /// A success: the next failure starts a new outage.
    pub fn reset(&mut self) {
        self.outage_since = None;
        self.next = self.initial;
        self.attempts = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn doubles_up_to_the_cap_then_gives_up_at_the_deadline() {
        let ms = Duration::from_millis;
        let mut b = Backoff::new(ms(100), ms(800), ms(2000));
        let t0 = Instant::now();
        assert_eq!(b.next_delay(t0), Some(ms(100)));
        assert_eq!(b.next_delay(t0 + ms(100)), Some(ms(200)));
        assert_eq!(b.next_delay(t0 + ms(300)), Some(ms(400)));
        assert_eq!(b.next_delay(t0 + ms(700)), Some(ms(800)));
        assert_eq!(
            b.next_delay(t0 + ms(1500)),
            Some(ms(500)),
            "clipped to the deadline"
        );
        assert_eq!(b.next_delay(t0 + ms(2000)), None);
        assert_eq!(b.attempts(), 5);
    }

    #[test]
    fn a_success_starts_over() {
        let ms = Duration::from_millis;
        let mut b = Backoff::new(ms(100), ms(800), ms(1000));
        let t0 = Instant::now();
        b.next_delay(t0);
        b.next_delay(t0 + ms(900));
        b.reset();
        assert_eq!(b.attempts(), 0);
        assert_eq!(b.next_delay(t0 + ms(5000)), Some(ms(100)));
    }
}
