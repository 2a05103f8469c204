//! Learner checkpoints (spec 4.1 "each model's state = params + optimizer state + step";
//! ARCHITECTURE "Resume that comes back empty"): everything a resumed learner needs to continue
//! exactly where it stopped.
//!
//! Layout of `RUN_DIR/checkpoint/`:
//!
//! | file                            | contents                                                     |
//! |---------------------------------|--------------------------------------------------------------|
//! | `learner.json`                  | the manifest: counters, UTD limiter, RNG states, buffer positions, config, file names |
//! | `networks.<gen>.safetensors`    | `actor/*`, `critic/*`, `target/*`, `temperature/log_alpha` in their own dtype |
//! | `optimizers.<gen>.safetensors`  | `<actor|critic|temperature>/{step, exp_avg.*, exp_avg_sq.*}` (Adam) |
//! | `replay.<gen>.bin`              | the stored rows of the online then the offline buffer: per buffer, fields obs, action, reward, mask, next_obs, `len` rows each, little-endian `f32` |
//!
//! Commit protocol: the data files of generation `gen` are written under new names and fsynced,
//! then the manifest is replaced atomically ([`rfcl_core::atomic::atomic_write`]); only then are
//! older generations deleted. A `kill -9` at any moment leaves the previous checkpoint or the new
//! one, never a mix.
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tch::{Device, Tensor};
use thiserror::Error;

use crate::limiter::UtdLimiter;
use crate::replay::{Replay, ReplayBuffer};
use crate::sac::Sac;

/// The manifest's `format`.
pub const FORMAT: &str = "rfcl-learner-checkpoint-v1";
pub const MANIFEST: &str = "learner.json";

#[derive(Debug, Error)]
pub enum CheckpointError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: not a learner checkpoint manifest: {source}")]
    Manifest {
        path: PathBuf,
        source: serde_json::Error,
    },
    #[error("{path}: format {got:?}, this learner reads {FORMAT:?}")]
    Format { path: PathBuf, got: String },
    #[error("checkpoint does not fit this learner: {0}")]
    Mismatch(String),
    #[error("libtorch: {0}")]
    Torch(#[from] tch::TchError),
    #[error(transparent)]
    Learner(#[from] crate::error::LearnerError),
}

type Result<T> = std::result::Result<T, CheckpointError>;

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> CheckpointError + '_ {
    move |source| CheckpointError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// The learner's counters (all restored on resume).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Progress {
    /// Transitions stored (received and accepted) over the whole run.
    pub env_steps: u64,
    pub critic_updates: u64,
    pub actor_updates: u64,
    /// The last published policy version (1 = the initial weights).
    pub policy_version: u64,
    /// 1 or 2.
    pub stage: u32,
    pub stage_epoch: u64,
    /// Env steps when stage 2 began (`train_stats/stage_1_steps`).
    pub stage_1_steps: Option<u64>,
    pub dropped_stale_epoch: u64,
    /// Received records not used because the run stopped (budget reached or shutdown).
    pub discarded: u64,
    pub next_checkpoint_at: u64,
    pub next_log_at: u64,
    /// Wall-clock milliseconds of training over all processes of the run.
    pub wall_ms: u64,
}

/// Position of one replay ring.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct BufferMeta {
    pub capacity: usize,
    pub len: usize,
    pub cursor: usize,
}

impl BufferMeta {
    fn of(buffer: &ReplayBuffer) -> Self {
        Self {
            capacity: buffer.capacity(),
            len: buffer.len(),
            cursor: buffer.cursor(),
        }
    }
}

/// `learner.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Manifest {
    pub format: String,
    pub generation: u64,
    pub run_name: String,
    pub obs_dim: usize,
    pub action_dim: usize,
    /// The resolved config the checkpoint was written under.
    pub config_yaml: String,
    pub progress: Progress,
    pub limiter: UtdLimiter,
    pub sac_rng: ChaCha8Rng,
    pub replay_rng: ChaCha8Rng,
    pub online: BufferMeta,
    pub offline: Option<BufferMeta>,
    pub networks_file: String,
    pub optimizers_file: String,
    pub replay_file: String,
    pub replay_bytes: u64,
}

