//! The whole curriculum through `acquire` / `report`: stage 1 to stage 2, stale reports, the
//! stage-only options.
use rfcl_core::config::RunConfig;
use rfcl_curriculum::{
    Applied, AssignmentKind, Curriculum, CurriculumError, DemoMeta, EpisodeOutcome, LevelSource,
    Resumed, Stage,
};

const SUCCESS: EpisodeOutcome = EpisodeOutcome {
    success_at_end: true,
    episode_return: 1.0,
};

/// `n` demos of 12 actions, the last 3 successful, reset with seeds 100, 101, ...
fn demos(n: u64) -> Vec<DemoMeta> {
    (0..n)
        .map(|i| DemoMeta {
            success: (0..12).map(|t| t >= 9).collect(),
            reset_seed: Some(100 + i),
        })
        .collect()
}

fn config() -> RunConfig {
    let mut config = RunConfig::default();
    config.forward.num_seeds = 10;
    config.env.max_episode_steps = 50;
    config
}

/// Reports success for every reset until a report ends stage 1; returns the env steps then.
fn solve_stage_1(curriculum: &mut Curriculum) -> u64 {
    for env_steps in 1..100_000 {
        let lease = curriculum.acquire().unwrap();
        let AssignmentKind::DemoState { .. } = lease.kind else {
            panic!("stage-1 lease {lease:?}");
        };
        let outcome = curriculum.report(&lease, SUCCESS, env_steps).unwrap();
        if let Some(change) = outcome.stage_change {
            assert_eq!(
                (change.from, change.epoch, change.env_steps),
                (Stage::Reverse, 1, env_steps)
            );
            return env_steps;
        }
    }
    panic!("stage 1 never ended");
}

#[test]
fn stage_1_ends_when_every_demo_is_solved_then_levels_are_handed_out() {
    let mut curriculum = Curriculum::new(&config(), &demos(5)).unwrap();
    let first = curriculum.acquire().unwrap();
    // S = 13, t = 12: every geometric draw clips to the last state; limit 16 + floor(1/3).
    assert_eq!(
        first.kind,
        AssignmentKind::DemoState {
            demo: first_demo(&first.kind),
            start_index: 12
        }
    );
    assert_eq!((first.time_limit, first.stage_epoch), (16, 0));

    let ended_at = solve_stage_1(&mut curriculum);
    let reverse = curriculum.reverse();
    // 5 of 5 solved (4 of 5 = 0.8 is not > 0.9).
    assert!(reverse
        .demos()
        .iter()
        .all(|d| d.solved && d.start_step == 0));
    assert_eq!(curriculum.stages().stage(), Stage::Forward);
    assert_eq!(curriculum.stages().stage_1_end_env_steps(), Some(ended_at));

    // The stage-1 lease is now stale.
    let stale = curriculum.report(&first, SUCCESS, ended_at + 1).unwrap();
    assert_eq!(stale.applied, Applied::Stale);

    // 10 seeds + 5 demo starts, stage-2 limit = H.
    let mut sources = Vec::new();
    for _ in 0..200 {
        let lease = curriculum.acquire().unwrap();
        assert_eq!((lease.time_limit, lease.stage_epoch), (50, 1));
        let AssignmentKind::Level { level, source } = lease.kind else {
            panic!("stage-2 lease {lease:?}");
        };
        assert_eq!(curriculum.forward().levels()[level].source, source);
        sources.push(source);
    }
    assert!(sources.contains(&LevelSource::DemoStart {
        demo: 4,
        reset_seed: Some(104)
    }));
    assert!(sources.contains(&LevelSource::Seed(9)));
}

fn first_demo(kind: &AssignmentKind) -> usize {
    match kind {
        AssignmentKind::DemoState { demo, .. } => *demo,
        AssignmentKind::Level { .. } => panic!("not a demo state"),
    }
}

