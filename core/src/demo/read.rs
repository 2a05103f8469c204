//! Reading a trajectory file (spec 6.1); the format is described in the module docs of `demo`.

use std::fs::File as StdFile;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

use hdf5::plist::group_create::LinkCreationOrder;
use hdf5::types::TypeDescriptor;
use hdf5::{Dataset, Group, IndexType, IterationOrder, LocationType};
use serde_json::Value;

use super::sidecar::{self, Sidecar};
use super::{Demo, DemoError, DemoSet, StateKind, StateLayout, SuccessSource};

/// The 8-byte HDF5 superblock signature.
const SIGNATURE: &[u8; 8] = b"\x89HDF\r\n\x1a\n";

/// How far from 1 the norm of a stored orientation may be. A simulator's own quaternions are unit
/// to float precision (about 1e-7 in ManiSkill3's demos); anything further off is damage.
const QUATERNION_NORM_TOLERANCE: f32 = 1e-3;

pub(super) fn load(path: &Path) -> Result<DemoSet, DemoError> {
    let file = open(path)?;
    let sidecar = sidecar::read(path)?;
    let mut demos: Vec<Demo> = Vec::new();
    let mut layout: Option<StateLayout> = None;
    for (episode_id, name) in trajectory_names(path, &file)? {
        let group = file
            .group(&name)
            .map_err(|e| DemoError::hdf5(path, format!("open {name}"), e))?;
        let reader = TrajReader {
            path,
            episode_id,
            group,
        };
        let traj = reader.read()?;
        if let (Some(first), Some(first_layout)) = (demos.first(), &layout) {
            let mismatch = if traj.obs.cols != first.obs_dim {
                Some((
                    "obs dim",
                    traj.obs.cols.to_string(),
                    first.obs_dim.to_string(),
                ))
            } else if traj.actions.cols != first.action_dim {
                Some((
                    "action dim",
                    traj.actions.cols.to_string(),
                    first.action_dim.to_string(),
                ))
            } else if traj.layout != *first_layout {
                Some((
                    "env_states",
                    traj.layout.describe(),
                    first_layout.describe(),
                ))
            } else {
                None
            };
            if let Some((what, got, expected)) = mismatch {
                return Err(DemoError::InconsistentDims {
                    path: path.to_path_buf(),
                    episode_id,
                    what,
                    got,
                    first_episode_id: first.episode_id,
                    expected,
                });
            }
        } else {
            layout = Some(traj.layout.clone());
        }
        demos.push(reader.into_demo(traj, sidecar.as_ref())?);
    }
    let state_layout = layout.ok_or_else(|| DemoError::NoTrajectories {
        path: path.to_path_buf(),
    })?;
    // After the whole file is read, so that a file that crashes the reader further on still
    // does (the crash is what `rfcl demos inspect`'s child process turns into one error line).
    unit_orientations(path, &state_layout, &demos)?;
    let (env_info, control_mode, sidecar_path) = match sidecar {
        Some(s) => {
            let mode = s.env_info["env_kwargs"]["control_mode"]
                .as_str()
                .map(str::to_owned);
            (s.env_info, mode.or(s.first_control_mode), Some(s.path))
        }
        None => (Value::Null, None, None),
    };
    Ok(DemoSet {
        path: path.to_path_buf(),
        sidecar: sidecar_path,
        env_id: env_info["env_id"].as_str().map(str::to_owned),
        env_info,
        control_mode,
        obs_dim: demos[0].obs_dim,
        action_dim: demos[0].action_dim,
        state_dim: state_layout.dim(),
        state_layout,
        demos,
    })
}

/// Every MS3 actor's and articulation root's orientation in every state (columns 3..7 of its
/// entry) is a unit quaternion, within [`QUATERNION_NORM_TOLERANCE`].
fn unit_orientations(path: &Path, layout: &StateLayout, demos: &[Demo]) -> Result<(), DemoError> {
    let posed: Vec<_> = layout
        .entries()
        .iter()
        .filter(|e| matches!(e.kind, StateKind::Actor | StateKind::Articulation))
        .collect();
    for demo in demos {
        for (step, state) in demo.env_states.chunks_exact(demo.state_dim).enumerate() {
            for entry in &posed {
                let at = entry.offset + 3;
                let quaternion: [f32; 4] = state[at..at + 4].try_into().expect("4 values");
                let norm = quaternion.iter().map(|q| q * q).sum::<f32>().sqrt();
                if (norm - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
                    return Err(DemoError::NotUnitQuaternion {
                        path: path.to_path_buf(),
                        episode_id: demo.episode_id,
                        field: format!("env_states/{}", entry.name),
                        step,
                        quaternion,
                        norm,
                        tolerance: QUATERNION_NORM_TOLERANCE,
                    });
                }
            }
        }
    }
    Ok(())
}