/// What a checkpoint holds besides the agent and the buffers.
#[derive(Debug, Clone)]
pub struct Extras<'a> {
    pub run_name: &'a str,
    pub config_yaml: &'a str,
    pub progress: &'a Progress,
    pub limiter: &'a UtdLimiter,
}

pub fn checkpoint_dir(run_dir: &Path) -> PathBuf {
    run_dir.join("checkpoint")
}

/// The manifest in `dir`, or `None` when there is no checkpoint.
pub fn read_manifest(dir: &Path) -> Result<Option<Manifest>> {
    let path = dir.join(MANIFEST);
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(io(&path)(e)),
    };
    let manifest: Manifest =
        serde_json::from_str(&text).map_err(|source| CheckpointError::Manifest {
            path: path.clone(),
            source,
        })?;
    if manifest.format != FORMAT {
        return Err(CheckpointError::Format {
            path,
            got: manifest.format,
        });
    }
    Ok(Some(manifest))
}

/// Writes a checkpoint of `sac`, `replay` and `extras` into `dir` (see the module docs).
/// Returns the manifest written.
pub fn save(dir: &Path, sac: &Sac, replay: &Replay, extras: &Extras<'_>) -> Result<Manifest> {
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let generation = read_manifest(dir)?.map_or(1, |m| m.generation + 1);
    let networks_file = format!("networks.{generation}.safetensors");
    let optimizers_file = format!("optimizers.{generation}.safetensors");
    let replay_file = format!("replay.{generation}.bin");

    write_tensors(&dir.join(&networks_file), &network_tensors(sac))?;
    write_tensors(&dir.join(&optimizers_file), &optimizer_tensors(sac))?;
    let replay_bytes = write_replay(&dir.join(&replay_file), replay)?;

    let manifest = Manifest {
        format: FORMAT.into(),
        generation,
        run_name: extras.run_name.into(),
        obs_dim: sac.obs_dim(),
        action_dim: sac.action_dim(),
        config_yaml: extras.config_yaml.into(),
        progress: extras.progress.clone(),
        limiter: extras.limiter.clone(),
        sac_rng: sac.rng().clone(),
        replay_rng: replay.rng().clone(),
        online: BufferMeta::of(&replay.online),
        offline: replay.offline.as_ref().map(BufferMeta::of),
        networks_file,
        optimizers_file,
        replay_file,
        replay_bytes,
    };
    let path = dir.join(MANIFEST);
    let json = serde_json::to_vec_pretty(&manifest).expect("a manifest serialises");
    rfcl_core::atomic::atomic_write(&path, &json).map_err(io(&path))?;
    remove_other_generations(dir, &manifest);
    Ok(manifest)
}

