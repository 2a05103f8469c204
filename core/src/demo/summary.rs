//! The report printed by `rfcl demos inspect`.

use std::fmt::Write as _;

use super::{DemoSet, StateKind, SuccessSource};

/// Reset options longer than this are cut in the per-episode table.
const OPTIONS_WIDTH: usize = 40;

pub(super) fn summary(set: &DemoSet) -> String {
    let mut out = String::new();
    // Writing into a String cannot fail.
    let _ = write_summary(set, &mut out);
    out
}

fn write_summary(set: &DemoSet, out: &mut String) -> std::fmt::Result {
    writeln!(out, "{}", set.path.display())?;
    match &set.sidecar {
        Some(json) => writeln!(out, "  sidecar: {}", json.display())?,
        None => writeln!(
            out,
            "  sidecar: none ({} not found): reset seeds unknown, episodes reset with no seed and options {{}}",
            DemoSet::sidecar_path(&set.path).display()
        )?,
    }
    let unknown = || "?".to_owned();
    let max_steps = set.env_info["max_episode_steps"]
        .as_u64()
        .map_or_else(unknown, |m| m.to_string());
    writeln!(
        out,
        "  env: {}  control_mode: {}  max_episode_steps: {max_steps}",
        set.env_id.clone().unwrap_or_else(unknown),
        set.control_mode.clone().unwrap_or_else(unknown),
    )?;
    let n = set.demos.len();
    let successful = set.demos.iter().filter(|d| d.succeeded).count();
    write!(out, "  episodes: {n} ({successful} successful)")?;
    let lengths: Vec<usize> = set.demos.iter().map(|d| d.len()).collect();
    if let (Some(min), Some(max)) = (lengths.iter().min(), lengths.iter().max()) {
        let mean = lengths.iter().sum::<usize>() as f64 / n as f64;
        write!(out, ", T min {min} / mean {mean:.1} / max {max}")?;
    }
    writeln!(out)?;
    writeln!(
        out,
        "  dims: obs {}, action {}, env_state {}",
        set.obs_dim, set.action_dim, set.state_dim
    )?;
    writeln!(out, "  state layout:")?;
    let width = set
        .state_layout
        .entries()
        .iter()
        .map(|e| e.name.chars().count())
        .max()
        .unwrap_or(0);
    for e in set.state_layout.entries() {
        let kind = match (e.kind, e.dof()) {
            (StateKind::Articulation, Some(dof)) => format!("articulation, dof {dof}"),
            (StateKind::Actor, _) => "actor".to_owned(),
            (StateKind::Flat, _) => "flat".to_owned(),
            _ => "field".to_owned(),
        };
        let (start, end, name) = (e.offset, e.offset + e.len, &e.name);
        writeln!(out, "    [{start:>5}, {end:>5})  {name:<width$}  ({kind})")?;
    }
    if set
        .demos
        .iter()
        .any(|d| d.success_source == SuccessSource::EpisodeFlag)
    {
        writeln!(
            out,
            "  * no 'success' dataset: the sidecar's episode flag labels the final step only"
        )?;
    }
    writeln!(
        out,
        "  {:<12} {:>6} {:>8} {:>13} {:>12}  options",
        "episode", "T", "success", "first success", "seed"
    )?;
    for d in &set.demos {
        let success = match (d.succeeded, d.success_source) {
            (true, SuccessSource::Steps) => "yes",
            (false, SuccessSource::Steps) => "no",
            (true, SuccessSource::EpisodeFlag) => "yes*",
            (false, SuccessSource::EpisodeFlag) => "no*",
        };
        let first = d
            .first_success()
            .map_or_else(|| "-".to_owned(), |s| s.to_string());
        let seed = d
            .reset
            .seed
            .map_or_else(|| "-".to_owned(), |s| s.to_string());
        let mut options = d.reset.options.to_string();
        if options.chars().count() > OPTIONS_WIDTH {
            options = options
                .chars()
                .take(OPTIONS_WIDTH - 1)
                .chain(['…'])
                .collect();
        }
        let name = format!("traj_{}", d.episode_id);
        writeln!(
            out,
            "  {name:<12} {:>6} {success:>8} {first:>13} {seed:>12}  {options}",
            d.len()
        )?;
    }
    Ok(())
}
