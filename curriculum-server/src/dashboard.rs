//! The curriculum dashboard: one self-refreshing HTML page (no JavaScript build step, charts drawn
//! server-side as SVG with plotters), the same data as JSON, and Prometheus text.
//!
//! Rendering is pure: [`DashboardView`] in, strings out. The service builds the view under its lock
//! and renders outside it.
use std::fmt::Write as _;

use plotters::prelude::*;
use serde::{Deserialize, Serialize};

/// Everything the dashboard shows; `/api/state` serves it as JSON.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DashboardView {
    pub run_name: String,
    pub env_id: String,
    pub stage: u32,
    pub stage_epoch: u64,
    /// The run is over: nothing more is handed out (the stop rule, or stage 1 under
    /// `stage_1_only`).
    #[serde(default)]
    pub finished: bool,
    /// Env steps reported by train episodes.
    pub env_steps: u64,
    pub stage_1_env_steps: Option<u64>,
    pub episodes: u64,
    pub episodes_per_s: f64,
    pub open_leases: u64,
    pub expired_leases: u64,
    /// Simulator worker restarts over all actors and their respawns (a restarted worker replays
    /// its episode, so nothing else shows it). Absent from older servers' JSON.
    #[serde(default)]
    pub sim_worker_restarts: u64,
    pub refused_reports: RefusedReports,
    /// Calls refused UNAUTHENTICATED (no run token or a wrong one) since the server started.
    #[serde(default)]
    pub unauthenticated_calls: u64,
    /// Actor ids dropped from `actors` after `service.forget_actors_after_s` without a call.
    #[serde(default)]
    pub actors_forgotten: u64,
    /// Snapshot writes that failed since the server started (each is logged; the server stops
    /// after several failures in a row).
    #[serde(default)]
    pub snapshot_failures: u64,
    pub solved_frac: f64,
    pub demos: Vec<DemoBar>,
    pub levels: Vec<LevelRow>,
    pub actors: Vec<ActorRow>,
    pub evals: Vec<EvalPoint>,
    pub history: Vec<ProgressPoint>,
    /// The PointMaze success heatmap (PointMaze runs only).
    #[serde(default)]
    pub maze: Option<MazeView>,
}

/// The PointMaze heatmap (the paper's figure): success per start cell over the run.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MazeView {
    /// The layout, one string per row (`#` wall, `X` hazard wall, `G` goal, `.` open), as in
    /// `rfcl_core::maze::MAP`.
    pub map: Vec<String>,
    /// Evals spread over the run, oldest first; the last is the latest complete eval.
    pub snapshots: Vec<MazeSnapshot>,
    /// Per demo, the point's `(x, y)` at every step (x = column, y = row).
    pub demo_paths: Vec<Vec<[f32; 2]>>,
}

/// Eval success per start cell of one policy version.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MazeSnapshot {
    pub policy_version: u64,
    pub env_steps: u64,
    pub success_rate: f64,
    pub cells: Vec<MazeCell>,
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct MazeCell {
    pub row: u32,
    pub col: u32,
    pub episodes: u64,
    pub successes: u64,
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RefusedReports {
    pub duplicate: u64,
    pub expired: u64,
    pub unknown: u64,
    pub epoch_mismatch: u64,
    pub malformed: u64,
    /// From an actor that does not hold the lease (refused PERMISSION_DENIED).
    #[serde(default)]
    pub not_holder: u64,
    /// Episodes longer than their lease's time limit (refused INVALID_ARGUMENT).
    #[serde(default)]
    pub over_time_limit: u64,
}

impl RefusedReports {
    /// Reports refused for any reason.
    pub fn total(&self) -> u64 {
        self.duplicate
            + self.expired
            + self.unknown
            + self.epoch_mismatch
            + self.malformed
            + self.not_holder
            + self.over_time_limit
    }
}

/// One demo's reverse-curriculum progress (spec 2).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DemoBar {
    pub demo: u32,
    /// Current start step t_i.
    pub t: u32,
    /// States kept, S_i.
    pub states: u32,
    /// Fraction of successes in the demo's frontier FIFO.
    pub frontier_success_rate: f64,
    pub solved: bool,
}

