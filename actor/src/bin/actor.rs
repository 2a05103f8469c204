//! `actor`: steps simulator envs with the latest policy, resets them from curriculum leases and
//! streams transitions to the learner (docs/DESIGN.md, "Processes").
//!
//! It asks the learner for the run (GetRunInfo: env, dims, curriculum address, resolved config,
//! run seed, spec 6.4's action scale: with `train.data_action_scale` the envs get a / s), makes `--envs` envs, watches the learner's policies, and then either trains
//! (Acquire → reset → step until the lease's time limit → transitions over PushTransitions, a
//! Report per episode) or, with `--eval`, evaluates each policy that passes a multiple of
//! `sac.eval_freq` with the deterministic policy on EVAL leases (spec 5.7). Lost connections are
//! retried with backoff for `--retry-for` seconds; after that the actor exits non-zero.
//!
//! Transport (`--transport auto|shm|grpc`, `rfcl_actor::service::shm`): transitions and policies
//! go over iceoryx2 shared memory when the actor runs on the learner's host, over gRPC otherwise;
//! the choice and its reason are logged. The service itself is `rfcl_actor::service::serve`.

use std::process::ExitCode;
use std::time::Duration;

use anyhow::{anyhow, Context};
use clap::Parser;
use rfcl_actor::service::{self, shm};
use rfcl_proto::auth::ClientAuth;

#[derive(Parser)]
#[command(
    name = "actor",
    version,
    about = "RFCL actor: steps envs with the latest policy and streams transitions to the learner"
)]
struct Args {
    /// Learner address, e.g. http://127.0.0.1:50051 or host:port (the curriculum server's comes
    /// from it).
    #[arg(long, value_name = "ADDR", env = "RFCL_LEARNER")]
    connect: String,
    /// The curriculum server's address, when this actor reaches it by another name than the
    /// one the learner announces (an actor on another host).
    #[arg(long, value_name = "ADDR", env = "RFCL_CURRICULUM")]
    curriculum: Option<String>,
    /// Run the deterministic policy on held-out seeds and report eval outcomes (spec 5.7).
    #[arg(long)]
    eval: bool,
    /// Environments stepped by this actor, in lockstep.
    #[arg(long, default_value_t = 4)]
    envs: u32,
    /// Actor id (seeds derive from the run seed, the actor id and the env index). Default: one
    /// derived from the host name, so replicas of one container spec differ.
    #[arg(long, env = "RFCL_ACTOR_ID")]
    id: Option<u32>,
    /// Seconds a lost learner or curriculum server is retried before the actor gives up.
    #[arg(long, default_value_t = 30.0, value_name = "SECONDS")]
    retry_for: f64,
    /// How transitions and policies travel: shared memory on the learner's host (auto), always
    /// shared memory (shm: an error if the learner's services do not open), or gRPC.
    #[arg(long, value_enum, default_value_t = shm::Choice::Auto)]
    transport: shm::Choice,
}

fn main() -> ExitCode {
    rfcl_runtime::init_logging();
    let args = Args::parse();
    if !(args.retry_for.is_finite() && args.retry_for > 0.0) {
        return rfcl_runtime::fail(anyhow!(
            "--retry-for must be a positive number of seconds, got {}",
            args.retry_for
        ));
    }
    let auth = match ClientAuth::from_env() {
        Ok(auth) => auth,
        Err(e) => return rfcl_runtime::fail(e),
    };
    rfcl_actor::net::configure_inference_threads();
    let opts = service::Options {
        connect: args.connect,
        curriculum: args.curriculum,
        auth,
        eval: args.eval,
        envs: args.envs,
        id: args.id.unwrap_or_else(id_from_hostname),
        retry_for: Duration::from_secs_f64(args.retry_for),
        transport: args.transport,
    };
    let id = opts.id;
    rfcl_runtime::run(rfcl_runtime::Flavor::CurrentThread, async move {
        let stopped = service::serve(opts, rfcl_runtime::shutdown_signal())
            .await
            .with_context(|| format!("actor {id}"))?;
        tracing::info!(actor = id, "stopped: {stopped:?}");
        Ok(())
    })
}

/// An actor id from the host name and the process id: replicas started from one container spec
/// (distinct host names, the same pid) or by hand on one host (one host name, distinct pids) get
/// distinct ids, hence distinct seeds; a restarted container keeps its id. Ids below 2^20 stay
/// free for explicit `--id`s.
fn id_from_hostname() -> u32 {
    let name = std::fs::read_to_string("/proc/sys/kernel/hostname").unwrap_or_default();
    let key = format!("{}/{}", name.trim(), std::process::id());
    // FNV-1a: stable across builds and platforms (std's hasher is not guaranteed to be).
    let hash = key.bytes().fold(0x811c_9dc5u32, |h, b| {
        (h ^ b as u32).wrapping_mul(0x0100_0193)
    });
    (1 << 20) | (hash >> 12)
}