#[test]
fn stage_2_reports_rescore_levels() {
    let mut config = config();
    config.train.stage_2_only = true;
    let mut curriculum = Curriculum::new(&config, &demos(2)).unwrap();
    let lease = curriculum.acquire().unwrap();
    let AssignmentKind::Level { level, .. } = lease.kind else {
        panic!("stage_2_only starts with levels: {lease:?}");
    };
    let outcome = curriculum.report(&lease, SUCCESS, 1).unwrap();
    assert_eq!(outcome.applied, Applied::Forward { level, score: 3.0 });
    assert_eq!(outcome.stage_change, None);
    // A score-3 level now takes nearly all of P_S.
    assert!(curriculum.forward().probabilities()[level] > 0.89);

    let mut wrong = lease;
    wrong.kind = AssignmentKind::DemoState {
        demo: 0,
        start_index: 0,
    };
    assert_eq!(
        curriculum.report(&wrong, SUCCESS, 2),
        Err(CurriculumError::WrongStage {
            kind: "demo-state",
            stage: Stage::Forward
        })
    );
}

#[test]
fn stage_1_only_finishes() {
    let mut config = config();
    config.train.stage_1_only = true;
    let mut curriculum = Curriculum::new(&config, &demos(1)).unwrap();
    solve_stage_1(&mut curriculum);
    assert_eq!(curriculum.stages().stage(), Stage::Finished);
    assert_eq!(curriculum.acquire(), Err(CurriculumError::Finished));
}

#[test]
fn failures_hold_the_frontier() {
    let mut curriculum = Curriculum::new(&config(), &demos(3)).unwrap();
    for step in 0..500 {
        let lease = curriculum.acquire().unwrap();
        let failure = EpisodeOutcome {
            success_at_end: false,
            episode_return: 0.0,
        };
        curriculum.report(&lease, failure, step).unwrap();
    }
    assert!(curriculum
        .reverse()
        .demos()
        .iter()
        .all(|d| d.start_step == 12 && !d.solved));
    assert_eq!(
        curriculum.reverse().demo_probabilities(),
        vec![1.0 / 3.0; 3]
    );
}

#[test]
fn rlpd_mode_hands_out_only_seeds_uniformly_and_reports_move_nothing() {
    let mut config = config();
    config.train.mode = rfcl_core::config::TrainMode::Rlpd;
    let mut curriculum = Curriculum::new(&config, &demos(2)).unwrap();
    // No demo-start levels: the 10 seeds only, each equally likely.
    let levels = curriculum.forward().levels();
    assert_eq!(levels.len(), 10);
    assert!(levels
        .iter()
        .all(|l| matches!(l.source, LevelSource::Seed(_))));
    let mut counts = [0u32; 10];
    for env_steps in 1..=2000 {
        let lease = curriculum.acquire().unwrap();
        let AssignmentKind::Level { level, .. } = lease.kind else {
            panic!("RLPD starts with levels only: {lease:?}");
        };
        counts[level] += 1;
        // A success would raise a level's score under RFCL; under RLPD it moves nothing.
        curriculum.report(&lease, SUCCESS, env_steps).unwrap();
        assert!(curriculum
            .forward()
            .probabilities()
            .iter()
            .all(|&p| (p - 0.1).abs() < 1e-12));
    }
    // 2000 uniform draws over 10 seeds: each near 200 (binomial sd 13.4; 5 sd either side).
    assert!(
        counts.iter().all(|&c| (133..=267).contains(&c)),
        "{counts:?}"
    );
    assert_eq!(curriculum.stages().stage(), Stage::Forward);
}