/// Opens `path` after checking that it exists and carries an HDF5 signature.
fn open(path: &Path) -> Result<hdf5::File, DemoError> {
    let io = |error| DemoError::Io {
        path: path.to_path_buf(),
        error,
    };
    if path.is_dir() {
        return Err(DemoError::IsDirectory {
            path: path.to_path_buf(),
        });
    }
    let mut file = match StdFile::open(path) {
        Ok(file) => file,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(DemoError::NotFound {
                path: path.to_path_buf(),
            });
        }
        Err(e) => return Err(io(e)),
    };
    if !has_signature(&mut file).map_err(io)? {
        return Err(DemoError::NotHdf5 {
            path: path.to_path_buf(),
        });
    }
    hdf5::File::open(path).map_err(|e| DemoError::hdf5(path, "open it", e))
}

/// HDF5 puts its signature at offset 0, or after a user block at 512, 1024, 2048, ...
fn has_signature(file: &mut StdFile) -> std::io::Result<bool> {
    let len = file.metadata()?.len();
    let mut offset = 0u64;
    while offset + 8 <= len {
        let mut head = [0u8; 8];
        file.seek(SeekFrom::Start(offset))?;
        file.read_exact(&mut head)?;
        if &head == SIGNATURE {
            return Ok(true);
        }
        offset = if offset == 0 { 512 } else { offset * 2 };
    }
    Ok(false)
}

/// The `traj_<id>` members, by ascending episode id.
fn trajectory_names(path: &Path, file: &hdf5::File) -> Result<Vec<(u64, String)>, DemoError> {
    let names = file
        .member_names()
        .map_err(|e| DemoError::hdf5(path, "list its groups", e))?;
    let mut trajs = Vec::new();
    for name in names {
        let Some(id) = name.strip_prefix("traj_") else {
            continue;
        };
        let id = id.parse::<u64>().map_err(|_| {
            DemoError::format(
                path,
                format!("group '{name}' is not named traj_<integer episode id>"),
            )
        })?;
        trajs.push((id, name));
    }
    if trajs.is_empty() {
        return Err(DemoError::NoTrajectories {
            path: path.to_path_buf(),
        });
    }
    trajs.sort_unstable();
    Ok(trajs)
}

/// A dataset read as `rows × cols` row-major `f32`s.
struct Matrix {
    rows: usize,
    cols: usize,
    data: Vec<f32>,
}

/// One trajectory group as stored, before the sidecar is applied.
struct Traj {
    obs: Matrix,
    actions: Matrix,
    success: Option<Vec<bool>>,
    states: Vec<f32>,
    layout: StateLayout,
}

/// Reads the group `traj_<episode_id>`; every error names the file and the trajectory.
struct TrajReader<'a> {
    path: &'a Path,
    episode_id: u64,
    group: Group,
}