/// Restores the agent's weights, optimiser states and RNG from a checkpoint into `sac` (built with
/// the same config and dims), and returns the replay it held.
pub fn restore(dir: &Path, manifest: &Manifest, sac: &mut Sac) -> Result<Replay> {
    if (manifest.obs_dim, manifest.action_dim) != (sac.obs_dim(), sac.action_dim()) {
        return Err(CheckpointError::Mismatch(format!(
            "the checkpoint has obs_dim {} / action_dim {}, the demos {} / {}",
            manifest.obs_dim,
            manifest.action_dim,
            sac.obs_dim(),
            sac.action_dim()
        )));
    }
    let networks = read_tensors(&dir.join(&manifest.networks_file))?;
    for (prefix, vs) in [
        ("actor", sac.actor_vars()),
        ("critic", sac.critic_vars()),
        ("target", sac.target_critic_vars()),
        ("temperature", sac.temperature_vars()),
    ] {
        let vars: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
        tch::no_grad(|| -> Result<()> {
            for (name, var) in vars {
                let key = format!("{prefix}/{name}");
                let src = find(&networks, &key)?;
                if src.size() != var.size() {
                    return Err(CheckpointError::Mismatch(format!(
                        "{key} has shape {:?}, the network {:?} (was the network config changed?)",
                        src.size(),
                        var.size()
                    )));
                }
                var.shallow_clone().f_copy_(src)?;
            }
            Ok(())
        })?;
    }
    let optimizers = read_tensors(&dir.join(&manifest.optimizers_file))?;
    for (name, adam) in sac.optimizers_mut() {
        let prefix = format!("{name}/");
        let state: Vec<(String, Tensor)> = optimizers
            .iter()
            .filter_map(|(k, t)| {
                k.strip_prefix(&prefix)
                    .map(|k| (k.to_string(), t.shallow_clone()))
            })
            .collect();
        adam.load_state(&state)?;
    }
    sac.set_rng(manifest.sac_rng.clone());

    let (d, a) = (manifest.obs_dim, manifest.action_dim);
    let path = dir.join(&manifest.replay_file);
    let file = File::open(&path).map_err(io(&path))?;
    let size = file.metadata().map_err(io(&path))?.len();
    if size != manifest.replay_bytes {
        return Err(CheckpointError::Mismatch(format!(
            "{} is {size} bytes, the manifest says {}",
            path.display(),
            manifest.replay_bytes
        )));
    }
    let mut reader = BufReader::with_capacity(1 << 20, file);
    let online = read_buffer(&mut reader, &path, "online", manifest.online, d, a)?;
    let offline = manifest
        .offline
        .map(|meta| read_buffer(&mut reader, &path, "offline", meta, d, a))
        .transpose()?;
    let mut replay = Replay::new(online, offline, 0);
    replay.set_rng(manifest.replay_rng.clone());
    Ok(replay)
}

/// Every network variable as `<store>/<name>`, on the host.
pub fn network_tensors(sac: &Sac) -> Vec<(String, Tensor)> {
    let mut out = Vec::new();
    for (prefix, vs) in [
        ("actor", sac.actor_vars()),
        ("critic", sac.critic_vars()),
        ("target", sac.target_critic_vars()),
        ("temperature", sac.temperature_vars()),
    ] {
        for (name, t) in vs.variables() {
            out.push((format!("{prefix}/{name}"), host(&t)));
        }
    }
    out.sort_by(|a, b| a.0.cmp(&b.0));
    out
}

/// Every Adam state tensor as `<optimizer>/<name>`, on the host.
pub fn optimizer_tensors(sac: &Sac) -> Vec<(String, Tensor)> {
    let mut out = Vec::new();
    for (opt, adam) in sac.optimizers() {
        for (name, t) in adam.state() {
            out.push((format!("{opt}/{name}"), host(&t)));
        }
    }
    out.sort_by(|a, b| a.0.cmp(&b.0));
    out
}

fn host(t: &Tensor) -> Tensor {
    t.detach().to_device(Device::Cpu).contiguous()
}

fn find<'a>(tensors: &'a [(String, Tensor)], name: &str) -> Result<&'a Tensor> {
    tensors
        .iter()
        .find(|(n, _)| n == name)
        .map(|(_, t)| t)
        .ok_or_else(|| CheckpointError::Mismatch(format!("the checkpoint lacks tensor {name}")))
}

fn write_tensors(path: &Path, tensors: &[(String, Tensor)]) -> Result<()> {
    Tensor::write_safetensors(tensors, path)?;
    File::open(path)
        .and_then(|f| f.sync_all())
        .map_err(io(path))
}

fn read_tensors(path: &Path) -> Result<Vec<(String, Tensor)>> {
    if !path.exists() {
        return Err(io(path)(std::io::Error::new(
            std::io::ErrorKind::NotFound,
            "checkpoint file missing",
        )));
    }
    Ok(Tensor::read_safetensors(path)?)
}

