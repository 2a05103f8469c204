//! Training metrics: `RUN_DIR/metrics.csv`, one row every `sac.log_freq` env steps with the tags
//! of spec 5.8 (`train/critic/critic_loss`, ..., `time/SPS`) and the learner's own
//! (`learner/*`: achieved UTD, buffer fill, drops, policy lag, where the time went).
//!
//! The same values go to TensorBoard ([`crate::tensorboard`], tag = column name, step =
//! `env_steps`): [`Row::fields`] is the one list both are written from.
//!
//! Rows are keyed by env steps, never by wall time, so curves of runs compare. On resume
//! the rows written after the checkpoint are removed, so a curve never has two points for one
//! step.
use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

use crate::sac::UpdateMetrics;

/// The CSV header, in column order.
pub const COLUMNS: &[&str] = &[
    "env_steps",
    "stage",
    "stage_epoch",
    "policy_version",
    "train/critic/critic_loss",
    "train/critic/q",
    "train/actor/actor_loss",
    "train/actor/entropy",
    "train/temp/temp",
    "train/temp/temp_loss",
    "train/training_steps",
    "train_stats/stage_1_steps",
    "time/SPS",
    "time/update_time",
    "time/total",
    "learner/iterations",
    "learner/utd",
    "learner/utd_target",
    "learner/updates_per_s",
    "learner/replay_online",
    "learner/replay_offline",
    "learner/replay_bytes",
    "learner/dropped_stale_epoch",
    "learner/policy_lag_max",
    "learner/wait_time",
    "learner/ingest_time",
    "learner/publish_time",
    "learner/checkpoint_time",
];

/// Means of the update metrics over the iterations of one logging window.
#[derive(Debug, Clone, Default)]
pub struct UpdateMeans {
    sums: [f64; 6],
    iterations: u64,
}

impl UpdateMeans {
    pub fn add(&mut self, m: &UpdateMetrics) {
        for (sum, (_, value)) in self.sums.iter_mut().zip(m.tagged()) {
            *sum += value;
        }
        self.iterations += 1;
    }

    pub fn iterations(&self) -> u64 {
        self.iterations
    }

    /// The six spec 5.8 update tags, `None` when no iteration ran in the window.
    pub fn means(&self) -> [Option<f64>; 6] {
        self.sums
            .map(|s| (self.iterations > 0).then(|| s / self.iterations as f64))
    }
}

/// Seconds spent per activity in one window (where the time goes).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Timings {
    pub wait: f64,
    pub ingest: f64,
    pub update: f64,
    pub publish: f64,
    pub checkpoint: f64,
}

/// One CSV row.
#[derive(Debug, Clone, Default)]
pub struct Row {
    pub env_steps: u64,
    pub stage: u32,
    pub stage_epoch: u64,
    pub policy_version: u64,
    pub updates: UpdateMeans,
    pub critic_updates_total: u64,
    pub stage_1_steps: Option<u64>,
    pub sps: f64,
    pub total_s: f64,
    pub iterations_total: u64,
    pub utd: f64,
    pub utd_target: f64,
    pub updates_per_s: f64,
    pub replay_online: usize,
    pub replay_offline: usize,
    pub replay_bytes: usize,
    pub dropped_stale_epoch: u64,
    pub policy_lag_max: u64,
    pub timings: Timings,
}

/// One cell of a row: integers are written as integers, `Missing` as an empty cell (a
/// TensorBoard event then has no point for that tag).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Cell {
    Int(u64),
    Float(f64),
    Missing,
}

impl Cell {
    fn text(self) -> String {
        match self {
            Cell::Int(v) => v.to_string(),
            Cell::Float(v) => v.to_string(),
            Cell::Missing => String::new(),
        }
    }

    fn value(self) -> Option<f64> {
        match self {
            Cell::Int(v) => Some(v as f64),
            Cell::Float(v) => Some(v),
            Cell::Missing => None,
        }
    }
}

impl Row {
    /// Every column with its cell, in [`COLUMNS`] order: the one list `metrics.csv` and the
    /// TensorBoard events are written from.
    pub fn fields(&self) -> Vec<(&'static str, Cell)> {
        let int = Cell::Int;
        let opt = |v: Option<f64>| v.map_or(Cell::Missing, Cell::Float);
        let mut cells = vec![
            int(self.env_steps),
            int(u64::from(self.stage)),
            int(self.stage_epoch),
            int(self.policy_version),
        ];
        cells.extend(self.updates.means().map(opt));
        cells.extend([
            int(self.critic_updates_total),
            self.stage_1_steps.map_or(Cell::Missing, int),
            Cell::Float(self.sps),
            Cell::Float(self.timings.update),
            Cell::Float(self.total_s),
            int(self.iterations_total),
            Cell::Float(self.utd),
            Cell::Float(self.utd_target),
            Cell::Float(self.updates_per_s),
            int(self.replay_online as u64),
            int(self.replay_offline as u64),
            int(self.replay_bytes as u64),
            int(self.dropped_stale_epoch),
            int(self.policy_lag_max),
            Cell::Float(self.timings.wait),
            Cell::Float(self.timings.ingest),
            Cell::Float(self.timings.publish),
            Cell::Float(self.timings.checkpoint),
        ]);
        debug_assert_eq!(cells.len(), COLUMNS.len());
        COLUMNS.iter().copied().zip(cells).collect()
    }

