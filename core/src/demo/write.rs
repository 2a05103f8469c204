//! Writing a [`DemoSet`] in ManiSkill's format, MS3 style (spec 6.1).

use std::collections::HashSet;
use std::path::Path;

use hdf5::plist::group_create::LinkCreationOrder;
use hdf5::Group;

use super::{sidecar, Demo, DemoError, DemoSet, StateKind};

pub(super) fn write(set: &DemoSet, path: &Path) -> Result<(), DemoError> {
    validate(set, path)?;
    let file = hdf5::File::create(path).map_err(|e| DemoError::hdf5(path, "create it", e))?;
    for demo in &set.demos {
        write_traj(&file, set, demo)
            .map_err(|e| DemoError::hdf5(path, format!("write traj_{}", demo.episode_id), e))?;
    }
    file.close()
        .map_err(|e| DemoError::hdf5(path, "close it", e))?;
    let json_path = DemoSet::sidecar_path(path);
    let mut json = serde_json::to_string_pretty(&sidecar::to_json(set))
        .expect("a JSON value always serialises");
    json.push('\n');
    std::fs::write(&json_path, json).map_err(|error| DemoError::Io {
        path: json_path,
        error,
    })
}

/// Rejects a set that would not read back as itself.
fn validate(set: &DemoSet, path: &Path) -> Result<(), DemoError> {
    let fail = |message: String| Err(DemoError::format(path, message));
    let layout = &set.state_layout;
    if layout.dim() != set.state_dim {
        return fail(format!(
            "state layout covers {} values but state_dim is {}",
            layout.dim(),
            set.state_dim
        ));
    }
    if layout.entries().is_empty() {
        return fail("state layout is empty: demos need env states".to_owned());
    }
    for e in layout.entries() {
        let prefix_ok = match e.kind {
            StateKind::Flat => layout.is_flat(),
            StateKind::Actor => e.name.starts_with("actors/"),
            StateKind::Articulation => e.name.starts_with("articulations/"),
            StateKind::Field => {
                !e.name.starts_with("actors/") && !e.name.starts_with("articulations/")
            }
        };
        if !prefix_ok || e.name.is_empty() {
            return fail(format!(
                "state entry '{}' of kind {:?} would read back differently (actors/<name>, articulations/<name>, a field name, or one flat entry)",
                e.name, e.kind
            ));
        }
    }
    let mut ids = HashSet::new();
    for demo in &set.demos {
        if !ids.insert(demo.episode_id) {
            return fail(format!("episode_id {} appears twice", demo.episode_id));
        }
        let dims = (demo.obs_dim, demo.action_dim, demo.state_dim);
        if dims != (set.obs_dim, set.action_dim, set.state_dim) {
            return fail(format!(
                "traj_{} has dims (obs, action, state) {dims:?} but the set has {:?}",
                demo.episode_id,
                (set.obs_dim, set.action_dim, set.state_dim)
            ));
        }
        let t = demo.len();
        let sizes = [
            (
                "obs",
                demo.obs.len(),
                (t + 1) * demo.obs_dim,
                "(T+1)·obs_dim",
            ),
            (
                "actions",
                demo.actions.len(),
                t * demo.action_dim,
                "T·action_dim",
            ),
            (
                "env_states",
                demo.env_states.len(),
                (t + 1) * demo.state_dim,
                "(T+1)·state_dim",
            ),
        ];
        if let Some((what, got, expected, formula)) = sizes.into_iter().find(|s| s.1 != s.2) {
            return fail(format!(
                "traj_{}: {what} holds {got} values, expected {formula} = {expected} with T = {t} success flags",
                demo.episode_id
            ));
        }
    }
    Ok(())
}

fn write_traj(file: &hdf5::File, set: &DemoSet, demo: &Demo) -> hdf5::Result<()> {
    let g = file.create_group(&format!("traj_{}", demo.episode_id))?;
    let t = demo.len();
    write_f32(&g, "actions", t, set.action_dim, &demo.actions)?;
    write_f32(&g, "obs", t + 1, set.obs_dim, &demo.obs)?;
    g.new_dataset::<bool>()
        .shape([t])
        .create("success")?
        .write_raw(&demo.success[..])?;
    if set.state_layout.is_flat() {
        return write_f32(&g, "env_states", t + 1, set.state_dim, &demo.env_states);
    }
    let root = ordered_group(&g, "env_states")?;
    for entry in set.state_layout.entries() {
        let mut parent = root.clone();
        let mut components: Vec<&str> = entry.name.split('/').collect();
        let leaf = components.pop().expect("split yields at least one part");
        for component in components {
            parent = ordered_group(&parent, component)?;
        }
        let column: Vec<f32> = (0..=t)
            .flat_map(|s| demo.state_row(s)[entry.range()].iter().copied())
            .collect();
        write_f32(&parent, leaf, t + 1, entry.len, &column)?;
    }
    Ok(())
}

fn write_f32(g: &Group, name: &str, rows: usize, cols: usize, data: &[f32]) -> hdf5::Result<()> {
    g.new_dataset::<f32>()
        .shape([rows, cols])
        .create(name)?
        .write_raw(data)
}

/// The subgroup `name`, created with tracked link order so that readers see creation order.
fn ordered_group(parent: &Group, name: &str) -> hdf5::Result<Group> {
    if parent.link_exists(name) {
        return parent.group(name);
    }
    parent
        .create_group_builder()
        .with_gcpl(|p| p.link_creation_order(LinkCreationOrder::Indexed))
        .create(name)
}
