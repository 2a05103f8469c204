//! `learner`: ensemble SAC on libtorch with replay, transition ingest (shared memory and gRPC),
//! policy publication and checkpoints. The service is not built yet (issue 5): the library holds
//! the SAC maths and the replay buffers.
use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;

#[derive(Parser)]
#[command(
    name = "learner",
    version,
    about = "RFCL learner: ensemble SAC on libtorch, replay, ingest, policy publication"
)]
struct Args {
    /// gRPC port for actors (0 = a free one, printed on stdout).
    #[arg(long, default_value_t = 0)]
    port: u16,
    /// Run config (YAML).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Curriculum server address, e.g. http://127.0.0.1:50051.
    #[arg(long)]
    curriculum: Option<String>,
    /// Where the SAC updates run: cpu or cuda.
    #[arg(long, default_value = "cpu")]
    device: String,
    /// Continue from the checkpoint in this run directory.
    #[arg(long, value_name = "RUN_DIR")]
    resume: Option<PathBuf>,
}

fn main() -> ExitCode {
    let args = Args::parse();
    eprintln!(
        "error: the learner service is not built yet (issue 5); asked to listen on port {}",
        args.port
    );
    ExitCode::FAILURE
}
