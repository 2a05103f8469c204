//! Read models built from the server state: the dashboard's view and the PointMaze heatmap's data.
//! They are built under the state's lock and rendered outside it.
use std::collections::BTreeMap;

use rfcl_core::maze::Cell;

use crate::dashboard::{
    ActorRow, DashboardView, DemoBar, DemoDifficulty, EvalPoint, LevelRow, MazeCell, MazeSnapshot,
    MazeView, RefusedReports, RunState,
};
use crate::state::{DemoResets, EvalAggregate, ServerState};
use crate::{LevelSource, Stage};

/// Heatmaps the PointMaze panel draws over a run.
pub const MAZE_SNAPSHOTS: usize = 6;

impl ServerState {
    /// The PointMaze heatmap's data: success per start cell at up to [`MAZE_SNAPSHOTS`] evals
    /// spread over the run (always the latest complete one), and the demos' paths. PointMaze
    /// states start with the point's `(x, y)` (spec 7.5: qpos then qvel).
    pub fn maze_view(&self, demos: &DemoResets) -> MazeView {
        let maze = rfcl_core::maze::maze();
        let cells = maze.start_cells();
        // An eval counts once it has covered every start cell (all evals but a running one).
        let complete: Vec<(&u64, &EvalAggregate)> = self
            .stats
            .evals
            .iter()
            .filter(|(_, e)| e.outcomes.len() >= cells.len())
            .collect();
        let picked: Vec<usize> = match complete.len() {
            0 => Vec::new(),
            n if n <= MAZE_SNAPSHOTS => (0..n).collect(),
            n => (0..MAZE_SNAPSHOTS)
                .map(|k| k * (n - 1) / (MAZE_SNAPSHOTS - 1))
                .collect(),
        };
        let snapshots = picked
            .into_iter()
            .map(|i| {
                let (version, e) = complete[i];
                let mut per_cell: BTreeMap<Cell, (u64, u64)> = BTreeMap::new();
                for &(seed, success) in &e.outcomes {
                    let c = per_cell.entry(maze.seed_cell(seed)).or_default();
                    c.0 += 1;
                    c.1 += success as u64;
                }
                MazeSnapshot {
                    policy_version: *version,
                    env_steps: e.env_steps,
                    success_rate: e.success_at_end as f64 / e.episodes.max(1) as f64,
                    cells: per_cell
                        .into_iter()
                        .map(|((row, col), (episodes, successes))| MazeCell {
                            row: row as u32,
                            col: col as u32,
                            episodes,
                            successes,
                        })
                        .collect(),
                }
            })
            .collect();
        let demo_paths = demos
            .states
            .iter()
            .map(|states| {
                states
                    .chunks_exact(demos.state_dim.max(2))
                    .map(|s| [s[0], s[1]])
                    .collect()
            })
            .collect();
        MazeView {
            map: rfcl_core::maze::MAP.lines().map(str::to_owned).collect(),
            snapshots,
            demo_paths,
        }
    }

