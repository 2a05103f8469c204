//! Tests of the dashboard's rendering, over one small view.
use super::*;

fn view() -> DashboardView {
    DashboardView {
        run: RunState {
            run_name: "test <run>".into(),
            env_id: "PointMaze-v0".into(),
            stage: 1,
            env_steps: 106_000,
            demos: demos(),
            ..Default::default()
        },
        history: vec![
            ProgressPoint {
                wall_s: 0.0,
                env_steps: 0,
                stage: 1,
                start_step_frac_avg: 1.0,
                solved_frac: 0.0,
                train_success_rate: 0.0,
            },
            ProgressPoint {
                wall_s: 5.0,
                env_steps: 800,
                stage: 1,
                start_step_frac_avg: 0.6,
                solved_frac: 0.5,
                train_success_rate: 0.4,
            },
        ],
        ..Default::default()
    }
}

fn demos() -> Vec<DemoBar> {
    vec![
        DemoBar {
            demo: 0,
            episode_id: 3,
            t: 10,
            states: 41,
            frontier_success_rate: 0.5,
            solved: false,
            difficulty: DemoDifficulty {
                episodes: 30,
                episode_share: 0.75,
                frontier_episodes: 12,
                frontier_success_rate: 0.25,
                speed: 1.5,
                env_steps_since_move: 61_000,
                solved_env_steps: None,
                stalled: true,
                cell: Some([4, 9]),
                frontier: vec![[20_000, 32], [45_000, 10]],
                failed_resets: 0,
                last_reset_failure: None,
            },
        },
        DemoBar {
            demo: 1,
            episode_id: 7,
            t: 0,
            states: 30,
            frontier_success_rate: 1.0,
            solved: true,
            difficulty: DemoDifficulty {
                episodes: 10,
                episode_share: 0.25,
                frontier_episodes: 8,
                frontier_success_rate: 0.875,
                speed: 4.0,
                env_steps_since_move: 0,
                solved_env_steps: Some(72_000),
                stalled: false,
                cell: Some([1, 2]),
                frontier: vec![[30_000, 21], [50_000, 13], [60_000, 5], [66_000, 0]],
                failed_resets: 0,
                last_reset_failure: None,
            },
        },
    ]
}

#[test]
fn the_page_flags_stalled_demos_with_where_they_stall_and_charts_each_frontier() {
    let html = render_html(&view(), 2);
    assert!(html.contains("stalled at state 10 (cell 4, 9)"), "{html}");
    assert_eq!(html.matches("stalled at state").count(), 1, "{html}");
    assert!(html.contains("1 demo(s) stalled"), "{html}");
    assert!(html.contains("demo 0 (stalled)") && html.contains("demo 1 &nbsp;"));
    // The frontier chart: one step line per demo, the stalled one drawn thicker.
    let svg = demo_frontiers_svg(&view().run.demos, 106_000);
    assert_eq!(svg.matches("stroke-width=\"4\"").count(), 1, "{svg}");
    assert_eq!(svg.matches("stroke-width=\"2\"").count(), 1, "{svg}");
    // The progress chart's legend is under it, not over the curves.
    assert!(html.contains("eval success at end"));
    assert!(!progress_svg(&view().history, &[]).contains("eval success at end"));
}

#[test]
fn the_page_has_one_bar_row_per_demo_and_escapes_names() {
    let html = render_html(&view(), 2);
    assert_eq!(html.matches("class=\"demo-bar\"").count(), 2);
    assert!(html.contains("test &lt;run&gt;"));
    assert!(html.contains("http-equiv=\"refresh\" content=\"2\""));
    assert!(!html.contains("chart failed"));
}

#[test]
fn the_page_shows_sim_worker_restarts_in_total_and_per_actor() {
    let mut v = view();
    v.run.sim_worker_restarts = 7;
    v.actors = vec![ActorRow {
        actor_id: 3,
        seconds_since_seen: 1.0,
        env_steps: 100,
        episodes: 4,
        open_leases: 1,
        sim_restarts: 7,
    }];
    let html = render_html(&v, 2);
    assert!(html.contains("sim worker restarts 7"), "{html}");
    assert!(
        html.contains("<td>100</td><td>4</td><td>1</td><td>7</td></tr>"),
        "{html}"
    );
}

