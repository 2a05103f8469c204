//! rfcl-core: the domain shared by every rfcl process, with no network I/O.
//!
//! * [`atomic`]: crash-safe file replacement for snapshots and checkpoints.
//! * [`checksum`]: self-checksummed JSON documents (checkpoint manifests, curriculum snapshots).
//! * [`config`]: the run configuration (every option of the RFCL spec), YAML resolution with
//!   `base_config` inheritance, dotted overrides and validation.
//! * [`error`]: an error and its causes on one line.
//! * [`demo`]: demonstration datasets in ManiSkill's trajectory format (HDF5 + JSON sidecar).
//! * [`final_counters`]: the learner's counters when it stops cleanly (`learner_final.json`).
//! * [`lease`]: reset leases and episode reports (the curriculum contract).
//! * [`maze`]: the fixed PointMaze layout (spec 7.5), for the native env and the dashboard.
//! * [`python`]: the Python interpreter the demo tools run under.
//! * [`ready`]: a service's ready line, printed once it serves and parsed by whoever started it.
//! * [`run_state`]: the run's state as the curriculum server tells other processes (`GetState`).
//! * [`run_lock`]: one owner per run directory and role (a kernel lock held while a process runs).
//! * [`transition`]: the one fixed binary layout of a transition record, shared by both transports.
//! * [`video`]: an eval episode's video and the file name that carries what it shows.
#![forbid(unsafe_code)]

pub mod atomic;
pub mod checksum;
pub mod config;
pub mod demo;
pub mod error;
pub mod final_counters;
pub mod lease;
pub mod maze;
pub mod python;
pub mod ready;
pub mod run_lock;
pub mod run_state;
pub mod transition;
pub mod video;

pub use config::RunConfig;
