//! `actor`: steps simulator envs with the latest policy, resets them from curriculum leases and
//! streams transitions to the learner.
use std::process::ExitCode;

use clap::Parser;

#[derive(Parser)]
#[command(
    name = "actor",
    version,
    about = "RFCL actor: steps envs with the latest policy and streams transitions to the learner"
)]
struct Args {
    /// Learner address, e.g. http://127.0.0.1:50051.
    #[arg(long, value_name = "ADDR")]
    connect: String,
    /// Run the deterministic policy on held-out seeds and report eval outcomes.
    #[arg(long)]
    eval: bool,
    /// Environments stepped by this actor.
    #[arg(long, default_value_t = 4)]
    envs: u32,
    /// Actor id (seeds derive from run seed, actor id and env index).
    #[arg(long, default_value_t = 0)]
    id: u32,
    /// Transition transport: auto (shared memory on the learner's host, gRPC elsewhere), shm, grpc.
    #[arg(long, default_value = "auto")]
    transport: String,
}

fn main() -> ExitCode {
    let args = Args::parse();
    eprintln!(
        "error: the actor service is not built yet (issue 6); asked to connect to {}",
        args.connect
    );
    ExitCode::FAILURE
}