/// Field widths in the order of [`ReplayBuffer::storage`].
fn widths(d: usize, a: usize) -> [usize; 5] {
    [d, a, 1, 1, d]
}

fn write_replay(path: &Path, replay: &Replay) -> Result<u64> {
    let file = File::create(path).map_err(io(path))?;
    let mut out = BufWriter::with_capacity(1 << 20, file);
    let mut bytes = 0u64;
    for buffer in std::iter::once(&replay.online).chain(replay.offline.as_ref()) {
        let w = widths(buffer.obs_dim(), buffer.action_dim());
        for (field, width) in buffer.storage().into_iter().zip(w) {
            for chunk in field[..buffer.len() * width].chunks(1 << 16) {
                let raw: Vec<u8> = chunk.iter().flat_map(|v| v.to_le_bytes()).collect();
                out.write_all(&raw).map_err(io(path))?;
                bytes += raw.len() as u64;
            }
        }
    }
    let file = out.into_inner().map_err(|e| io(path)(e.into_error()))?;
    file.sync_all().map_err(io(path))?;
    Ok(bytes)
}

fn read_buffer(
    reader: &mut impl Read,
    path: &Path,
    name: &'static str,
    meta: BufferMeta,
    d: usize,
    a: usize,
) -> Result<ReplayBuffer> {
    let mut buffer = ReplayBuffer::new(name, meta.capacity, d, a)?;
    let fields = buffer.restore_storage(meta.len, meta.cursor)?;
    let mut raw = vec![0u8; 4 << 16];
    for (field, width) in fields.into_iter().zip(widths(d, a)) {
        for chunk in field[..meta.len * width].chunks_mut(1 << 16) {
            let raw = &mut raw[..chunk.len() * 4];
            reader.read_exact(raw).map_err(io(path))?;
            for (v, b) in chunk.iter_mut().zip(raw.chunks_exact(4)) {
                *v = f32::from_le_bytes(b.try_into().expect("4 bytes"));
            }
        }
    }
    Ok(buffer)
}

