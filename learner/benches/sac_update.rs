//! `cargo bench -p rfcl-learner`: SAC updates/s on CPU as JSON (see `rfcl_learner::bench`).
//! Environment: `RFCL_BENCH_SECONDS` (seconds per window), `RFCL_BENCH_WINDOWS` (best of N),
//! `RFCL_BENCH_THREADS`, `RFCL_BENCH_PARALLELISM=ops` (default members), `RFCL_BENCH_BACKEND=fused`
//! (default libtorch), `RFCL_BENCH_SCHEDULES` (`G/F,...`), `RFCL_BENCH_PRECISION=bf16`,
//! `RFCL_BENCH_SHAPE` (`obs,action,batch,critics,hidden...`, e.g. `7,2,256,2,64,64` for the
//! PointMaze test agent).
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
    if std::env::var("RFCL_BENCH_PARALLELISM").as_deref() == Ok("ops") {
        cfg.parallelism = rfcl_core::config::Parallelism::Ops;
    }
    match std::env::var("RFCL_BENCH_BACKEND").as_deref() {
        Ok("fused") => cfg.backend = rfcl_core::config::Backend::Fused,
        Ok("libtorch") | Err(_) => {}
        Ok(other) => {
            return Err(format!("RFCL_BENCH_BACKEND: {other} is not libtorch or fused").into())
        }
    }
    if std::env::var("RFCL_BENCH_PRECISION").as_deref() == Ok("bf16") {
        cfg.matmul_precision = MatmulPrecision::Bf16;
    }
    if let Ok(shape) = std::env::var("RFCL_BENCH_SHAPE") {
        let v: Vec<u32> = shape.split(',').map(str::parse).collect::<Result<_, _>>()?;
        if v.len() < 5 {
            return Err("RFCL_BENCH_SHAPE: expected obs,action,batch,critics,hidden...".into());
        }
        cfg.obs_dim = v[0] as usize;
        cfg.action_dim = v[1] as usize;
        cfg.batch_size = v[2];
        cfg.critic_ensemble = v[3];
        cfg.target_pool = v[3];
        cfg.hidden = v[4..].to_vec();
    }
    let report = run(&cfg)?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}
