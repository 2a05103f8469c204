//! The dashboard's `/metrics` endpoint: Prometheus (OpenMetrics) text.
use super::view::DashboardView;

/// Prometheus text exposition of the view, with `rfcl_curriculum_` names. Built per scrape from the
/// same view as the page, so the two never disagree.
pub fn metrics_text(view: &DashboardView, leases_granted: u64) -> String {
    use prometheus_client::encoding::text::encode;
    use prometheus_client::metrics::counter::Counter;
    use prometheus_client::metrics::family::Family;
    use prometheus_client::metrics::gauge::Gauge;
    use prometheus_client::registry::Registry;

    fn counter(registry: &mut Registry, name: &str, help: &str, value: u64) {
        let c: Counter = Counter::default();
        c.inc_by(value);
        registry.register(name, help, c);
    }
    fn gauge(registry: &mut Registry, name: &str, help: &str, value: f64) {
        let g: Gauge<f64, std::sync::atomic::AtomicU64> = Gauge::default();
        g.set(value);
        registry.register(name, help, g);
    }

    let mut r = Registry::with_prefix("rfcl_curriculum");
    gauge(
        &mut r,
        "stage",
        "Current stage (1 reverse, 2 forward)",
        view.run.stage as f64,
    );
    gauge(
        &mut r,
        "stage_epoch",
        "Stage epoch, bumped on every stage change",
        view.run.stage_epoch as f64,
    );
    counter(
        &mut r,
        "env_steps",
        "Env steps of reported train episodes",
        view.run.env_steps,
    );
    counter(
        &mut r,
        "episodes",
        "Reported train episodes",
        view.run.episodes,
    );
    gauge(
        &mut r,
        "episodes_per_second",
        "Reported train episodes per second (recent)",
        view.episodes_per_s,
    );
    counter(
        &mut r,
        "leases_granted",
        "Reset leases handed out",
        leases_granted,
    );
    gauge(
        &mut r,
        "leases_open",
        "Reset leases handed out and not yet reported",
        view.open_leases as f64,
    );
    counter(
        &mut r,
        "leases_expired",
        "Leases that expired unreported",
        view.run.expired_leases,
    );
    counter(
        &mut r,
        "unauthenticated_calls",
        "gRPC calls refused for a missing or wrong run token",
        view.unauthenticated_calls,
    );
    counter(
        &mut r,
        "oversized_requests",
        "gRPC calls refused for a request over the server's message limit",
        view.oversized_requests,
    );
    counter(
        &mut r,
        "dashboard_connections_refused",
        "Dashboard connections closed at once for being over the dashboard's bound",
        view.dashboard_refused,
    );
    counter(
        &mut r,
        "sim_worker_restarts",
        "Simulator worker processes restarted after a crash or hang (episode replayed)",
        view.run.sim_worker_restarts,
    );
    counter(
        &mut r,
        "failed_resets",
        "Leases an actor could not reset its env to (the episode never ran)",
        view.run.failed_resets,
    );
    counter(
        &mut r,
        "actors_forgotten",
        "Actor ids dropped from the per-actor table after service.forget_actors_after_s without a call",
        view.actors_forgotten,
    );
    counter(
        &mut r,
        "snapshot_failures",
        "Curriculum snapshot writes that failed",
        view.snapshot_failures,
    );
    gauge(
        &mut r,
        "solved_fraction",
        "Fraction of demos reverse-solved (docs/ALGORITHM.md 2.7)",
        view.solved_frac,
    );
    let refused = Family::<Vec<(String, String)>, Counter>::default();
    let rr = view.run.refused_reports;
    for (reason, v) in [
        ("duplicate", rr.duplicate),
        ("expired", rr.expired),
        ("unknown", rr.unknown),
        ("epoch_mismatch", rr.epoch_mismatch),
        ("malformed", rr.malformed),
        ("not_holder", rr.not_holder),
        ("over_time_limit", rr.over_time_limit),
    ] {
        refused
            .get_or_create(&vec![("reason".into(), reason.into())])
            .inc_by(v);
    }
    r.register(
        "reports_refused",
        "Reports that changed nothing, by reason",
        refused,
    );
    let start =
        Family::<Vec<(String, String)>, Gauge<f64, std::sync::atomic::AtomicU64>>::default();
    let solved = Family::<Vec<(String, String)>, Gauge>::default();
    let stalled = Family::<Vec<(String, String)>, Gauge>::default();
    let since_move = Family::<Vec<(String, String)>, Gauge>::default();
    let speed =
        Family::<Vec<(String, String)>, Gauge<f64, std::sync::atomic::AtomicU64>>::default();
    for d in &view.run.demos {
        let labels = vec![("demo".to_string(), d.demo.to_string())];
        start
            .get_or_create(&labels)
            .set(d.t as f64 / (d.states.max(2) - 1) as f64);
        solved.get_or_create(&labels).set(d.solved as i64);
        stalled
            .get_or_create(&labels)
            .set(d.difficulty.stalled as i64);
        since_move
            .get_or_create(&labels)
            .set(d.difficulty.env_steps_since_move.min(i64::MAX as u64) as i64);
        speed.get_or_create(&labels).set(d.difficulty.speed);
    }
    r.register(
        "demo_stalled",
        "1 when the demo's frontier stalled while others advanced (docs/ALGORITHM.md 2.10)",
        stalled,
    );
    r.register(
        "demo_env_steps_since_move",
        "Env steps since the demo's frontier last moved",
        since_move,
    );
    r.register(
        "demo_frontier_speed",
        "Demo states the frontier moved back per 10,000 env steps",
        speed,
    );
    r.register(
        "demo_start_step_fraction",
        "t_i / (S_i - 1) per demo",
        start,
    );
    r.register("demo_solved", "1 when the demo is reverse-solved", solved);
    let mut out = String::new();
    encode(&mut out, &r).expect("writing to a String cannot fail");
    out
}
