//! `rfcl-health ADDR [--service NAME]`: asks the rfcl service at ADDR whether it is serving, over
//! the standard gRPC health protocol, and exits 0 when it is, 1 when it is not or does not answer
//! (with the reason on stderr). Container healthchecks run it; it needs no token, and speaks TLS
//! when `RFCL_TLS_CA` names the services' CA.
#![forbid(unsafe_code)]
use std::process::ExitCode;
use std::time::Duration;

use clap::Parser;
use rfcl_proto::auth::client_tls_from_env;
use rfcl_proto::health;
use tonic::transport::Endpoint;

#[derive(Parser)]
#[command(
    name = "rfcl-health",
    version,
    about = "Exit 0 when the rfcl service at ADDR is serving (grpc.health.v1)"
)]
struct Args {
    /// The service's gRPC address: host:port or http(s)://host:port.
    addr: String,
    /// The service to ask about, e.g. rfcl.v1.Curriculum or rfcl.v1.Learner (default: the server
    /// as a whole).
    #[arg(long, default_value = "")]
    service: String,
    /// Seconds to wait for an answer.
    #[arg(long, default_value_t = 3.0)]
    timeout: f64,
}

fn main() -> ExitCode {
    let args = Args::parse();
    match check(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("rfcl-health: {}: {e}", args.addr);
            ExitCode::FAILURE
        }
    }
}

fn check(args: &Args) -> Result<(), String> {
    let uri = if args.addr.contains("://") {
        args.addr.clone()
    } else {
        format!("http://{}", args.addr)
    };
    let mut endpoint = Endpoint::from_shared(uri).map_err(|e| format!("invalid address: {e}"))?;
    if let Some(tls) = client_tls_from_env().map_err(|e| e.to_string())? {
        endpoint = endpoint.tls_config(tls).map_err(|e| format!("TLS: {e}"))?;
    }
    let timeout = Duration::from_secs_f64(args.timeout.max(0.1));
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| format!("starting the async runtime: {e}"))?;
    match runtime.block_on(health::check(endpoint, &args.service, timeout))? {
        true => Ok(()),
        false => Err("not serving".into()),
    }
}