/// Deletes data files of generations other than the manifest's (best effort).
fn remove_other_generations(dir: &Path, manifest: &Manifest) {
    let keep = [
        &manifest.networks_file,
        &manifest.optimizers_file,
        &manifest.replay_file,
    ];
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().to_string();
        let ours = ["networks.", "optimizers.", "replay."]
            .iter()
            .any(|p| name.starts_with(p));
        if ours && !keep.iter().any(|k| **k == name) {
            if let Err(e) = std::fs::remove_file(entry.path()) {
                tracing::warn!("removing the old checkpoint file {name}: {e}");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::batch::HostBatch;
    use rfcl_core::config::{NetworkConfig, SacConfig, UtdMode};

    fn small() -> (SacConfig, NetworkConfig) {
        let sac = SacConfig {
            batch_size: 4,
            grad_updates_per_step: 2,
            actor_update_freq: 1,
            critic_ensemble: 3,
            target_pool: 3,
            ..SacConfig::default()
        };
        let net = NetworkConfig {
            actor_features: vec![8, 8],
            critic_features: vec![8, 8],
            ..NetworkConfig::default()
        };
        (sac, net)
    }

    fn filled_replay(seed: u64) -> Replay {
        let mut online = ReplayBuffer::new("online", 10, 3, 2).unwrap();
        let mut offline = ReplayBuffer::new("offline", 5, 3, 2).unwrap();
        for i in 0..13 {
            let x = i as f32;
            online
                .push(
                    &[x, x + 0.5, -x],
                    &[0.1, -0.2],
                    x / 10.0,
                    1.0,
                    &[x, 0.0, 1.0],
                )
                .unwrap();
        }
        for i in 0..4 {
            let x = i as f32;
            offline
                .push(&[x; 3], &[0.3, 0.4], 1.0, 1.0, &[x + 1.0; 3])
                .unwrap();
        }
        Replay::new(online, Some(offline), seed)
    }

    fn tensors_equal(a: &[(String, Tensor)], b: &[(String, Tensor)]) -> bool {
        a.len() == b.len()
            && a.iter()
                .zip(b)
                .all(|((na, ta), (nb, tb))| na == nb && ta.equal(tb))
    }

    #[test]
    fn save_then_restore_gives_identical_state_and_the_same_next_iteration() {
        let (cfg, net) = small();
        let mut sac = Sac::new(3, 2, &cfg, &net, 5).unwrap();
        let mut replay = filled_replay(9);
        // Train a little so the optimiser states are not zero.
        for _ in 0..3 {
            let batch = replay
                .sample(2, 4)
                .unwrap()
                .to_tensors(sac.kind(), sac.device());
            sac.train_iteration(&batch).unwrap();
        }
        let dir = tempfile::tempdir().unwrap();
        let progress = Progress {
            env_steps: 13,
            critic_updates: 6,
            policy_version: 3,
            stage: 1,
            ..Progress::default()
        };
        let limiter = UtdLimiter::new(UtdMode::Sync, 4, 2, 0);
        let extras = Extras {
            run_name: "t",
            config_yaml: "name: t\n",
            progress: &progress,
            limiter: &limiter,
        };
        save(dir.path(), &sac, &replay, &extras).unwrap();
        // A second save replaces the first generation's files.
        let manifest = save(dir.path(), &sac, &replay, &extras).unwrap();
        assert_eq!(manifest.generation, 2);
        let mut names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
            .collect();
        names.sort();
        assert_eq!(
            names,
            [
                "learner.json",
                "networks.2.safetensors",
                "optimizers.2.safetensors",
                "replay.2.bin"
            ]
        );

        let manifest = read_manifest(dir.path()).unwrap().unwrap();
        assert_eq!(manifest.progress, progress);
        assert_eq!(manifest.limiter, limiter);
        let mut fresh = Sac::new(3, 2, &cfg, &net, 99).unwrap();
        let mut restored = restore(dir.path(), &manifest, &mut fresh).unwrap();
        assert!(tensors_equal(
            &network_tensors(&sac),
            &network_tensors(&fresh)
        ));
        assert!(tensors_equal(
            &optimizer_tensors(&sac),
            &optimizer_tensors(&fresh)
        ));
        for (a, b) in [
            (&replay.online, &restored.online),
            (
                replay.offline.as_ref().unwrap(),
                restored.offline.as_ref().unwrap(),
            ),
        ] {
            assert_eq!(
                (a.len(), a.cursor(), a.capacity()),
                (b.len(), b.cursor(), b.capacity())
            );
            assert_eq!(a.storage(), b.storage());
        }
        // Both continue identically: same sample, same update.
        let next: HostBatch = replay.sample(2, 4).unwrap();
        assert_eq!(next, restored.sample(2, 4).unwrap());
        let m1 = sac
            .train_iteration(&next.to_tensors(sac.kind(), sac.device()))
            .unwrap();
        let m2 = fresh
            .train_iteration(&next.to_tensors(fresh.kind(), fresh.device()))
            .unwrap();
        assert_eq!(m1, m2);
        assert!(tensors_equal(
            &network_tensors(&sac),
            &network_tensors(&fresh)
        ));
    }

    #[test]
    fn a_missing_or_foreign_manifest_is_reported() {
        let dir = tempfile::tempdir().unwrap();
        assert!(read_manifest(dir.path()).unwrap().is_none());
        std::fs::write(dir.path().join(MANIFEST), "{\"format\": 1}").unwrap();
        assert!(matches!(
            read_manifest(dir.path()),
            Err(CheckpointError::Manifest { .. })
        ));
    }
}