#[test]
fn a_stage_1_checkpoint_goes_on_into_stage_2_under_new_forward_options() {
    let mut stage_1_only = config();
    stage_1_only.train.stage_1_only = true;
    let mut curriculum = Curriculum::new(&stage_1_only, &demos(2)).unwrap();
    solve_stage_1(&mut curriculum);
    assert_eq!(curriculum.forward().levels().len(), 12);

    let mut variant = config();
    variant.forward.include_demo_starts = false;
    let resumed = curriculum.resume_under(&variant, &demos(2), 500).unwrap();
    assert_eq!(
        resumed.forward_adopted,
        ["forward.include_demo_starts: true -> false"]
    );
    assert!(resumed.reverse_ignored.is_empty());
    assert_eq!(
        resumed.stage_change.map(|c| (c.from, c.to)),
        Some((Stage::Finished, Stage::Forward))
    );
    // Only the 10 seeds are levels now.
    assert_eq!(curriculum.forward().levels().len(), 10);
    for _ in 0..50 {
        let lease = curriculum.acquire().unwrap();
        assert!(
            matches!(
                lease.kind,
                AssignmentKind::Level {
                    source: LevelSource::Seed(_),
                    ..
                }
            ),
            "{lease:?}"
        );
    }
}

#[test]
fn forward_options_cannot_change_once_stage_2_has_begun() {
    let mut curriculum = Curriculum::new(&config(), &demos(2)).unwrap();
    solve_stage_1(&mut curriculum);
    let before = curriculum.clone();
    let mut variant = config();
    variant.forward.staleness_coef = 0.5;
    let Err(err) = curriculum.resume_under(&variant, &demos(2), 500) else {
        panic!("a forward change in stage 2 was taken");
    };
    assert_eq!(
        err,
        CurriculumError::ChangedOnResume {
            changes: vec!["forward.staleness_coef: 0.1 -> 0.5".into()],
            why: "stage 2 has begun and its level scores were built under the old values",
        }
    );
    assert!(err
        .to_string()
        .contains("forward.staleness_coef: 0.1 -> 0.5"));
    assert_eq!(curriculum, before);
}

#[test]
fn reverse_options_are_refused_in_stage_1_and_reported_after_it() {
    let mut curriculum = Curriculum::new(&config(), &demos(2)).unwrap();
    let mut variant = config();
    variant.reverse.reverse_step_size = 8;
    let Err(CurriculumError::ChangedOnResume { changes, .. }) =
        curriculum.resume_under(&variant, &demos(2), 10)
    else {
        panic!("a reverse change in stage 1 was taken");
    };
    assert_eq!(changes, ["reverse.reverse_step_size: 4 -> 8"]);
    // Unchanged options resume as before.
    assert_eq!(
        curriculum.resume_under(&config(), &demos(2), 10),
        Ok(Resumed::default())
    );

    solve_stage_1(&mut curriculum);
    let resumed = curriculum.resume_under(&variant, &demos(2), 500).unwrap();
    assert_eq!(
        resumed.reverse_ignored,
        ["reverse.reverse_step_size: 4 -> 8"]
    );
    assert_eq!(curriculum.reverse().config().reverse_step_size, 4);
}

#[test]
fn the_horizon_is_refused_in_stage_1_and_taken_after_it() {
    let mut curriculum = Curriculum::new(&config(), &demos(2)).unwrap();
    let old = config().env.max_episode_steps;
    let mut longer = config();
    longer.env.max_episode_steps = old * 2;
    let Err(CurriculumError::ChangedOnResume { changes, .. }) =
        curriculum.resume_under(&longer, &demos(2), 10)
    else {
        panic!("a new horizon in stage 1 was taken");
    };
    assert_eq!(
        changes,
        [format!("env.max_episode_steps: {old} -> {}", old * 2)]
    );

    solve_stage_1(&mut curriculum);
    assert_eq!(curriculum.acquire().unwrap().time_limit, old);
    let resumed = curriculum.resume_under(&longer, &demos(2), 500).unwrap();
    assert_eq!(
        resumed.horizon_adopted,
        Some(format!("env.max_episode_steps: {old} -> {}", old * 2))
    );
    assert_eq!(curriculum.acquire().unwrap().time_limit, old * 2);
}