impl TrajReader<'_> {
    fn read(&self) -> Result<Traj, DemoError> {
        let actions = self.matrix(&self.group, "actions", "actions")?;
        let t = actions.rows;
        let check_rows = |what: &str, rows: usize, formula: &'static str, expected: usize| {
            if rows == expected {
                return Ok(());
            }
            Err(DemoError::LengthMismatch {
                path: self.path.to_path_buf(),
                episode_id: self.episode_id,
                what: what.to_owned(),
                rows,
                actions: t,
                formula,
                expected,
            })
        };
        let obs = self.matrix(&self.group, "obs", "obs")?;
        check_rows("obs", obs.rows, "T+1", t + 1)?;
        let success = self.flags()?;
        if let Some(flags) = &success {
            check_rows("success", flags.len(), "T", t)?;
        }
        let (leaves, layout) = self.state_leaves()?;
        for (shown, m) in &leaves {
            check_rows(shown, m.rows, "T+1", t + 1)?;
        }
        let mut states = Vec::with_capacity((t + 1) * layout.dim());
        for row in 0..=t {
            for (_, m) in &leaves {
                states.extend_from_slice(&m.data[row * m.cols..(row + 1) * m.cols]);
            }
        }
        Ok(Traj {
            obs,
            actions,
            success,
            states,
            layout,
        })
    }

    /// Applies the sidecar's episode entry: reset arguments and, without a `success` dataset,
    /// the episode's success flag on the final step.
    fn into_demo(self, t: Traj, sidecar: Option<&Sidecar>) -> Result<Demo, DemoError> {
        let episode_id = self.episode_id;
        let episode = match sidecar {
            Some(s) => Some(s.episodes.get(&episode_id).ok_or_else(|| {
                let message = format!(
                    "no episodes[] entry with episode_id {episode_id} (for traj_{episode_id})"
                );
                DemoError::format(&s.path, message)
            })?),
            None => None,
        };
        let flag = episode.and_then(|e| e.success);
        let (success, success_source) = match (t.success, flag) {
            (Some(steps), _) => (steps, SuccessSource::Steps),
            (None, Some(flag)) => {
                let mut steps = vec![false; t.actions.rows];
                if let Some(last) = steps.last_mut() {
                    *last = flag;
                }
                (steps, SuccessSource::EpisodeFlag)
            }
            (None, None) => {
                let message = format!(
                    "traj_{episode_id} has no 'success' dataset and the JSON sidecar gives no success flag for it (episodes[].success or info.success)"
                );
                return Err(DemoError::format(self.path, message));
            }
        };
        Ok(Demo {
            episode_id,
            obs_dim: t.obs.cols,
            action_dim: t.actions.cols,
            state_dim: t.layout.dim(),
            obs: t.obs.data,
            actions: t.actions.data,
            succeeded: flag.unwrap_or(success.last() == Some(&true)),
            success,
            env_states: t.states,
            success_source,
            reset: episode.map(|e| e.reset.clone()).unwrap_or_default(),
        })
    }

    /// The `success` dataset, if any: h5py's bool enum, or numbers (non-zero = true).
    fn flags(&self) -> Result<Option<Vec<bool>>, DemoError> {
        if !self.group.link_exists("success") {
            return Ok(None);
        }
        let ds = self.dataset(&self.group, "success", "success")?;
        if !matches!(ds.shape()[..], [_] | [_, 1]) {
            return Err(self.format(format!("success has shape {:?}, expected [T]", ds.shape())));
        }
        let read_err = |e| self.hdf5("read", "success", e);
        let descriptor = ds
            .dtype()
            .and_then(|t| t.to_descriptor())
            .map_err(read_err)?;
        let flags = match descriptor {
            TypeDescriptor::Boolean => ds.read_raw::<bool>().map_err(read_err)?,
            TypeDescriptor::Integer(_) | TypeDescriptor::Unsigned(_) | TypeDescriptor::Float(_) => {
                ds.read_raw::<f64>()
                    .map_err(read_err)?
                    .into_iter()
                    .map(|v| v != 0.0)
                    .collect()
            }
            other => return Err(self.format(format!("success has type {other}, expected bool"))),
        };
        Ok(Some(flags))
    }

    /// The leaves of `env_states`, each with its path below the trajectory, in layout order (see
    /// the `demo` module docs), and the layout.
    fn state_leaves(&self) -> Result<(Vec<(String, Matrix)>, StateLayout), DemoError> {
        const ROOT: &str = "env_states";
        if self.location_type(&self.group, ROOT, ROOT)? == LocationType::Dataset {
            let m = self.matrix(&self.group, ROOT, ROOT)?;
            let layout = StateLayout::flat(m.cols);
            return Ok((vec![(ROOT.to_owned(), m)], layout));
        }
        let env_states = self
            .group
            .group(ROOT)
            .map_err(|e| self.hdf5("open", ROOT, e))?;
        let mut members = self.link_order(&env_states, ROOT)?;
        // Actors first, then articulations, then named fields; stable, so link order within each.
        members.sort_by_key(|m| match m.as_str() {
            "actors" => 0,
            "articulations" => 1,
            _ => 2,
        });
        let (mut leaves, mut parts) = (Vec::new(), Vec::new());
        for member in members {
            let kind = match member.as_str() {
                "actors" => StateKind::Actor,
                "articulations" => StateKind::Articulation,
                _ => StateKind::Field,
            };
            self.collect_leaves(&env_states, &member, &member, kind, &mut leaves, &mut parts)?;
        }
        if leaves.is_empty() {
            return Err(self.format(format!("{ROOT} is a group without datasets")));
        }
        Ok((leaves, StateLayout::from_parts(parts)))
    }

    /// Adds the datasets at or below `name` of `group`; `rel` is its path below `env_states`.
    fn collect_leaves(
        &self,
        group: &Group,
        name: &str,
        rel: &str,
        kind: StateKind,
        leaves: &mut Vec<(String, Matrix)>,
        parts: &mut Vec<(String, StateKind, usize)>,
    ) -> Result<(), DemoError> {
        let shown = format!("env_states/{rel}");
        if self.location_type(group, name, &shown)? == LocationType::Group {
            let sub = group
                .group(name)
                .map_err(|e| self.hdf5("open", &shown, e))?;
            for member in self.link_order(&sub, &shown)? {
                let rel = format!("{rel}/{member}");
                self.collect_leaves(&sub, &member, &rel, kind, leaves, parts)?;
            }
            return Ok(());
        }
        // Only what lies below `env_states/actors` is an actor (likewise articulations).
        let kind = if rel.contains('/') {
            kind
        } else {
            StateKind::Field
        };
        let m = self.matrix(group, name, &shown)?;
        let expected = match kind {
            StateKind::Actor if m.cols != StateKind::ACTOR_LEN => {
                Some("13 (pos 3, quat 4, linear velocity 3, angular velocity 3)")
            }
            StateKind::Articulation
                if m.cols < StateKind::ROOT_LEN
                    || !(m.cols - StateKind::ROOT_LEN).is_multiple_of(2) =>
            {
                Some("13 + 2·dof (root pose 7, root velocity 6, qpos, qvel)")
            }
            _ => None,
        };
        if let Some(expected) = expected {
            return Err(self.format(format!(
                "{shown} has {} columns, expected {expected}",
                m.cols
            )));
        }
        parts.push((rel.to_owned(), kind, m.cols));
        leaves.push((shown, m));
        Ok(())
    }

    /// Reads `[rows]` or `[rows, cols]` numbers as `f32` (HDF5 converts other numeric types);
    /// `shown` is the dataset's path below the trajectory.
    fn matrix(&self, group: &Group, name: &str, shown: &str) -> Result<Matrix, DemoError> {
        let ds = self.dataset(group, name, shown)?;
        let (rows, cols) = match ds.shape()[..] {
            [rows] => (rows, 1),
            [rows, cols] => (rows, cols),
            ref shape => {
                return Err(self.format(format!(
                    "{shown} has shape {shape:?}, expected [rows, columns]"
                )));
            }
        };
        let data = ds
            .read_raw::<f32>()
            .map_err(|e| self.hdf5("read", shown, e))?;
        if let Some(i) = data.iter().position(|x| !x.is_finite()) {
            return Err(DemoError::NonFinite {
                path: self.path.to_path_buf(),
                episode_id: self.episode_id,
                field: shown.to_owned(),
                step: i / cols.max(1),
                column: i % cols.max(1),
                value: data[i],
            });
        }
        Ok(Matrix { rows, cols, data })
    }

    fn dataset(&self, group: &Group, name: &str, shown: &str) -> Result<Dataset, DemoError> {
        if self.location_type(group, name, shown)? != LocationType::Dataset {
            let hint = if shown == "obs" {
                " (record the demos with obs_mode \"state\")"
            } else {
                ""
            };
            return Err(self.format(format!("{shown} is not a dataset{hint}")));
        }
        group.dataset(name).map_err(|e| self.hdf5("open", shown, e))
    }

    fn location_type(
        &self,
        group: &Group,
        name: &str,
        shown: &str,
    ) -> Result<LocationType, DemoError> {
        if !group.link_exists(name) {
            return Err(DemoError::MissingDataset {
                path: self.path.to_path_buf(),
                episode_id: self.episode_id,
                dataset: shown.to_owned(),
            });
        }
        group
            .loc_type_by_name(name)
            .map_err(|e| self.hdf5("open", shown, e))
    }

    /// Member names in the file's link order: creation order where the group tracks it, else
    /// name order.
    fn link_order(&self, group: &Group, shown: &str) -> Result<Vec<String>, DemoError> {
        let err = |e| self.hdf5("list", shown, e);
        let index = match group.create_plist().map_err(err)?.link_creation_order() {
            LinkCreationOrder::Untracked => IndexType::Name,
            LinkCreationOrder::Tracked | LinkCreationOrder::Indexed => IndexType::CreationOrder,
        };
        group
            .member_names_by(index, IterationOrder::Increasing)
            .map_err(err)
    }

    fn format(&self, message: String) -> DemoError {
        DemoError::format(self.path, format!("traj_{}/{message}", self.episode_id))
    }

    fn hdf5(&self, action: &str, shown: &str, e: hdf5::Error) -> DemoError {
        DemoError::hdf5(
            self.path,
            format!("{action} traj_{}/{shown}", self.episode_id),
            e,
        )
    }
}