/// One forward-curriculum level (spec 3).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LevelRow {
    pub level: u32,
    /// "seed 12" or "demo 3 start".
    pub label: String,
    pub score: f64,
    pub staleness: u64,
    pub probability: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActorRow {
    pub actor_id: u32,
    pub seconds_since_seen: f64,
    pub env_steps: u64,
    pub episodes: u64,
    pub open_leases: u64,
    /// Simulator worker restarts of this actor id over all its processes.
    #[serde(default)]
    pub sim_restarts: u64,
}

/// Eval outcomes of one policy version.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalPoint {
    pub policy_version: u64,
    pub env_steps: u64,
    pub episodes: u64,
    pub success_at_end: f64,
    pub success_once: f64,
    pub mean_return: f64,
}

/// A sample of progress over time, taken by the service every few seconds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ProgressPoint {
    pub wall_s: f64,
    pub env_steps: u64,
    pub stage: u32,
    /// Mean of t_i / (S_i - 1): 1 at the start of stage 1, 0 when every demo starts from its beginning.
    pub start_step_frac_avg: f64,
    pub solved_frac: f64,
    pub train_success_rate: f64,
}

const CHART_W: u32 = 640;

fn chart_err<E: std::fmt::Debug>(e: E) -> String {
    format!("<p class=err>chart failed: {e:?}</p>")
}

/// Horizontal bars, one per demo: the filled part is the part of the demo the curriculum has
/// reached, (S_i - 1 - t_i) / (S_i - 1); solved demos are green.
pub fn demo_bars_svg(demos: &[DemoBar]) -> String {
    let height = 40 + 26 * demos.len().max(1) as u32;
    let mut svg = String::new();
    let result = (|| -> Result<(), Box<dyn std::error::Error>> {
        let root = SVGBackend::with_string(&mut svg, (CHART_W, height)).into_drawing_area();
        root.fill(&WHITE)?;
        let n = demos.len().max(1) as i32;
        let mut chart = ChartBuilder::on(&root)
            .margin(8)
            .x_label_area_size(28)
            .y_label_area_size(70)
            .build_cartesian_2d(0f64..1f64, (0..n).into_segmented())?;
        chart
            .configure_mesh()
            .disable_y_mesh()
            .x_desc("fraction of the demo reached (1 - t_i/(S_i-1))")
            .y_label_formatter(&|v| match v {
                SegmentValue::CenterOf(i) => demos
                    .get(*i as usize)
                    .map(|d| format!("demo {}", d.demo))
                    .unwrap_or_default(),
                _ => String::new(),
            })
            .draw()?;
        chart.draw_series(demos.iter().enumerate().map(|(i, d)| {
            let reached = if d.states > 1 {
                1.0 - d.t as f64 / (d.states - 1) as f64
            } else {
                1.0
            };
            let color = if d.solved {
                GREEN.mix(0.8)
            } else {
                BLUE.mix(0.6)
            };
            let i = i as i32;
            Rectangle::new(
                [
                    (0.0, SegmentValue::Exact(i)),
                    (reached, SegmentValue::Exact(i + 1)),
                ],
                color.filled(),
            )
        }))?;
        root.present()?;
        Ok(())
    })();
    match result {
        Ok(()) => svg,
        Err(e) => chart_err(e),
    }
}

/// Side of one maze cell in the heatmap, in pixels.
const MAZE_CELL_PX: u32 = 13;

/// White at 0, the page's green at 1 (opaque: a transparent colour would not be drawn at all).
fn success_color(rate: f64) -> RGBColor {
    let rate = rate.clamp(0.0, 1.0);
    let lerp = |from: u8, to: u8| (from as f64 + (to as f64 - from as f64) * rate).round() as u8;
    RGBColor(lerp(255, 26), lerp(255, 127), lerp(255, 55))
}