#[test]
fn the_page_shows_failed_resets_in_total_and_per_demo_with_the_reason() {
    let mut v = view();
    v.run.failed_resets = 3;
    v.run.demos[1].difficulty.failed_resets = 3;
    v.run.demos[1].difficulty.last_reset_failure = Some((
        12,
        "state field `collided` is invalid: 50 <is> neither 0 nor 1".into(),
    ));
    let html = render_html(&v, 2);
    assert!(html.contains("failed resets 3"), "{html}");
    assert!(
        html.contains("3 failed reset(s), last at state 12</span>"),
        "{html}"
    );
    assert!(html.contains("50 &lt;is&gt; neither"), "{html}");
    let text = metrics_text(&v, 1);
    assert!(
        text.contains("rfcl_curriculum_failed_resets_total 3"),
        "{text}"
    );
}

#[test]
fn demo_bars_are_svg_rectangles() {
    let svg = demo_bars_svg(&view().run.demos);
    assert!(svg.starts_with("<svg"));
    // Background + plot area + one filled rectangle per demo at least.
    assert!(svg.matches("<rect").count() >= 3, "{svg}");
    assert!(svg.contains("demo 1"));
}

#[test]
fn metrics_use_rfcl_names_and_labels() {
    let mut v = view();
    v.run.refused_reports.duplicate = 3;
    v.run.refused_reports.over_time_limit = 4;
    v.run.refused_reports.not_holder = 5;
    v.actors_forgotten = 6;
    v.snapshot_failures = 7;
    v.run.sim_worker_restarts = 2;
    let text = metrics_text(&v, 42);
    for line in [
        "rfcl_curriculum_sim_worker_restarts_total 2",
        "rfcl_curriculum_leases_granted_total 42",
        "rfcl_curriculum_reports_refused_total{reason=\"duplicate\"} 3",
        "rfcl_curriculum_reports_refused_total{reason=\"over_time_limit\"} 4",
        "rfcl_curriculum_reports_refused_total{reason=\"not_holder\"} 5",
        "rfcl_curriculum_actors_forgotten_total 6",
        "rfcl_curriculum_snapshot_failures_total 7",
        "rfcl_curriculum_demo_solved{demo=\"1\"} 1",
        "rfcl_curriculum_demo_stalled{demo=\"0\"} 1",
        "rfcl_curriculum_demo_stalled{demo=\"1\"} 0",
        "rfcl_curriculum_demo_env_steps_since_move{demo=\"0\"} 61000",
        "rfcl_curriculum_demo_frontier_speed{demo=\"1\"} 4.0",
    ] {
        assert!(text.contains(line), "{line} missing from {text}");
    }
    assert!(text.ends_with("# EOF\n"));
}

fn maze() -> MazeView {
    let snapshot = |steps: u64, successes: u64| MazeSnapshot {
        policy_version: steps / 100,
        env_steps: steps,
        success_rate: successes as f64 / 2.0,
        cells: vec![
            MazeCell {
                row: 1,
                col: 2,
                episodes: 1,
                successes: 1,
            },
            MazeCell {
                row: 1,
                col: 3,
                episodes: 1,
                successes: successes - 1,
            },
        ],
    };
    MazeView {
        map: vec!["####".into(), "#G..".into(), "####".into()],
        snapshots: vec![snapshot(5000, 1), snapshot(9000, 2)],
        demo_paths: vec![vec![[3.0, 1.0], [2.0, 1.0], [1.0, 1.0]]],
    }
}

#[test]
fn the_maze_heatmap_has_a_cell_per_map_square_per_snapshot() {
    let m = maze();
    let svg = maze_heatmap_svg(&m);
    assert!(svg.starts_with("<svg"), "{svg}");
    // Background + 12 squares in each of the two panels: more than 2 × 12.
    assert!(svg.matches("<rect").count() > 2 * 12, "{svg}");
    assert!(
        svg.contains("5000 steps: 50%") && svg.contains("9000 steps: 100%"),
        "{svg}"
    );
    // The goal (red circle) in each panel and a demo path.
    assert_eq!(svg.matches("<circle").count(), 2, "{svg}");
    assert!(svg.contains("<polyline"), "{svg}");
    let mut v = view();
    v.maze = Some(m);
    let html = render_html(&v, 2);
    assert!(html.contains("id=\"maze-heatmap\""));
    assert!(!html.contains("chart failed"));
    // No heatmap section for other suites.
    assert!(!render_html(&view(), 2).contains("maze-heatmap"));
}

