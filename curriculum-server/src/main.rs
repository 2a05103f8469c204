//! `curriculum-server`: the single writer of RFCL curriculum state (spec sections 2-4), serving
//! reset leases over gRPC and the curriculum dashboard over HTTP.
use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;

#[derive(Parser)]
#[command(name = "curriculum-server", version, about = "RFCL curriculum server: reset leases over gRPC, dashboard over HTTP")]
struct Args {
    /// gRPC port (0 = pick a free one and print it).
    #[arg(long, default_value_t = 0)]
    port: u16,
    /// Demo file (ManiSkill-format .h5 with its .json sidecar).
    #[arg(long)]
    demos: PathBuf,
    /// Run config (YAML).
    #[arg(long)]
    config: PathBuf,
    /// Dashboard HTTP port (0 = pick a free one and print it).
    #[arg(long, default_value_t = 0)]
    dashboard_port: u16,
    /// Continue the curriculum from the snapshot in this run directory.
    #[arg(long, value_name = "RUN_DIR")]
    resume: Option<PathBuf>,
}

fn main() -> ExitCode {
    let args = Args::parse();
    eprintln!(
        "error: the curriculum service is not built yet (issue 4); asked to serve {} on port {}",
        args.demos.display(),
        args.port
    );
    ExitCode::FAILURE
}