/// The PointMaze heatmap: one small maze per snapshot, each start cell shaded from white (never
/// solved) to green (always solved), walls dark, hazard walls dark red, the goal red, the demos'
/// paths blue (the paper's figure). Cells without eval episodes stay light grey.
pub fn maze_heatmap_svg(maze: &MazeView) -> String {
    let rows = maze.map.len().max(1) as u32;
    let cols = maze.map.iter().map(|r| r.len()).max().unwrap_or(1).max(1) as u32;
    let panels = maze.snapshots.len().max(1) as u32;
    let (caption_h, gap) = (30u32, 12u32);
    let panel_w = cols * MAZE_CELL_PX;
    let width = panels * panel_w + (panels + 1) * gap;
    let height = rows * MAZE_CELL_PX + caption_h + gap;
    let mut svg = String::new();
    let result = (|| -> Result<(), Box<dyn std::error::Error>> {
        let root = SVGBackend::with_string(&mut svg, (width, height)).into_drawing_area();
        root.fill(&WHITE)?;
        let empty = MazeSnapshot::default();
        let snapshots: Vec<&MazeSnapshot> = if maze.snapshots.is_empty() {
            vec![&empty]
        } else {
            maze.snapshots.iter().collect()
        };
        for (p, snap) in snapshots.iter().enumerate() {
            let x0 = gap as i32 + p as i32 * (panel_w + gap) as i32;
            let caption = if maze.snapshots.is_empty() {
                "no eval yet".to_string()
            } else {
                format!(
                    "{} steps: {:.0}%",
                    snap.env_steps,
                    snap.success_rate * 100.0
                )
            };
            root.draw_text(
                &caption,
                &("sans-serif", 15).into_font().color(&BLACK),
                (x0, 8),
            )?;
            let grid = root
                .clone()
                .shrink((x0, caption_h as i32), (panel_w, rows * MAZE_CELL_PX));
            let mut chart = ChartBuilder::on(&grid)
                .build_cartesian_2d(-0.5f32..cols as f32 - 0.5, rows as f32 - 0.5..-0.5f32)?;
            for (r, line) in maze.map.iter().enumerate() {
                for (c, ch) in line.chars().enumerate() {
                    let color = match ch {
                        '#' => RGBColor(60, 60, 60).filled(),
                        'X' => RGBColor(150, 30, 30).filled(),
                        _ => match snap
                            .cells
                            .iter()
                            .find(|m| (m.row, m.col) == (r as u32, c as u32))
                        {
                            Some(m) if m.episodes > 0 => {
                                success_color(m.successes as f64 / m.episodes as f64).filled()
                            }
                            _ => RGBColor(235, 235, 235).filled(),
                        },
                    };
                    let (x, y) = (c as f32, r as f32);
                    chart.draw_series(std::iter::once(Rectangle::new(
                        [(x - 0.5, y - 0.5), (x + 0.5, y + 0.5)],
                        color,
                    )))?;
                    if ch == 'G' {
                        chart.draw_series(std::iter::once(Circle::new((x, y), 4, RED.filled())))?;
                    }
                }
            }
            for path in &maze.demo_paths {
                chart.draw_series(std::iter::once(PathElement::new(
                    path.iter().map(|[x, y]| (*x, *y)).collect::<Vec<_>>(),
                    BLUE.mix(0.7).stroke_width(2),
                )))?;
            }
        }
        root.present()?;
        Ok(())
    })();
    match result {
        Ok(()) => svg,
        Err(e) => chart_err(e),
    }
}

