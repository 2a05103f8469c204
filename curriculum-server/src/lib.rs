//! RFCL curricula (docs/ALGORITHM.md sections 2-4) as pure logic, with no I/O.
//!
//! * [`rank`]: rank transforms and probability vectors (spec 3.4).
//! * [`reverse`]: stage 1, the per-demo reverse curriculum (spec 2).
//! * [`forward`]: stage 2, the seed-based forward curriculum (spec 3).
//! * [`stage`]: the stage machine and its epoch (spec 2.7, 4).
//! * [`stop`]: the run's stop rule on evaluation success.
//! * [`difficulty`]: per-demo stage-1 history and stall flags (rfcl's addition, section 2.10).
//! * [`curriculum`]: all of them behind `acquire` / `report`, with one seeded random stream;
//!   serialisable for snapshots.
#![forbid(unsafe_code)]

mod curriculum;
mod difficulty;
pub mod forward;
pub mod rank;
mod reverse;
mod stage;
pub mod stop;

pub use curriculum::{
    Applied, Assignment, AssignmentKind, Curriculum, CurriculumError, EpisodeOutcome,
    ReportOutcome, Resumed,
};
pub use difficulty::{DemoAssessment, DemoRecord, Difficulty};
pub use forward::{Forward, Level, LevelSource};
pub use reverse::{DemoMeta, DemoProgress, ReportEffect, Reverse, StartChoice};
pub use stage::{ReplanError, Stage, StageChange, StageMachine, StageStatus};

// The service around the pure logic.
//
// * `state`: the server state (curriculum, leases, counters) and its transitions, in domain types.
// * `views`: read models built from the state (the dashboard's view, the PointMaze heatmap).
// * `service`: the handles a running server shares between its tasks.
// * `grpc`: the tonic handlers, where wire messages are converted.
// * `learner_link`: the learner panel's Health polls.
// * `dashboard`: rendering of the views (page, charts, metrics); `server`: the process's tasks.
pub mod bench;
pub mod dashboard;
pub mod dashboard_listener;
mod grpc;
mod learner_link;
mod leases;
pub mod server;
pub mod service;
pub mod snapshot;
pub mod state;
pub mod videos;
mod views;
