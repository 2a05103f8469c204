//! PointMaze demonstrations: every start cell has a successful, collision-free demo that ends in
//! success states and replays exactly.

use rfcl_actor::pointmaze::demos::{
    demo_set, generate_demos, plan_demo, PointMazeDemo, SUCCESS_STEPS,
};
use rfcl_actor::pointmaze::{self, maze, PointMaze, ACTION_DIM, HORIZON, OBS_DIM, STATE_DIM};
use rfcl_actor::Env;
use rfcl_core::demo::DemoSet;
use serde_json::Value;

fn check_demo(demo: &PointMazeDemo) {
    let t = demo.len();
    let cell = demo.start_cell;
    assert!(
        t > SUCCESS_STEPS && t <= HORIZON,
        "demo from {cell:?} has {t} steps"
    );
    assert_eq!(demo.obs.len(), (t + 1) * OBS_DIM);
    assert_eq!(demo.actions.len(), t * ACTION_DIM);
    assert_eq!(demo.env_states.len(), (t + 1) * STATE_DIM);
    assert_eq!(cell, pointmaze::seed_cell(demo.reset_seed));

    // Successful, collision-free, ending with SUCCESS_STEPS success steps.
    assert!(demo.success[t - SUCCESS_STEPS..].iter().all(|&s| s));
    assert!(
        !demo.success[..t - SUCCESS_STEPS].iter().all(|&s| s),
        "starts outside the goal"
    );
    for i in 0..=t {
        assert_eq!(
            demo.obs_at(i)[6],
            0.0,
            "collision at step {i} from {cell:?}"
        );
        assert_eq!(demo.state_at(i)[4], 0.0);
        assert_eq!(
            demo.obs_at(i)[..4],
            demo.state_at(i)[..4],
            "obs carries qpos, qvel"
        );
    }
    assert!(demo.actions.iter().all(|a| (-1.0..=1.0).contains(a)));

    // The final state is a success state once restored: where the reverse curriculum starts.
    let mut env = PointMaze::new(0);
    env.reset_to_state(Some(demo.reset_seed), &Value::Null, demo.state_at(t))
        .unwrap();
    assert!(env.is_success());

    // Replaying the actions from the demo's reset reproduces every state and success flag.
    let obs = env
        .reset_to_seed(Some(demo.reset_seed), &Value::Null)
        .unwrap();
    assert_eq!(obs, demo.obs_at(0));
    for i in 0..t {
        let out = env.step(demo.action_at(i)).unwrap();
        assert_eq!(out.obs, demo.obs_at(i + 1));
        assert_eq!(out.success, demo.success[i]);
        assert_eq!(env.get_state(), demo.state_at(i + 1));
    }
}

#[test]
fn every_start_cell_has_a_successful_collision_free_demo() {
    for seed in 0..34u64 {
        let demo = plan_demo(seed).expect("a demo");
        check_demo(&demo);
        let path = maze().path_to_goal(demo.start_cell).unwrap();
        // About 5 steps per cell at 0.2 cells per step, plus the final success steps.
        assert!(
            demo.len() <= 6 * path.len() + SUCCESS_STEPS + 5,
            "{} steps",
            demo.len()
        );
    }
}

#[test]
fn a_demo_restarted_mid_way_from_its_state_matches_the_demo() {
    let demo = plan_demo(30).unwrap();
    let mid = demo.len() / 2;
    let mut env = PointMaze::new(77);
    let obs = env
        .reset_to_state(Some(30), &Value::Null, demo.state_at(mid))
        .unwrap();
    assert_eq!(obs, demo.obs_at(mid));
    for i in mid..demo.len() {
        assert_eq!(env.step(demo.action_at(i)).unwrap().obs, demo.obs_at(i + 1));
    }
}

#[test]
fn generated_demos_are_deterministic_and_start_from_distinct_cells() {
    let demos = generate_demos(34, 5);
    assert_eq!(demos, generate_demos(34, 5));
    let mut cells: Vec<_> = demos.iter().map(|d| d.start_cell).collect();
    cells.sort();
    assert_eq!(
        cells,
        pointmaze::start_cells(),
        "34 demos cover all 34 start cells once"
    );
    demos.iter().for_each(check_demo);

    let other: Vec<u64> = generate_demos(5, 6).iter().map(|d| d.reset_seed).collect();
    let first: Vec<u64> = demos[..5].iter().map(|d| d.reset_seed).collect();
    assert_ne!(other, first, "the seed shuffles the start cells");
    assert!(generate_demos(0, 5).is_empty());
}

#[test]
fn three_generated_demos_pass_every_start_cell() {
    // The maze's corridors form a tree with three dead ends, (10, 6), (3, 10) and (9, 3): the
    // greedy cover starts there, whatever the seed, and their paths pass all 34 start cells.
    for seed in [0, 1, 7] {
        let demos = generate_demos(3, seed);
        let starts: Vec<_> = demos.iter().map(|d| d.start_cell).collect();
        assert_eq!(starts, [(10, 6), (3, 10), (9, 3)], "seed {seed}");
        let passed: std::collections::BTreeSet<_> = demos
            .iter()
            .flat_map(|d| pointmaze::maze().path_to_goal(d.start_cell).unwrap())
            .collect();
        for cell in pointmaze::start_cells() {
            assert!(passed.contains(&cell), "no demo passes {cell:?}");
        }
    }
}

#[test]
fn demos_beyond_34_revisit_cells_with_new_seeds() {
    let demos = generate_demos(40, 1);
    for k in 34..40 {
        assert_eq!(demos[k].reset_seed, demos[k - 34].reset_seed + 34);
        assert_eq!(demos[k].start_cell, demos[k - 34].start_cell);
        assert_ne!(
            demos[k].obs_at(0),
            demos[k - 34].obs_at(0),
            "another jitter"
        );
        check_demo(&demos[k]);
    }
}

#[test]
fn demos_convert_to_a_demo_set_that_round_trips_through_the_file_format() {
    let demos = generate_demos(3, 2);
    let set = demo_set(demos.clone(), "unused.h5");
    assert_eq!(set.env_id.as_deref(), Some(pointmaze::ENV_ID));
    assert_eq!((set.obs_dim, set.action_dim, set.state_dim), (7, 2, 5));
    assert_eq!(set.state_layout, *PointMaze::new(0).state_layout());
    for (id, (demo, pm)) in set.demos.iter().zip(&demos).enumerate() {
        assert_eq!(demo.episode_id, id as u64);
        assert_eq!(demo.reset.seed, Some(pm.reset_seed));
        assert!(demo.succeeded);
        assert_eq!((&demo.obs, &demo.env_states), (&pm.obs, &pm.env_states));
    }

    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("pointmaze.h5");
    set.write(&path).expect("a valid demo set");
    let loaded = DemoSet::load(&path).expect("reads back");
    assert_eq!(loaded.demos, set.demos);
    assert_eq!(loaded.state_layout, set.state_layout);
    assert_eq!(loaded.env_id, set.env_id);

    // A loaded demo's last state, restored with its reset seed, is a success state.
    let demo = &loaded.demos[0];
    let mut env = PointMaze::new(0);
    env.reset_to_state(
        demo.reset.seed,
        &demo.reset.options,
        demo.state_row(demo.len()),
    )
    .unwrap();
    assert!(env.is_success());
}