/// Sampling probability per level, as bars (at most the 60 most likely levels are drawn).
pub fn level_probabilities_svg(levels: &[LevelRow]) -> String {
    let mut top: Vec<&LevelRow> = levels.iter().collect();
    top.sort_by(|a, b| {
        b.probability
            .total_cmp(&a.probability)
            .then(a.level.cmp(&b.level))
    });
    top.truncate(60);
    let mut svg = String::new();
    let result = (|| -> Result<(), Box<dyn std::error::Error>> {
        let root = SVGBackend::with_string(&mut svg, (CHART_W, 220)).into_drawing_area();
        root.fill(&WHITE)?;
        let n = top.len().max(1) as i32;
        let max_p = top.first().map(|l| l.probability).unwrap_or(1.0).max(1e-9);
        let mut chart = ChartBuilder::on(&root)
            .margin(8)
            .x_label_area_size(28)
            .y_label_area_size(50)
            .build_cartesian_2d((0..n).into_segmented(), 0f64..max_p * 1.05)?;
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_desc("levels, most likely first")
            .y_desc("P(level)")
            .x_label_formatter(&|_| String::new())
            .draw()?;
        chart.draw_series(top.iter().enumerate().map(|(i, l)| {
            let i = i as i32;
            let color = match l.score as i64 {
                3 => RED.mix(0.7),
                2 => BLUE.mix(0.6),
                _ => GREEN.mix(0.6),
            };
            Rectangle::new(
                [
                    (SegmentValue::Exact(i), 0.0),
                    (SegmentValue::Exact(i + 1), l.probability),
                ],
                color.filled(),
            )
        }))?;
        root.present()?;
        Ok(())
    })();
    match result {
        Ok(()) => svg,
        Err(e) => chart_err(e),
    }
}

