//! `rfcl-sim-worker`: one Python simulator env (an adapter of `python/rfcl_sim/adapters`) served
//! over stdin/stdout to a [`rfcl_actor::python::PythonEnv`] in the actor, with the frames of
//! [`rfcl_actor::python::protocol`]. It embeds Python (pyo3); it is a process of its own so that a
//! simulator crash takes down only this env (see the `python` module docs of rfcl-actor).
//!
//! The protocol owns the real stdout: at start the worker moves it to a private descriptor and
//! points descriptor 1 at stderr, so that whatever Python or a C extension prints cannot corrupt a
//! frame. It exits when its stdin closes (its actor stopped or died).
//!
//! `--bench-steps N` instead measures the in-process rates (raw adapter steps timed in Python, and
//! steps through pyo3 calls with framing) and prints them as JSON: benches/RESULTS.md.
#![forbid(unsafe_code)]

mod embed;

use std::fs::File;
use std::io::{BufReader, BufWriter, Write};
use std::os::fd::AsFd;
use std::process::ExitCode;
use std::time::Instant;

use clap::Parser;
use rfcl_actor::python::protocol::{self, read_frame, write_frame};

#[derive(Parser)]
#[command(
    name = "rfcl-sim-worker",
    version,
    about = "One Python simulator env served to an rfcl actor over stdin/stdout (started by the actor)"
)]
struct Args {
    /// Suite: maniskill3, metaworld, adroit.
    #[arg(long)]
    suite: String,
    /// The simulator's env id, e.g. PickCube-v1.
    #[arg(long)]
    env_id: String,
    /// The adapter's keyword arguments, a JSON object.
    #[arg(long, default_value = "{}")]
    options: String,
    /// Measure in-process step rates for N steps and print them instead of serving.
    #[arg(long, value_name = "N")]
    bench_steps: Option<u32>,
}

fn main() -> ExitCode {
    let args = Args::parse();
    // The protocol's stdout, kept apart from descriptor 1 (which then goes to stderr).
    let out = match rustix::io::dup(std::io::stdout().as_fd())
        .and_then(|fd| rustix::stdio::dup2_stdout(std::io::stderr().as_fd()).map(|()| fd))
    {
        Ok(fd) => File::from(fd),
        Err(e) => {
            eprintln!("rfcl-sim-worker: cannot set up its output descriptors: {e}");
            return ExitCode::FAILURE;
        }
    };
    let mut out = BufWriter::new(out);
    let bridge = embed::Bridge::new(&args.suite, &args.env_id, &args.options);
    if let Some(n) = args.bench_steps {
        return bench(bridge, n, &mut out);
    }
    let bridge = match bridge {
        Ok(b) => b,
        Err(traceback) => {
            eprintln!(
                "rfcl-sim-worker: making {} of {} failed:\n{traceback}",
                args.env_id, args.suite
            );
            let _ = write_frame(&mut out, protocol::STATUS_EXCEPTION, traceback.as_bytes());
            return ExitCode::FAILURE;
        }
    };
    let (status, hello) = bridge.handle(protocol::OP_HELLO, &[]);
    if write_frame(&mut out, status, &hello).is_err() {
        return ExitCode::FAILURE;
    }
    let mut input = BufReader::new(std::io::stdin().lock());
    loop {
        match read_frame(&mut input) {
            Ok(Some(frame)) => {
                let (status, payload) = bridge.handle(frame.tag, &frame.payload);
                if let Err(e) = write_frame(&mut out, status, &payload) {
                    eprintln!("rfcl-sim-worker: writing an answer: {e}");
                    return ExitCode::FAILURE;
                }
            }
            Ok(None) => return ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("rfcl-sim-worker: reading a request: {e}");
                return ExitCode::FAILURE;
            }
        }
    }
}

/// In-process rates on this worker's adapter: `raw` (the adapter stepped from a Python loop)
/// and `pyo3` (each step a framed request through `Bridge.handle`, as the worker serves them).
fn bench(bridge: Result<embed::Bridge, String>, n: u32, out: &mut impl Write) -> ExitCode {
    let bridge = match bridge {
        Ok(b) => b,
        Err(traceback) => {
            eprintln!("{traceback}");
            return ExitCode::FAILURE;
        }
    };
    let (_, hello) = bridge.handle(protocol::OP_HELLO, &[]);
    let hello: protocol::Hello = serde_json::from_slice(&hello).expect("hello JSON");
    let raw = match bridge.raw_steps_per_s(n) {
        Ok(r) => r,
        Err(traceback) => {
            eprintln!("{traceback}");
            return ExitCode::FAILURE;
        }
    };
    bridge.handle(
        protocol::OP_RESET,
        &protocol::reset_request(Some(0), "{}", &[]),
    );
    let mut payload = Vec::new();
    let mut x = 0x2545_f491_4f6c_dd1du64;
    let start = Instant::now();
    for _ in 0..n {
        payload.clear();
        let action: Vec<f32> = (0..hello.action_dim)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                (x >> 40) as f32 / (1u64 << 23) as f32 - 1.0
            })
            .collect();
        protocol::put_f32s(&mut payload, &action);
        let (status, _) = bridge.handle(protocol::OP_STEP, &payload);
        if status != protocol::STATUS_OK {
            eprintln!("a bench step failed with status {status}");
            return ExitCode::FAILURE;
        }
    }
    let pyo3 = f64::from(n) / start.elapsed().as_secs_f64();
    let json = serde_json::json!({
        "env_id": hello.env_id,
        "steps": n,
        "raw_steps_per_s": raw,
        "in_process_pyo3_steps_per_s": pyo3,
        "python": hello.python,
    });
    let _ = writeln!(out, "{json}");
    let _ = out.flush();
    ExitCode::SUCCESS
}