    fn cells(&self) -> Vec<String> {
        self.fields().into_iter().map(|(_, c)| c.text()).collect()
    }

    /// `(tag, value)` of every column but `env_steps` (the events' step) that has a value.
    pub fn scalars(&self) -> Vec<(&'static str, f64)> {
        self.fields()
            .into_iter()
            .skip(1)
            .filter_map(|(tag, c)| Some((tag, c.value()?)))
            .collect()
    }
}

/// `metrics.csv`, appended row by row (each row flushed).
#[derive(Debug)]
pub struct MetricsCsv {
    path: PathBuf,
    file: File,
}

impl MetricsCsv {
    /// Opens `path` for appending; writes the header to a new file. With `keep_until`, first
    /// removes the rows of env steps beyond it (a resume from a checkpoint at that step).
    pub fn open(path: &Path, keep_until: Option<u64>) -> std::io::Result<Self> {
        if let (Some(limit), true) = (keep_until, path.exists()) {
            let kept: Vec<String> = BufReader::new(File::open(path)?)
                .lines()
                .collect::<std::io::Result<Vec<_>>>()?
                .into_iter()
                .enumerate()
                .filter(|(i, line)| {
                    *i == 0
                        || line
                            .split(',')
                            .next()
                            .and_then(|s| s.parse::<u64>().ok())
                            .is_some_and(|step| step <= limit)
                })
                .map(|(_, line)| line + "\n")
                .collect();
            rfcl_core::atomic::atomic_write(path, kept.concat().as_bytes())?;
        }
        let new = !path.exists() || std::fs::metadata(path)?.len() == 0;
        let mut file = OpenOptions::new().create(true).append(true).open(path)?;
        if new {
            writeln!(file, "{}", COLUMNS.join(","))?;
        }
        Ok(Self {
            path: path.to_path_buf(),
            file,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn write(&mut self, row: &Row) -> std::io::Result<()> {
        writeln!(self.file, "{}", row.cells().join(","))?;
        self.file.flush()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_have_one_cell_per_column_and_resume_drops_later_rows() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.csv");
        let mut csv = MetricsCsv::open(&path, None).unwrap();
        let mut row = Row::default();
        for step in [100, 200, 300] {
            row.env_steps = step;
            csv.write(&row).unwrap();
        }
        row.updates.add(&UpdateMetrics {
            critic_loss: 1.0,
            q: 2.0,
            actor_loss: 3.0,
            entropy: 4.0,
            temp: 0.5,
            temp_loss: 6.0,
            critic_updates: 16,
            actor_updates: 16,
        });
        row.env_steps = 400;
        csv.write(&row).unwrap();
        drop(csv);
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], COLUMNS.join(","));
        assert!(lines.iter().all(|l| l.split(',').count() == COLUMNS.len()));
        let last: Vec<&str> = lines[4].split(',').collect();
        assert_eq!(last[4], "1");
        assert_eq!(last[8], "0.5");

        let mut csv = MetricsCsv::open(&path, Some(200)).unwrap();
        row.env_steps = 250;
        csv.write(&row).unwrap();
        let steps: Vec<String> = std::fs::read_to_string(&path)
            .unwrap()
            .lines()
            .skip(1)
            .map(|l| l.split(',').next().unwrap().to_string())
            .collect();
        assert_eq!(steps, ["100", "200", "250"]);
    }

    #[test]
    fn scalars_are_the_csv_cells_without_env_steps_and_empty_cells() {
        let mut row = Row {
            env_steps: 500,
            stage: 2,
            sps: 12.5,
            ..Row::default()
        };
        let tags: Vec<&str> = row.scalars().iter().map(|(t, _)| *t).collect();
        // No update ran and stage 1 has not ended: those cells are empty and have no scalar.
        assert!(!tags.contains(&"env_steps"));
        assert!(!tags.contains(&"train/critic/critic_loss"));
        assert!(!tags.contains(&"train_stats/stage_1_steps"));
        assert_eq!(tags.len(), COLUMNS.len() - 1 - 6 - 1);
        row.stage_1_steps = Some(400);
        let scalars = row.scalars();
        let get = |tag: &str| scalars.iter().find(|(t, _)| *t == tag).map(|(_, v)| *v);
        assert_eq!(get("stage"), Some(2.0));
        assert_eq!(get("time/SPS"), Some(12.5));
        assert_eq!(get("train_stats/stage_1_steps"), Some(400.0));
        let cells = row.cells();
        for (tag, value) in &scalars {
            let i = COLUMNS.iter().position(|c| c == tag).unwrap();
            assert_eq!(cells[i].parse::<f64>().unwrap(), *value, "{tag}");
        }
    }
}
