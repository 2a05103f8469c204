//! `cargo bench -p rfcl-learner`: SAC updates/s on CPU as JSON (see `rfcl_learner::bench`).
//! Environment: `RFCL_BENCH_SECONDS` (seconds per window), `RFCL_BENCH_WINDOWS` (best of N),
//! `RFCL_BENCH_THREADS`, `RFCL_BENCH_SCHEDULES` (`G/F,...`), `RFCL_BENCH_PRECISION=bf16`.
use rfcl_core::config::MatmulPrecision;
use rfcl_learner::bench::{run, BenchConfig};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut cfg = BenchConfig::default();
    if let Ok(seconds) = std::env::var("RFCL_BENCH_SECONDS") {
        cfg.window_seconds = seconds.parse()?;
    }
    if let Ok(windows) = std::env::var("RFCL_BENCH_WINDOWS") {
        cfg.windows = windows.parse()?;
    }
    if let Ok(threads) = std::env::var("RFCL_BENCH_THREADS") {
        cfg.threads = threads.parse()?;
    }
    if let Ok(schedules) = std::env::var("RFCL_BENCH_SCHEDULES") {
        // e.g. "80/20,16/1"
        cfg.schedules = schedules
            .split(',')
            .map(|s| {
                let (g, f) = s
                    .split_once('/')
                    .ok_or("RFCL_BENCH_SCHEDULES: expected G/F,...")?;
                Ok::<_, Box<dyn std::error::Error>>((g.parse()?, f.parse()?))
            })
            .collect::<Result<_, _>>()?;
    }
    if std::env::var("RFCL_BENCH_PRECISION").as_deref() == Ok("bf16") {
        cfg.matmul_precision = MatmulPrecision::Bf16;
    }
    let report = run(&cfg)?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}
