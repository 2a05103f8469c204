//! The dashboard page: plain HTML with the charts inlined, refreshed by a meta tag.
use std::fmt::Write as _;

use super::charts::{
    demo_bars_svg, demo_color, demo_frontiers_svg, level_probabilities_svg, maze_heatmap_svg,
    progress_svg, PROGRESS_LEGEND,
};
use super::view::{DashboardView, LearnerPanel, LevelRow, VideoLink};

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// Colours of the learner's activities in its time bar, in `TimeShares::labelled` order.
const ACTIVITY_COLOURS: [&str; 5] = ["#1f77b4", "#bbbbbb", "#ff7f0e", "#2ca02c", "#9467bd"];

/// The learner beside the curriculum: rates, losses and where its time goes, as its Health RPC
/// last answered.
fn learner_panel(h: &mut String, panel: Option<&LearnerPanel>) {
    h.push_str("<h2>Learner</h2>\n<div id=\"learner\">");
    let Some(p) = panel else {
        h.push_str("<p>No learner has announced itself yet (it does when it subscribes to the stage announcements).</p></div>\n");
        return;
    };
    let answered = match p.seconds_since_answer {
        Some(s) => format!("answered {s:.0} s ago"),
        None => "no answer yet".into(),
    };
    let _ = writeln!(
        h,
        "<p class=\"kv\"><span>at <code>{}</code> ({answered})</span><span>{}</span><span>env steps <b>{}</b></span><span>critic updates {}</span><span>policy v{}</span></p>",
        esc(&p.address),
        if p.ok || p.seconds_since_answer.is_none() { "ok" } else { "<span class=err>training failed</span>" },
        p.env_steps,
        p.critic_updates,
        p.policy_version,
    );
    if let Some(e) = &p.error {
        let _ = writeln!(h, "<p class=err>{}</p>", esc(e));
    }
    let Some(w) = &p.window else {
        h.push_str("<p>No progress window yet (the learner reports one every 10 s).</p></div>\n");
        return;
    };
    let num = |v: Option<f64>| v.map_or("–".to_string(), |v| format!("{v:.4}"));
    let _ = writeln!(
        h,
        "<p class=\"kv\"><span>updates/s <b>{:.1}</b></span><span>env steps/s {:.1}</span><span>UTD {:.2} (target {:.2})</span><span>policy lag ≤ {}</span></p>\n\
         <p class=\"kv\"><span>critic loss {}</span><span>actor loss {}</span><span>mean Q {}</span><span>temperature {}</span><span>entropy {}</span><span>(means over the last {:.0} s)</span></p>",
        w.updates_per_s,
        w.env_steps_per_s,
        w.utd,
        w.utd_target,
        w.policy_lag_max,
        num(w.critic_loss),
        num(w.actor_loss),
        num(w.q),
        num(w.temperature),
        num(w.entropy),
        w.seconds,
    );
    h.push_str("<div id=\"learner-time\" style=\"display:flex;width:600px;height:14px;border:1px solid #ccc\">");
    let shares = w.time_shares.labelled();
    for ((label, share), colour) in shares.iter().zip(ACTIVITY_COLOURS) {
        let _ = write!(
            h,
            "<div title=\"{label} {:.0}%\" style=\"width:{:.2}%;background:{colour}\"></div>",
            share * 100.0,
            share * 100.0
        );
    }
    h.push_str("</div>\n<p class=\"legend\">where the learner's time goes: ");
    for ((label, share), colour) in shares.iter().zip(ACTIVITY_COLOURS) {
        let _ = write!(
            h,
            "<span style=\"color:{colour}\">■</span> {label} {:.0}% &nbsp; ",
            share * 100.0
        );
    }
    h.push_str("</p></div>\n");
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
<span>sim worker restarts {restarts}</span><span>failed resets {failedresets}</span>
<span>demos solved {solved:.0}%</span></p>
<p class="kv"><span>refused reports: duplicate {dup}, expired {rexp}, unknown {unk}, other epoch {epm}, malformed {mal}, not the lease holder {nothold}, over the time limit {overlim}</span>
<span>unauthenticated calls {unauth}</span><span>oversized requests {oversized}</span><span>dashboard connections refused {dashrefused}</span><span>actors forgotten {forgotten}</span><span>snapshot failures {snapfail}</span></p>
"#,
        name = esc(&view.run.run_name),
        env = esc(&view.run.env_id),
        stage = view.run.stage,
        epoch = view.run.stage_epoch,
        finished = if view.run.finished {
            " · <b>run finished</b>"
        } else {
            ""
        },
        steps = view.run.env_steps,
        episodes = view.run.episodes,
        eps = view.episodes_per_s,
        open = view.open_leases,
        expired = view.run.expired_leases,
        restarts = view.run.sim_worker_restarts,
        failedresets = view.run.failed_resets,
        solved = view.solved_frac * 100.0,
        dup = view.run.refused_reports.duplicate,
        rexp = view.run.refused_reports.expired,
        unk = view.run.refused_reports.unknown,
        epm = view.run.refused_reports.epoch_mismatch,
        mal = view.run.refused_reports.malformed,
        nothold = view.run.refused_reports.not_holder,
        overlim = view.run.refused_reports.over_time_limit,
        unauth = view.unauthenticated_calls,
        oversized = view.oversized_requests,
        dashrefused = view.dashboard_refused,
        forgotten = view.actors_forgotten,
        snapfail = view.snapshot_failures,
    );
    if let Some(s1) = view.run.stage_1_env_steps {
        let _ = writeln!(h, "<p>stage 1 ended after <b>{s1}</b> env steps</p>");
    }
    learner_panel(&mut h, view.learner.as_ref());
    h.push_str("<h2>Reverse curriculum: demos</h2>\n");
    h.push_str(&demo_bars_svg(&view.run.demos));
    h.push_str("<h3>Frontiers over env steps</h3>\n");
    h.push_str(&demo_frontiers_svg(
        &view.run.demos,
        view.run.stage_1_env_steps.unwrap_or(view.run.env_steps),
    ));
    h.push_str("\n<p class=\"legend\">");
    for (i, d) in view.run.demos.iter().enumerate() {
        let c = demo_color(i);
        let _ = write!(
            h,
            "<span style=\"color:#{:02x}{:02x}{:02x}\">━━</span> demo {}{} &nbsp; ",
            c.0,
            c.1,
            c.2,
            d.demo,
            if d.difficulty.stalled {
                " (stalled)"
            } else {
                ""
            }
        );
    }
    h.push_str("</p>\n");
    h.push_str("\n<table id=\"demos\"><tr><th>demo (episode id)</th><th>t_i</th><th>S_i</th><th>t_i / S_i</th><th>frontier success (last m)</th><th>solved</th><th>states / 10k steps</th><th>steps since it moved</th><th>frontier episodes, success</th><th>share of episodes</th><th>flag</th></tr>\n");
    for d in &view.run.demos {
        let x = &d.difficulty;
        let mut flag = match (x.stalled, x.cell) {
            (true, Some([row, col])) => format!(
                "<span class=err>stalled at state {} (cell {row}, {col})</span>",
                d.t
            ),
            (true, None) => format!("<span class=err>stalled at state {}</span>", d.t),
            (false, _) => String::new(),
        };
        if let Some((state, reason)) = &x.last_reset_failure {
            let _ = write!(
                flag,
                " <span class=err title=\"{}\">{} failed reset(s), last at state {state}</span>",
                esc(reason),
                x.failed_resets
            );
        }
        let _ = writeln!(
            h,
            "<tr class=\"demo-bar\"><td>{} ({})</td><td>{}</td><td>{}</td><td>{:.3}</td><td>{:.2}</td><td>{}</td><td>{:.1}</td><td>{}</td><td>{}, {:.2}</td><td>{:.2}</td><td>{}</td></tr>",
            d.demo,
            d.episode_id,
            d.t,
            d.states,
            d.t as f64 / d.states.max(1) as f64,
            d.frontier_success_rate,
            if d.solved { "<span class=solved>✔</span>" } else { "" },
            x.speed,
            x.env_steps_since_move,
            x.frontier_episodes,
            x.frontier_success_rate,
            x.episode_share,
            flag,
        );
    }
    let stalled = view
        .run
        .demos
        .iter()
        .filter(|d| d.difficulty.stalled)
        .count();
    if stalled > 0 {
        let _ = writeln!(
            h,
            "</table>\n<p class=err>{stalled} demo(s) stalled: their frontier has not moved for a while \
             as others advanced. <code>rfcl demos select</code> writes the demo file without them.</p>"
        );
    } else {
        h.push_str("</table>\n");
    }
    if let Some(maze) = &view.maze {
        h.push_str("<h2>PointMaze: eval success per start cell</h2>\n<div id=\"maze-heatmap\">");
        h.push_str(&maze_heatmap_svg(maze));
        h.push_str("</div>\n<p>Green: the share of eval episodes from that cell that end at the goal; grey: no episode yet; blue: the demos; red: the goal.</p>\n");
    }
    h.push_str("<h2>Progress</h2>\n");
    h.push_str(&progress_svg(&view.history, &view.run.evals));
    h.push_str("\n<p class=\"legend\">");
    for (label, colour) in PROGRESS_LEGEND {
        let _ = write!(
            h,
            "<span style=\"color:{colour}\">━━</span> {label} &nbsp; "
        );
    }
    h.push_str("</p>\n");
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
    if !view.run.evals.is_empty() {
        h.push_str("<h2>Evaluation</h2>\n<table id=\"evals\"><tr><th>policy version</th><th>env steps</th><th>episodes</th><th>success at end</th><th>success once</th><th>return</th><th>video</th></tr>\n");
        for e in view.run.evals.iter().rev().take(10) {
            let _ = writeln!(
                h,
                "<tr><td>{}</td><td>{}</td><td>{}</td><td>{:.2}</td><td>{:.2}</td><td>{:.1}</td><td>{}</td></tr>",
                e.policy_version,
                e.env_steps,
                e.episodes,
                e.success_at_end,
                e.success_once,
                e.mean_return,
                video_links(&view.videos, e.policy_version)
            );
        }
        h.push_str("</table>\n");
    }
    if !view.videos.is_empty() || view.videos_refused > 0 {
        let _ = write!(h, "<p>{} eval episode(s) recorded", view.videos.len());
        if let Some(last) = view.videos.last() {
            let _ = write!(
                h,
                "; the latest: {}",
                video_link(last, &format!("policy v{}", last.meta.policy_version))
            );
        }
        if view.videos_refused > 0 {
            let _ = write!(
                h,
                "; <span class=err>{} refused</span>",
                view.videos_refused
            );
        }
        if view.videos_evicted > 0 {
            let _ = write!(
                h,
                "; {} older one(s) removed to keep within the videos' bounds",
                view.videos_evicted
            );
        }
        h.push_str(".</p>\n");
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

/// The recorded episodes of one evaluated policy, as links to `/videos/<name>`.
fn video_links(videos: &[VideoLink], policy_version: u64) -> String {
    videos
        .iter()
        .filter(|v| v.meta.policy_version == policy_version)
        .map(|v| {
            let outcome = if v.meta.success_at_end {
                "success"
            } else {
                "failure"
            };
            video_link(v, &format!("seed {} ({outcome})", v.meta.seed))
        })
        .collect::<Vec<_>>()
        .join(" ")
}

fn video_link(v: &VideoLink, text: &str) -> String {
    format!("<a href=\"{}\">{}</a>", esc(&v.url), esc(text))
}