    /// The dashboard's view of this state; a stage-1 demo stalls after `stall_after_env_steps`
    /// env steps without a move (docs/ALGORITHM.md 2.10).
    pub fn view(
        &self,
        run_name: &str,
        env_id: &str,
        now: f64,
        stall_after_env_steps: u64,
    ) -> DashboardView {
        let reverse = self.curriculum.reverse();
        let forward = self.curriculum.forward();
        let status = self.stage_status();
        let history = self.curriculum.difficulty();
        // After stage 1 the histories stand as they were when it ended.
        let stage_1_now = status.stage_1_end_env_steps.unwrap_or(self.stats.env_steps);
        let assessments = history.assess(reverse.demos(), stage_1_now, stall_after_env_steps);
        let demos = reverse
            .demos()
            .iter()
            .zip(assessments)
            .enumerate()
            .map(|(i, (d, a))| {
                let record = history.demos().get(i).cloned().unwrap_or_default();
                let failures = self.stats.failed_resets.per_demo.get(&(i as u32));
                DemoBar {
                    demo: i as u32,
                    // Known only to the service: `Shared::view` fills it in.
                    episode_id: 0,
                    t: d.start_step as u32,
                    states: d.num_states as u32,
                    frontier_success_rate: d.frontier_success_rate(),
                    solved: d.solved,
                    difficulty: DemoDifficulty {
                        episodes: record.episodes,
                        episode_share: a.episode_share,
                        frontier_episodes: record.frontier_episodes,
                        frontier_success_rate: a.frontier_success_rate,
                        speed: a.speed,
                        env_steps_since_move: a.env_steps_since_move,
                        solved_env_steps: record.solved_env_steps,
                        stalled: a.stalled,
                        cell: None,
                        frontier: record
                            .frontier
                            .iter()
                            .map(|&(steps, t)| [steps, u64::from(t)])
                            .collect(),
                        failed_resets: failures.map_or(0, |f| f.count),
                        last_reset_failure: failures
                            .map(|f| (f.last_start_index, f.last_reason.clone())),
                    },
                }
            })
            .collect();
        let levels = if status.stage == Stage::Forward {
            let probs = forward.probabilities();
            forward
                .levels()
                .iter()
                .zip(probs)
                .enumerate()
                .map(|(i, (l, p))| LevelRow {
                    level: i as u32,
                    label: match l.source {
                        LevelSource::Seed(s) => format!("seed {s}"),
                        LevelSource::DemoStart { demo, .. } => format!("demo {demo} start"),
                    },
                    score: l.score,
                    staleness: l.staleness,
                    probability: p,
                })
                .collect()
        } else {
            Vec::new()
        };
        let mut open_per_actor: BTreeMap<u32, u64> = BTreeMap::new();
        for g in self.leases.open_leases() {
            *open_per_actor.entry(g.actor_id).or_default() += 1;
        }
        let actors = self
            .stats
            .actors
            .iter()
            .map(|(id, a)| ActorRow {
                actor_id: *id,
                seconds_since_seen: (now - a.last_seen).max(0.0),
                env_steps: a.env_steps,
                episodes: a.episodes,
                open_leases: open_per_actor.get(id).copied().unwrap_or(0),
                sim_restarts: a.sim_restarts,
            })
            .collect();
        let evals = self
            .stats
            .evals
            .iter()
            .map(|(v, e)| EvalPoint {
                policy_version: *v,
                env_steps: e.env_steps,
                episodes: e.episodes,
                success_at_end: e.success_at_end as f64 / e.episodes.max(1) as f64,
                success_once: e.success_once as f64 / e.episodes.max(1) as f64,
                mean_return: e.return_sum / e.episodes.max(1) as f64,
            })
            .collect();
        let r = self.leases.refusals;
        DashboardView {
            run: RunState {
                run_name: run_name.to_string(),
                env_id: env_id.to_string(),
                stage: status.number(),
                finished: status.finished(),
                stage_epoch: status.epoch,
                env_steps: self.stats.env_steps,
                stage_1_env_steps: status.stage_1_end_env_steps,
                episodes: self.stats.episodes,
                expired_leases: self.leases.expired_total,
                sim_worker_restarts: self.stats.sim_worker_restarts(),
                failed_resets: self.stats.failed_resets.total(),
                refused_reports: RefusedReports {
                    duplicate: r.duplicate,
                    expired: r.expired,
                    unknown: r.unknown,
                    epoch_mismatch: r.epoch_mismatch,
                    malformed: self.stats.malformed_reports,
                    not_holder: r.not_holder,
                    over_time_limit: r.over_time_limit,
                },
                train_success_rate: self.stats.history.last().map(|p| p.train_success_rate),
                demos,
                evals,
            },
            episodes_per_s: self.stats.episodes_per_s,
            open_leases: self.leases.open_count() as u64,
            actors_forgotten: self.stats.actors_forgotten,
            // Known only to the snapshot writer: `Shared::view` fills it in.
            snapshot_failures: 0,
            // Known only to the gRPC service: `Shared::view` fills it in.
            unauthenticated_calls: 0,
            dashboard_refused: 0,
            oversized_requests: 0,
            solved_frac: reverse.solved_frac(),
            levels,
            actors,
            history: self.stats.history.clone(),
            maze: None,
            // Known only to the service: `Shared::view` fills it in.
            learner: None,
            videos: Vec::new(),
            videos_refused: 0,
            videos_evicted: 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Curriculum, DemoMeta};
    use rfcl_core::config::RunConfig;
    use rfcl_core::lease::ResetArgs;

    #[test]
    fn the_maze_view_spreads_snapshots_over_complete_evals_and_counts_cells() {
        let metas = [DemoMeta {
            success: vec![false, false, true],
            reset_seed: Some(0),
        }];
        let mut state =
            ServerState::new(Curriculum::new(&RunConfig::default(), &metas).unwrap(), 0.0);
        let cells = rfcl_core::maze::maze().start_cells().len() as u64;
        // Ten complete evals (one episode per start cell); version v solves cells with seed < v.
        for v in 1..=10u64 {
            let e = state.stats.evals.entry(v).or_default();
            e.env_steps = v * 1000;
            for seed in 0..cells {
                let success = seed < v;
                e.episodes += 1;
                e.success_at_end += success as u64;
                e.outcomes.push((100 * cells + seed, success));
            }
        }
        // A running eval that has not covered every cell yet is left out.
        state
            .stats
            .evals
            .entry(11)
            .or_default()
            .outcomes
            .push((0, true));
        let demos = DemoResets {
            state_dim: 5,
            states: vec![vec![7.0, 1.0, 0.0, 0.0, 0.0, 6.0, 1.0, 0.0, 0.0, 0.0]],
            reset: vec![ResetArgs::default()],
            episode_ids: vec![0],
        };
        let view = state.maze_view(&demos);
        let versions: Vec<u64> = view.snapshots.iter().map(|s| s.policy_version).collect();
        // 6 of 10, evenly: indices 0, 1, 3, 5, 7, 9.
        assert_eq!(versions, vec![1, 2, 4, 6, 8, 10]);
        let last = view.snapshots.last().unwrap();
        assert_eq!(last.cells.len() as u64, cells);
        assert_eq!(last.cells.iter().map(|c| c.successes).sum::<u64>(), 10);
        // Seed s starts in cell s mod 34 (row-major): seed 100*34 is the cell right of the goal.
        let first_cell = rfcl_core::maze::maze().seed_cell(0);
        let c = last
            .cells
            .iter()
            .find(|c| (c.row as usize, c.col as usize) == first_cell)
            .unwrap();
        assert_eq!((c.episodes, c.successes), (1, 1));
        assert_eq!(view.demo_paths, vec![vec![[7.0, 1.0], [6.0, 1.0]]]);
        assert_eq!(view.map.len(), 12);
    }
}
