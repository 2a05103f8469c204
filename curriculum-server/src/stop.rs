//! The run's stop rule (`service.stop_at_eval_success`): the run ends once the mean success at the
//! end of the last [`STOP_WINDOW`] complete evaluations reaches the bar. An evaluation is complete
//! once its policy version has [`episodes_per_eval`](rfcl_core::config::episodes_per_eval)
//! episodes. The curriculum server applies it (so a run ends the same way under any launcher);
//! `rfcl train` reports it.
use std::collections::BTreeMap;

use crate::state::EvalAggregate;

/// Evaluations whose running mean decides the stop.
pub const STOP_WINDOW: usize = 5;

/// Mean of the last [`STOP_WINDOW`] rates, once there are that many.
pub fn running_mean(rates: &[f64]) -> Option<f64> {
    (rates.len() >= STOP_WINDOW)
        .then(|| rates[rates.len() - STOP_WINDOW..].iter().sum::<f64>() / STOP_WINDOW as f64)
}

/// The complete evaluations: those with at least `episodes_needed` episodes (at least one).
fn complete(
    evals: &BTreeMap<u64, EvalAggregate>,
    episodes_needed: u64,
) -> impl Iterator<Item = (&u64, &EvalAggregate)> {
    evals
        .iter()
        .filter(move |(_, e)| e.episodes >= episodes_needed.max(1))
}

/// Success-at-end rates of the complete evaluations, in env-step order (policy versions break
/// ties).
pub fn complete_rates(evals: &BTreeMap<u64, EvalAggregate>, episodes_needed: u64) -> Vec<f64> {
    let mut complete: Vec<(u64, u64, f64)> = complete(evals, episodes_needed)
        .map(|(v, e)| (e.env_steps, *v, e.success_at_end as f64 / e.episodes as f64))
        .collect();
    complete.sort_by_key(|&(steps, version, _)| (steps, version));
    complete.into_iter().map(|(_, _, rate)| rate).collect()
}

/// The learner's env steps at the publication of the newest policy whose evaluation is complete:
/// where a (re)started eval actor's schedule goes on from (spec 5.7).
pub fn last_complete_env_steps(
    evals: &BTreeMap<u64, EvalAggregate>,
    episodes_needed: u64,
) -> Option<u64> {
    complete(evals, episodes_needed)
        .map(|(_, e)| e.env_steps)
        .max()
}

/// Whether the evaluations reached `bar` (never without a bar).
pub fn reached(
    evals: &BTreeMap<u64, EvalAggregate>,
    episodes_needed: u64,
    bar: Option<f64>,
) -> bool {
    match (bar, running_mean(&complete_rates(evals, episodes_needed))) {
        (Some(bar), Some(mean)) => mean >= bar,
        _ => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn eval(env_steps: u64, episodes: u64, successes: u64) -> EvalAggregate {
        EvalAggregate {
            env_steps,
            episodes,
            success_at_end: successes,
            ..EvalAggregate::default()
        }
    }

    #[test]
    fn the_mean_of_the_last_five_complete_evals_decides() {
        // Hand-computed: complete evals (10 episodes) at 1k..6k env steps with 2, 9, 8, 10, 9, 10
        // successes; the running eval at 7k (3 episodes) does not count. The last five rates:
        // 0.9, 0.8, 1.0, 0.9, 1.0 -> mean 0.92.
        let mut evals = BTreeMap::new();
        for (v, successes) in [2, 9, 8, 10, 9, 10].into_iter().enumerate() {
            evals.insert(v as u64 + 1, eval(1000 * (v as u64 + 1), 10, successes));
        }
        evals.insert(7, eval(7000, 3, 0));
        assert_eq!(complete_rates(&evals, 10).len(), 6);
        let mean = running_mean(&complete_rates(&evals, 10)).unwrap();
        assert!((mean - 0.92).abs() < 1e-12, "{mean}");
        assert!(reached(&evals, 10, Some(0.9)));
        assert!(!reached(&evals, 10, Some(0.93)));
        assert!(!reached(&evals, 10, None));
        // Four complete evals are not enough.
        assert_eq!(running_mean(&[1.0; 4]), None);
    }

    #[test]
    fn the_newest_complete_eval_is_where_a_restarted_eval_actor_goes_on() {
        let mut evals = BTreeMap::new();
        assert_eq!(last_complete_env_steps(&evals, 10), None);
        evals.insert(3, eval(20_008, 10, 0));
        evals.insert(7, eval(40_016, 10, 1));
        // An evaluation cut short by a stop (4 of 10 episodes) is not complete.
        evals.insert(9, eval(60_000, 4, 0));
        assert_eq!(last_complete_env_steps(&evals, 10), Some(40_016));
        assert_eq!(last_complete_env_steps(&evals, 4), Some(60_000));
    }

    #[test]
    fn evals_are_ordered_by_env_steps() {
        let mut evals = BTreeMap::new();
        // Version 9 was evaluated at fewer env steps than version 3 (ids need not follow steps).
        evals.insert(3, eval(5000, 10, 10));
        evals.insert(9, eval(1000, 10, 0));
        assert_eq!(complete_rates(&evals, 10), vec![0.0, 1.0]);
    }
}