#[test]
fn empty_views_render() {
    let html = render_html(&DashboardView::default(), 5);
    assert!(html.contains("<svg"));
    assert!(level_probabilities_svg(&[]).starts_with("<svg"));
}

#[test]
fn the_learner_panel_shows_rates_losses_and_where_the_time_goes() {
    let mut v = view();
    let html = render_html(&v, 2);
    assert!(
        html.contains("No learner has announced itself yet"),
        "{html}"
    );

    v.learner = Some(LearnerPanel {
        address: "http://learner:50052".into(),
        seconds_since_answer: Some(1.0),
        error: None,
        ok: true,
        env_steps: 40_000,
        critic_updates: 640_000,
        policy_version: 12,
        run_id: "r1".into(),
        window: Some(LearnerWindowView {
            seconds: 10.0,
            updates_per_s: 31.5,
            env_steps_per_s: 2.0,
            utd: 15.9,
            utd_target: 16.0,
            policy_lag_max: 2,
            critic_loss: Some(0.125),
            actor_loss: Some(-3.5),
            q: Some(4.25),
            entropy: None,
            temperature: Some(0.05),
            time_shares: TimeShares {
                waiting: 0.1,
                ingesting: 0.05,
                updating: 0.8,
                publishing: 0.02,
                checkpointing: 0.0,
            },
        }),
    });
    let html = render_html(&v, 2);
    for expected in [
        "<code>http://learner:50052</code> (answered 1 s ago)",
        "updates/s <b>31.5</b>",
        "UTD 15.90 (target 16.00)",
        "policy lag ≤ 2",
        "critic loss 0.1250",
        "actor loss -3.5000",
        "mean Q 4.2500",
        "temperature 0.0500",
        "entropy –",
        "updating 80%",
        "waiting for data 10%",
        "publishing the policy 2%",
    ] {
        assert!(html.contains(expected), "{expected}: {html}");
    }
    assert_eq!(html.matches("<div title=").count(), 5);

    // A failed poll keeps the last answer and says why.
    let panel = v.learner.as_mut().unwrap();
    panel.error = Some("Health at http://learner:50052: no answer within 2 s".into());
    let html = render_html(&v, 2);
    assert!(html.contains("<p class=err>Health at http://learner:50052: no answer within 2 s</p>"));
    assert!(html.contains("updates/s <b>31.5</b>"));
}

#[test]
fn the_eval_table_links_each_policys_recorded_episodes() {
    let mut v = view();
    let eval = |policy_version, env_steps| EvalPoint {
        policy_version,
        env_steps,
        episodes: 20,
        success_at_end: 0.5,
        success_once: 0.6,
        mean_return: 3.0,
    };
    v.run.evals = vec![eval(4, 20_000), eval(9, 40_000)];
    let html = render_html(&v, 2);
    assert!(!html.contains("eval episode(s) recorded"), "{html}");

    let meta = rfcl_core::video::VideoMeta {
        policy_version: 9,
        env_steps: 40_000,
        seed: 1_000_021,
        success_at_end: true,
        episode_return: 12.0,
        actor_id: 2,
    };
    v.videos = vec![VideoLink::from(meta)];
    v.videos_refused = 1;
    v.videos_evicted = 3;
    let html = render_html(&v, 2);
    let link = "<a href=\"/videos/v000009_steps40000_seed1000021_success_return12.0_actor2.gif\">";
    assert!(
        html.contains(&format!("{link}seed 1000021 (success)</a></td></tr>")),
        "{html}"
    );
    // Only policy 9's row has one; the line under the table links the latest and counts refusals.
    assert_eq!(html.matches(link).count(), 2, "{html}");
    assert!(
        html.contains("1 eval episode(s) recorded; the latest: "),
        "{html}"
    );
    assert!(html.contains("<span class=err>1 refused</span>"), "{html}");
    assert!(
        html.contains("; 3 older one(s) removed to keep within the videos' bounds."),
        "{html}"
    );
}