/// Curriculum progress and success rates against env steps.
pub fn progress_svg(history: &[ProgressPoint], evals: &[EvalPoint]) -> String {
    let mut svg = String::new();
    let result = (|| -> Result<(), Box<dyn std::error::Error>> {
        let root = SVGBackend::with_string(&mut svg, (CHART_W, 260)).into_drawing_area();
        root.fill(&WHITE)?;
        let max_x = history
            .iter()
            .map(|p| p.env_steps)
            .chain(evals.iter().map(|e| e.env_steps))
            .max()
            .unwrap_or(1)
            .max(1) as f64;
        let mut chart = ChartBuilder::on(&root)
            .margin(8)
            .x_label_area_size(28)
            .y_label_area_size(40)
            .build_cartesian_2d(0f64..max_x, 0f64..1.02f64)?;
        chart.configure_mesh().x_desc("env steps").draw()?;
        let series: [(&str, RGBColor, fn(&ProgressPoint) -> f64); 3] = [
            ("start step frac (avg t_i/(S_i-1))", BLUE, |p| {
                p.start_step_frac_avg
            }),
            ("demos solved", GREEN, |p| p.solved_frac),
            ("train success", MAGENTA, |p| p.train_success_rate),
        ];
        for (label, color, f) in series {
            chart
                .draw_series(LineSeries::new(
                    history.iter().map(|p| (p.env_steps as f64, f(p))),
                    color.stroke_width(2),
                ))?
                .label(label)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 16, y)], color.stroke_width(2))
                });
        }
        chart
            .draw_series(LineSeries::new(
                evals.iter().map(|e| (e.env_steps as f64, e.success_at_end)),
                RED.stroke_width(2),
            ))?
            .label("eval success at end")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], RED.stroke_width(2)));
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()?;
        root.present()?;
        Ok(())
    })();
    match result {
        Ok(()) => svg,
        Err(e) => chart_err(e),
    }
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// The dashboard page. It refreshes itself every `refresh_s` seconds with a meta tag.
pub fn render_html(view: &DashboardView, refresh_s: u32) -> String {
    let mut h = String::new();
    let _ = write!(
        h,
        r#"<!doctype html><html><head><meta charset="utf-8"><meta http-equiv="refresh" content="{refresh_s}">
<title>rfcl · {name}</title>
<style>body{{font-family:sans-serif;margin:1.5em;color:#222}} table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:2px 8px;text-align:right}} th{{background:#f4f4f4}}
.kv span{{display:inline-block;margin-right:2em}} .solved{{color:#1a7f37;font-weight:bold}} .err{{color:#b00}}</style>
</head><body>
<h1>rfcl curriculum · {name} <small>({env})</small></h1>
<p class="kv"><span id="stage">stage <b>{stage}</b> (epoch {epoch}){finished}</span><span>env steps <b>{steps}</b></span>
<span>episodes {episodes} ({eps:.1}/s)</span><span>open leases {open}</span><span>expired leases {expired}</span>
<span>sim worker restarts {restarts}</span>
<span>demos solved {solved:.0}%</span></p>
<p class="kv"><span>refused reports: duplicate {dup}, expired {rexp}, unknown {unk}, other epoch {epm}, malformed {mal}, not the lease holder {nothold}, over the time limit {overlim}</span>
<span>unauthenticated calls {unauth}</span><span>actors forgotten {forgotten}</span><span>snapshot failures {snapfail}</span></p>
"#,
        name = esc(&view.run_name),
        env = esc(&view.env_id),
        stage = view.stage,
        epoch = view.stage_epoch,
        finished = if view.finished {
            " · <b>run finished</b>"
        } else {
            ""
        },
        steps = view.env_steps,
        episodes = view.episodes,
        eps = view.episodes_per_s,
        open = view.open_leases,
        expired = view.expired_leases,
        restarts = view.sim_worker_restarts,
        solved = view.solved_frac * 100.0,
        dup = view.refused_reports.duplicate,
        rexp = view.refused_reports.expired,
        unk = view.refused_reports.unknown,
        epm = view.refused_reports.epoch_mismatch,
        mal = view.refused_reports.malformed,
        nothold = view.refused_reports.not_holder,
        overlim = view.refused_reports.over_time_limit,
        unauth = view.unauthenticated_calls,
        forgotten = view.actors_forgotten,
        snapfail = view.snapshot_failures,
    );
    if let Some(s1) = view.stage_1_env_steps {
        let _ = writeln!(h, "<p>stage 1 ended after <b>{s1}</b> env steps</p>");
    }
    h.push_str("<h2>Reverse curriculum: demos</h2>\n");
    h.push_str(&demo_bars_svg(&view.demos));
    h.push_str("\n<table id=\"demos\"><tr><th>demo</th><th>t_i</th><th>S_i</th><th>t_i / S_i</th><th>frontier success</th><th>solved</th></tr>\n");
    for d in &view.demos {
        let _ = writeln!(
            h,
            "<tr class=\"demo-bar\"><td>{}</td><td>{}</td><td>{}</td><td>{:.3}</td><td>{:.2}</td><td>{}</td></tr>",
            d.demo,
            d.t,
            d.states,
            d.t as f64 / d.states.max(1) as f64,
            d.frontier_success_rate,
            if d.solved { "<span class=solved>✔</span>" } else { "" }
        );
    }
    h.push_str("</table>\n");
    if let Some(maze) = &view.maze {
        h.push_str("<h2>PointMaze: eval success per start cell</h2>\n<div id=\"maze-heatmap\">");
        h.push_str(&maze_heatmap_svg(maze));
        h.push_str("</div>\n<p>Green: the share of eval episodes from that cell that end at the goal; grey: no episode yet; blue: the demos; red: the goal.</p>\n");
    }
    h.push_str("<h2>Progress</h2>\n");
    h.push_str(&progress_svg(&view.history, &view.evals));
    if !view.levels.is_empty() {
        h.push_str("\n<h2>Forward curriculum: level sampling</h2>\n");
        h.push_str(&level_probabilities_svg(&view.levels));
        let mut top: Vec<&LevelRow> = view.levels.iter().collect();
        top.sort_by(|a, b| b.probability.total_cmp(&a.probability));
        h.push_str("\n<table id=\"levels\"><tr><th>level</th><th>score</th><th>staleness</th><th>P</th></tr>\n");
        for l in top.iter().take(20) {
            let _ = writeln!(
                h,
                "<tr><td>{}</td><td>{}</td><td>{}</td><td>{:.4}</td></tr>",
                esc(&l.label),
                l.score,
                l.staleness,
                l.probability
            );
        }
        let _ = writeln!(
            h,
            "</table><p>{} levels in all; the 20 most likely shown.</p>",
            view.levels.len()
        );
    }
    if !view.evals.is_empty() {
        h.push_str("<h2>Evaluation</h2>\n<table><tr><th>policy version</th><th>env steps</th><th>episodes</th><th>success at end</th><th>success once</th><th>return</th></tr>\n");
        for e in view.evals.iter().rev().take(10) {
            let _ = writeln!(
                h,
                "<tr><td>{}</td><td>{}</td><td>{}</td><td>{:.2}</td><td>{:.2}</td><td>{:.1}</td></tr>",
                e.policy_version, e.env_steps, e.episodes, e.success_at_end, e.success_once, e.mean_return
            );
        }
        h.push_str("</table>\n");
    }
    h.push_str("<h2>Actors</h2>\n<table id=\"actors\"><tr><th>actor</th><th>last seen</th><th>env steps</th><th>episodes</th><th>open leases</th><th>sim worker restarts</th></tr>\n");
    for a in &view.actors {
        let _ =
            writeln!(
            h,
            "<tr><td>{}</td><td>{:.1} s ago</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
            a.actor_id, a.seconds_since_seen, a.env_steps, a.episodes, a.open_leases, a.sim_restarts
        );
    }
    h.push_str("</table>\n<p><a href=\"/api/state\">JSON</a> · <a href=\"/metrics\">metrics</a></p></body></html>\n");
    h
}

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
        view.stage as f64,
    );
    gauge(
        &mut r,
        "stage_epoch",
        "Stage epoch, bumped on every stage change",
        view.stage_epoch as f64,
    );
    counter(
        &mut r,
        "env_steps",
        "Env steps of reported train episodes",
        view.env_steps,
    );
    counter(&mut r, "episodes", "Reported train episodes", view.episodes);
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
        view.expired_leases,
    );
    counter(
        &mut r,
        "unauthenticated_calls",
        "gRPC calls refused for a missing or wrong run token",
        view.unauthenticated_calls,
    );
    counter(
        &mut r,
        "sim_worker_restarts",
        "Simulator worker processes restarted after a crash or hang (episode replayed)",
        view.sim_worker_restarts,
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
        "Fraction of demos reverse-solved (spec 2.7)",
        view.solved_frac,
    );
    let refused = Family::<Vec<(String, String)>, Counter>::default();
    let rr = view.refused_reports;
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
    for d in &view.demos {
        let labels = vec![("demo".to_string(), d.demo.to_string())];
        start
            .get_or_create(&labels)
            .set(d.t as f64 / (d.states.max(2) - 1) as f64);
        solved.get_or_create(&labels).set(d.solved as i64);
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    fn view() -> DashboardView {
        DashboardView {
            run_name: "test <run>".into(),
            env_id: "PointMaze-v0".into(),
            stage: 1,
            demos: vec![
                DemoBar {
                    demo: 0,
                    t: 10,
                    states: 41,
                    frontier_success_rate: 0.5,
                    solved: false,
                },
                DemoBar {
                    demo: 1,
                    t: 0,
                    states: 30,
                    frontier_success_rate: 1.0,
                    solved: true,
                },
            ],
            history: vec![
                ProgressPoint {
                    wall_s: 0.0,
                    env_steps: 0,
                    stage: 1,
                    start_step_frac_avg: 1.0,
                    solved_frac: 0.0,
                    train_success_rate: 0.0,
                },
                ProgressPoint {
                    wall_s: 5.0,
                    env_steps: 800,
                    stage: 1,
                    start_step_frac_avg: 0.6,
                    solved_frac: 0.5,
                    train_success_rate: 0.4,
                },
            ],
            ..Default::default()
        }
    }

    #[test]
    fn the_page_has_one_bar_row_per_demo_and_escapes_names() {
        let html = render_html(&view(), 2);
        assert_eq!(html.matches("class=\"demo-bar\"").count(), 2);
        assert!(html.contains("test &lt;run&gt;"));
        assert!(html.contains("http-equiv=\"refresh\" content=\"2\""));
        assert!(!html.contains("chart failed"));
    }

    #[test]
    fn the_page_shows_sim_worker_restarts_in_total_and_per_actor() {
        let mut v = view();
        v.sim_worker_restarts = 7;
        v.actors = vec![ActorRow {
            actor_id: 3,
            seconds_since_seen: 1.0,
            env_steps: 100,
            episodes: 4,
            open_leases: 1,
            sim_restarts: 7,
        }];
        let html = render_html(&v, 2);
        assert!(html.contains("sim worker restarts 7"), "{html}");
        assert!(
            html.contains("<td>100</td><td>4</td><td>1</td><td>7</td></tr>"),
            "{html}"
        );
    }

    #[test]
    fn demo_bars_are_svg_rectangles() {
        let svg = demo_bars_svg(&view().demos);
        assert!(svg.starts_with("<svg"));
        // Background + plot area + one filled rectangle per demo at least.
        assert!(svg.matches("<rect").count() >= 3, "{svg}");
        assert!(svg.contains("demo 1"));
    }

    #[test]
    fn metrics_use_rfcl_names_and_labels() {
        let mut v = view();
        v.refused_reports.duplicate = 3;
        v.refused_reports.over_time_limit = 4;
        v.refused_reports.not_holder = 5;
        v.actors_forgotten = 6;
        v.snapshot_failures = 7;
        v.sim_worker_restarts = 2;
        let text = metrics_text(&v, 42);
        assert!(
            text.contains("rfcl_curriculum_sim_worker_restarts_total 2"),
            "{text}"
        );
        assert!(
            text.contains("rfcl_curriculum_leases_granted_total 42"),
            "{text}"
        );
        assert!(
            text.contains("rfcl_curriculum_reports_refused_total{reason=\"duplicate\"} 3"),
            "{text}"
        );
        for line in [
            "rfcl_curriculum_reports_refused_total{reason=\"over_time_limit\"} 4",
            "rfcl_curriculum_reports_refused_total{reason=\"not_holder\"} 5",
            "rfcl_curriculum_actors_forgotten_total 6",
            "rfcl_curriculum_snapshot_failures_total 7",
        ] {
            assert!(text.contains(line), "{line} missing from {text}");
        }
        assert!(
            text.contains("rfcl_curriculum_demo_solved{demo=\"1\"} 1"),
            "{text}"
        );
        assert!(text.ends_with("# EOF\n"));
    }

    fn maze() -> MazeView {
        let snapshot = |steps: u64, successes: u64| MazeSnapshot {
            policy_version: steps / 100,
            env_steps: steps,
            success_rate: successes as f64 / 2.0,
            cells: vec![
                MazeCell {
                    row: 1,
                    col: 2,
                    episodes: 1,
                    successes: 1,
                },
                MazeCell {
                    row: 1,
                    col: 3,
                    episodes: 1,
                    successes: successes - 1,
                },
            ],
        };
        MazeView {
            map: vec!["####".into(), "#G..".into(), "####".into()],
            snapshots: vec![snapshot(5000, 1), snapshot(9000, 2)],
            demo_paths: vec![vec![[3.0, 1.0], [2.0, 1.0], [1.0, 1.0]]],
        }
    }

    #[test]
    fn the_maze_heatmap_has_a_cell_per_map_square_per_snapshot() {
        let m = maze();
        let svg = maze_heatmap_svg(&m);
        assert!(svg.starts_with("<svg"), "{svg}");
        // Background + 12 squares in each of the two panels.
        assert!(svg.matches("<rect").count() >= 1 + 2 * 12, "{svg}");
        assert!(
            svg.contains("5000 steps: 50%") && svg.contains("9000 steps: 100%"),
            "{svg}"
        );
        // The goal (red circle) in each panel and a demo path.
        assert_eq!(svg.matches("<circle").count(), 2, "{svg}");
        assert!(svg.contains("<polyline"), "{svg}");
        let mut v = view();
        v.maze = Some(m);
        let html = render_html(&v, 2);
        assert!(html.contains("id=\"maze-heatmap\""));
        assert!(!html.contains("chart failed"));
        // No heatmap section for other suites.
        assert!(!render_html(&view(), 2).contains("maze-heatmap"));
    }

    #[test]
    fn empty_views_render() {
        let html = render_html(&DashboardView::default(), 5);
        assert!(html.contains("<svg"));
        assert!(level_probabilities_svg(&[]).starts_with("<svg"));
    }
}
