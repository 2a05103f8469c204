//! Learner checkpoints (spec 4.1 "each model's state = params + optimizer state + step"):
//! everything a resumed learner needs to continue
//! exactly where it stopped.
//!
//! Layout of `RUN_DIR/checkpoint/`:
//!
//! | file                                  | contents                                               |
//! |---------------------------------------|--------------------------------------------------------|
//! | `learner.json`                        | the manifest: counters, UTD limiter, RNG states, buffer positions, config, the names, sizes and CRC-32Cs of every data file |
//! | `networks.<gen>.safetensors`          | `actor/*`, `critic/*`, `target/*`, `temperature/log_alpha` in their own dtype |
//! | `optimizers.<gen>.safetensors`        | `<actor|critic|temperature>/{step, exp_avg.*, exp_avg_sq.*}` (Adam) |
//! | `replay.<gen>.<buffer>.<k>.bin`       | segment k of the `online` or `offline` buffer: its rows [k·N, min((k+1)·N, len)) as fields obs, action, reward, mask, next_obs, little-endian `f32`; N = the buffer's `segment_rows` ([`SEGMENT_ROWS`](crate::replay::SEGMENT_ROWS)) |
//!
//! `<gen>` is the generation that wrote the file. The replay is written by segments so that a
//! checkpoint writes only what changed: a segment no push touched since the checkpoint that wrote
//! it keeps its file (the manifest of the next generation names it again), and one that was pushed
//! into (new rows, or old ones overwritten once the ring wrapped) is written anew. A buffer moved
//! at the stage transition keeps its files.
//!
//! | `learner.prev.json`                   | the previous generation's manifest: the fallback       |
//!
//! Commit protocol: the data files of generation `gen` are written under new names and fsynced,
//! the current manifest (when whole) is copied to `learner.prev.json`, then the manifest is
//! replaced atomically ([`rfcl_core::atomic::atomic_write`]); only then are the files neither
//! manifest names deleted. A `kill -9` at any moment leaves the previous checkpoint or the new one,
//! never a mix.
//!
//! Damage is detected, never trusted: the manifest carries a CRC-32C of its own bytes (`checksum`,
//! computed with its value zeroed), and names the CRC-32C of every data file. [`read_manifest`]
//! gives the newest generation that is whole (`learner.json`, or else `learner.prev.json`, with a
//! warning naming the damage) and refuses when neither is.
use std::collections::HashSet;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tch::{Device, Tensor};
use thiserror::Error;

use crate::limiter::UtdLimiter;
use crate::replay::{Replay, ReplayBuffer, SegmentFile};
use crate::sac::Sac;

/// The manifest's `format`.
pub const FORMAT: &str = "rfcl-learner-checkpoint-v3";
/// The format before manifests carried checksums: still read (nothing to verify but the replay).
const FORMAT_V2: &str = "rfcl-learner-checkpoint-v2";
pub const MANIFEST: &str = "learner.json";
/// The generation before [`MANIFEST`]'s, kept as the fallback.
pub const PREVIOUS: &str = "learner.prev.json";
/// What a user can do when no generation is intact.
const AFRESH: &str = "move this directory aside to start the learner afresh (the curriculum \
                      keeps its progress; the learner's networks and replay start over)";

/// Causes are sources, never repeated in the message: `{:#}` (anyhow) and
/// [`crate::error::chain`] print each once.
#[derive(Debug, Error)]
pub enum CheckpointError {
    #[error("{}", path.display())]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: not a learner checkpoint manifest", path.display())]
    Manifest {
        path: PathBuf,
        source: serde_json::Error,
    },
    #[error("{}: format {got:?}, this learner reads {FORMAT:?}", path.display())]
    Format { path: PathBuf, got: String },
    #[error("checkpoint does not fit this learner: {0}")]
    Mismatch(String),
    #[error("{}: {problem}", path.display())]
    Corrupt { path: PathBuf, problem: String },
    /// Refused: a checkpoint never holds weights a resumed run could not continue from.
    #[error("refusing to checkpoint non-finite (NaN or infinite) values in tensor {tensor}")]
    NonFinite { tensor: String },
    #[error("libtorch")]
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

/// Position of one replay ring and the files of its segments.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct BufferMeta {
    pub capacity: usize,
    pub len: usize,
    pub cursor: usize,
    pub segment_rows: usize,
    /// One per stored segment, in order (`ceil(len / segment_rows)` of them).
    pub segments: Vec<SegmentFile>,
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
    /// CRC-32C of the networks and optimizers files (absent in v2 checkpoints).
    #[serde(default)]
    pub networks_crc32c: Option<u32>,
    #[serde(default)]
    pub optimizers_crc32c: Option<u32>,
    /// Bytes of all replay segment files this checkpoint names.
    pub replay_bytes: u64,
    /// CRC-32C of this manifest's bytes with this value written as `00000000`, in hex (v3).
    #[serde(default)]
    pub checksum: Option<String>,
}

impl Manifest {
    /// Every data file this checkpoint needs.
    pub fn files(&self) -> impl Iterator<Item = &str> {
        [self.networks_file.as_str(), self.optimizers_file.as_str()]
            .into_iter()
            .chain(self.segments().map(|s| s.file.as_str()))
    }

    /// Every replay segment file this checkpoint names, online buffer first.
    pub fn segments(&self) -> impl Iterator<Item = &SegmentFile> {
        std::iter::once(&self.online)
            .chain(self.offline.as_ref())
            .flat_map(|b| &b.segments)
    }
}

/// What [`save`] wrote.
#[derive(Debug, Clone)]
pub struct Saved {
    pub manifest: Manifest,
    /// Replay segment files written by this checkpoint (the others were kept).
    pub replay_files_written: usize,
    pub replay_bytes_written: u64,
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

/// The newest whole checkpoint's manifest in `dir`, or `None` when there is no checkpoint: the
/// current one, or when it or a data file it names is damaged the previous generation's (a
/// warning names the damage). Refused when neither is whole.
pub fn read_manifest(dir: &Path) -> Result<Option<Manifest>> {
    let current = match read_verified(dir, MANIFEST) {
        Ok(None) => return Ok(None),
        Ok(Some(m)) => return Ok(Some(m)),
        Err(e) => e,
    };
    match read_verified(dir, PREVIOUS) {
        Ok(Some(previous)) => {
            tracing::warn!(
                generation = previous.generation,
                "the checkpoint in {} is damaged ({}): resuming from the generation before it",
                dir.display(),
                crate::error::chain(&current)
            );
            Ok(Some(previous))
        }
        // Damage is said with what to do: the learner cannot continue this run's learning.
        Ok(None) => Err(match current {
            CheckpointError::Corrupt { .. } => CheckpointError::Corrupt {
                path: dir.to_path_buf(),
                problem: format!(
                    "{}; there is no generation before it to fall back to: {AFRESH}",
                    crate::error::chain(&current)
                ),
            },
            other => other,
        }),
        Err(previous) => Err(CheckpointError::Corrupt {
            path: dir.to_path_buf(),
            problem: format!(
                "both generations are damaged: {}; and {}; {AFRESH}",
                crate::error::chain(&current),
                crate::error::chain(&previous)
            ),
        }),
    }
}

/// The manifest `dir/name` with its own checksum and every data file's CRC-32C checked.
fn read_verified(dir: &Path, name: &str) -> Result<Option<Manifest>> {
    let Some(manifest) = read_one(dir, name)? else {
        return Ok(None);
    };
    verify_files(dir, &manifest, true)?;
    Ok(Some(manifest))
}

/// The manifest `dir/name` with its own checksum checked (v3), or `None` when the file is absent.
fn read_one(dir: &Path, name: &str) -> Result<Option<Manifest>> {
    let path = dir.join(name);
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
    match manifest.format.as_str() {
        FORMAT => {
            rfcl_core::checksum::verify(text.as_bytes()).map_err(|e| CheckpointError::Corrupt {
                path: path.clone(),
                problem: e.to_string(),
            })?;
        }
        FORMAT_V2 => {}
        _ => {
            return Err(CheckpointError::Format {
                path,
                got: manifest.format,
            })
        }
    }
    Ok(Some(manifest))
}

/// The manifest as written: pretty JSON whose `checksum` is the CRC-32C of these bytes with the
/// value zeroed.
fn manifest_bytes(manifest: &Manifest) -> Vec<u8> {
    let mut manifest = manifest.clone();
    manifest.checksum = Some(rfcl_core::checksum::UNSEALED.into());
    rfcl_core::checksum::seal(serde_json::to_vec_pretty(&manifest).expect("a manifest serialises"))
}

/// Every data file `manifest` names is there with its size, and (with `contents`) its CRC-32C.
fn verify_files(dir: &Path, manifest: &Manifest, contents: bool) -> Result<()> {
    let tensors = [
        (&manifest.networks_file, manifest.networks_crc32c),
        (&manifest.optimizers_file, manifest.optimizers_crc32c),
    ];
    for (file, crc) in tensors {
        let path = dir.join(file);
        if !path.is_file() {
            return Err(io(&path)(std::io::Error::new(
                std::io::ErrorKind::NotFound,
                "checkpoint file missing",
            )));
        }
        if let (Some(want), true) = (crc, contents) {
            check_crc(&path, want)?;
        }
    }
    for segment in manifest.segments() {
        let path = dir.join(&segment.file);
        if !file_has_size(&path, segment.bytes) {
            return Err(CheckpointError::Corrupt {
                path,
                problem: format!(
                    "missing, or not the {} bytes the manifest says",
                    segment.bytes
                ),
            });
        }
        if contents {
            check_crc(&path, segment.crc32c)?;
        }
    }
    Ok(())
}

fn check_crc(path: &Path, want: u32) -> Result<()> {
    let raw = std::fs::read(path).map_err(io(path))?;
    let crc = crc32c::crc32c(&raw);
    if crc != want {
        return Err(CheckpointError::Corrupt {
            path: path.to_path_buf(),
            problem: format!("CRC-32C {crc:#010x}, the manifest says {want:#010x}"),
        });
    }
    Ok(())
}

/// The highest generation any manifest in `dir` names, damaged or not (a new one never reuses it).
fn last_generation(dir: &Path) -> u64 {
    #[derive(Deserialize)]
    struct Generation {
        generation: u64,
    }
    [MANIFEST, PREVIOUS]
        .iter()
        .filter_map(|name| std::fs::read(dir.join(name)).ok())
        .filter_map(|bytes| serde_json::from_slice::<Generation>(&bytes).ok())
        .map(|g| g.generation)
        .max()
        .unwrap_or(0)
}

/// Writes a checkpoint of `sac`, `replay` and `extras` into `dir` (see the module docs): the
/// replay segments changed since the last checkpoint into `dir`, the others are named again. The
/// buffers remember which file holds each segment once the manifest is committed.
pub fn save(dir: &Path, sac: &Sac, replay: &mut Replay, extras: &Extras<'_>) -> Result<Saved> {
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let generation = last_generation(dir) + 1;
    let networks_file = format!("networks.{generation}.safetensors");
    let optimizers_file = format!("optimizers.{generation}.safetensors");

    let networks = network_tensors(sac);
    let optimizers = optimizer_tensors(sac);
    for (name, t) in networks.iter().chain(&optimizers) {
        if !all_finite(t)? {
            return Err(CheckpointError::NonFinite {
                tensor: name.clone(),
            });
        }
    }
    let networks_crc32c = write_tensors(&dir.join(&networks_file), &networks)?;
    let optimizers_crc32c = write_tensors(&dir.join(&optimizers_file), &optimizers)?;

    // (buffer, segment, file) of the segments written now: recorded in the buffers only once the
    // manifest naming them is committed.
    let mut written: Vec<(usize, usize, SegmentFile)> = Vec::new();
    let mut metas = Vec::new();
    for (b, buffer) in buffers(replay).enumerate() {
        let mut segments = Vec::with_capacity(buffer.stored_segments());
        for k in 0..buffer.stored_segments() {
            let kept = buffer
                .saved_segment(k)
                .filter(|f| file_has_size(&dir.join(&f.file), f.bytes));
            let file = match kept {
                Some(file) => file.clone(),
                None => {
                    let name = format!("replay.{generation}.{}.{k}.bin", buffer.name());
                    let file = write_segment(&dir.join(&name), name, buffer, k)?;
                    written.push((b, k, file.clone()));
                    file
                }
            };
            segments.push(file);
        }
        metas.push(BufferMeta {
            capacity: buffer.capacity(),
            len: buffer.len(),
            cursor: buffer.cursor(),
            segment_rows: buffer.segment_rows(),
            segments,
        });
    }
    let mut metas = metas.into_iter();
    let online = metas.next().expect("the online buffer");
    let offline = metas.next();
    let replay_bytes = std::iter::once(&online)
        .chain(offline.as_ref())
        .flat_map(|m| &m.segments)
        .map(|f| f.bytes)
        .sum();

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
        online,
        offline,
        networks_file,
        optimizers_file,
        networks_crc32c: Some(networks_crc32c),
        optimizers_crc32c: Some(optimizers_crc32c),
        replay_bytes,
        checksum: None,
    };
    // The current generation becomes the fallback when it is whole (its files' CRCs were checked
    // when it was written or read; a damaged one never replaces a good fallback).
    let current = read_one(dir, MANIFEST)
        .ok()
        .flatten()
        .filter(|m| verify_files(dir, m, false).is_ok());
    let previous = match current {
        Some(current) => {
            let path = dir.join(PREVIOUS);
            rfcl_core::atomic::atomic_write(&path, &manifest_bytes(&current)).map_err(io(&path))?;
            Some(current)
        }
        None => read_one(dir, PREVIOUS).ok().flatten(),
    };
    let path = dir.join(MANIFEST);
    rfcl_core::atomic::atomic_write(&path, &manifest_bytes(&manifest)).map_err(io(&path))?;

    let saved = Saved {
        replay_files_written: written.len(),
        replay_bytes_written: written.iter().map(|(_, _, f)| f.bytes).sum(),
        manifest,
    };
    for (b, k, file) in written {
        let buffer = if b == 0 {
            &mut replay.online
        } else {
            replay
                .offline
                .as_mut()
                .expect("written from the offline buffer")
        };
        buffer.set_saved_segment(k, file);
    }
    remove_unnamed(dir, &saved.manifest, previous.as_ref());
    Ok(saved)
}

fn buffers(replay: &Replay) -> impl Iterator<Item = &ReplayBuffer> {
    std::iter::once(&replay.online).chain(replay.offline.as_ref())
}

fn file_has_size(path: &Path, bytes: u64) -> bool {
    std::fs::metadata(path).is_ok_and(|m| m.len() == bytes)
}

/// Whether every value of `t` is finite (integer tensors always are).
pub fn all_finite(t: &Tensor) -> Result<bool> {
    if !t.is_floating_point() {
        return Ok(true);
    }
    Ok(t.f_isfinite()?.f_all()?.f_int64_value(&[])? != 0)
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
    let online = read_buffer(dir, "online", &manifest.online, d, a)?;
    let offline = manifest
        .offline
        .as_ref()
        .map(|meta| read_buffer(dir, "offline", meta, d, a))
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

/// Writes and fsyncs `tensors`; returns the file's CRC-32C.
fn write_tensors(path: &Path, tensors: &[(String, Tensor)]) -> Result<u32> {
    Tensor::write_safetensors(tensors, path)?;
    File::open(path)
        .and_then(|f| f.sync_all())
        .map_err(io(path))?;
    Ok(crc32c::crc32c(&std::fs::read(path).map_err(io(path))?))
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

/// Writes segment `k` of `buffer` to `path` (fsynced): each field's rows of the segment in turn.
fn write_segment(
    path: &Path,
    name: String,
    buffer: &ReplayBuffer,
    k: usize,
) -> Result<SegmentFile> {
    let rows = buffer.segment_range(k);
    let file = File::create(path).map_err(io(path))?;
    let mut out = BufWriter::with_capacity(1 << 20, file);
    let (mut bytes, mut crc) = (0u64, 0u32);
    let mut raw = Vec::with_capacity(4 << 14);
    let w = widths(buffer.obs_dim(), buffer.action_dim());
    for (field, width) in buffer.storage().into_iter().zip(w) {
        for chunk in field[rows.start * width..rows.end * width].chunks(1 << 14) {
            raw.clear();
            for v in chunk {
                raw.extend_from_slice(&v.to_le_bytes());
            }
            crc = crc32c::crc32c_append(crc, &raw);
            out.write_all(&raw).map_err(io(path))?;
            bytes += raw.len() as u64;
        }
    }
    let file = out.into_inner().map_err(|e| io(path)(e.into_error()))?;
    file.sync_all().map_err(io(path))?;
    Ok(SegmentFile {
        file: name,
        rows: rows.len(),
        bytes,
        crc32c: crc,
    })
}

/// A buffer as the manifest describes it, each segment checked (rows, size, CRC) and read into
/// place; the buffer then knows its segments are saved.
fn read_buffer(
    dir: &Path,
    name: &'static str,
    meta: &BufferMeta,
    d: usize,
    a: usize,
) -> Result<ReplayBuffer> {
    let mut buffer = ReplayBuffer::new(name, meta.capacity, d, a)?;
    buffer.set_segment_rows(meta.segment_rows)?;
    let expected = meta.len.div_ceil(meta.segment_rows);
    if meta.segments.len() != expected {
        return Err(CheckpointError::Mismatch(format!(
            "the {name} buffer holds {} rows in segments of {}: {expected} segment files expected, the manifest names {}",
            meta.len,
            meta.segment_rows,
            meta.segments.len()
        )));
    }
    let ranges: Vec<_> = (0..expected)
        .map(|k| (k * meta.segment_rows)..((k + 1) * meta.segment_rows).min(meta.len))
        .collect();
    let widths = widths(d, a);
    let mut fields = buffer.restore_storage(meta.len, meta.cursor)?;
    for (segment, rows) in meta.segments.iter().zip(&ranges) {
        let path = dir.join(&segment.file);
        let row_bytes: usize = widths.iter().sum::<usize>() * 4;
        let want = (rows.len() * row_bytes) as u64;
        if segment.rows != rows.len() || segment.bytes != want {
            return Err(CheckpointError::Corrupt {
                path,
                problem: format!(
                    "the manifest says {} rows / {} bytes; rows {}..{} of the {name} buffer are {} rows / {want} bytes",
                    segment.rows,
                    segment.bytes,
                    rows.start,
                    rows.end,
                    rows.len()
                ),
            });
        }
        let raw = std::fs::read(&path).map_err(io(&path))?;
        if raw.len() as u64 != want {
            return Err(CheckpointError::Corrupt {
                path,
                problem: format!("{} bytes, the manifest says {want}", raw.len()),
            });
        }
        let crc = crc32c::crc32c(&raw);
        if crc != segment.crc32c {
            return Err(CheckpointError::Corrupt {
                path,
                problem: format!(
                    "CRC-32C {crc:#010x}, the manifest says {:#010x}",
                    segment.crc32c
                ),
            });
        }
        let mut at = 0;
        for (field, &width) in fields.iter_mut().zip(&widths) {
            let dst = &mut field[rows.start * width..rows.end * width];
            let n = dst.len() * 4;
            for (v, b) in dst.iter_mut().zip(raw[at..at + n].chunks_exact(4)) {
                *v = f32::from_le_bytes(b.try_into().expect("4 bytes"));
            }
            at += n;
        }
    }
    for (k, segment) in meta.segments.iter().enumerate() {
        buffer.set_saved_segment(k, segment.clone());
    }
    Ok(buffer)
}

/// Deletes the data files neither the manifest nor the fallback names (best effort; each failure
/// logged).
fn remove_unnamed(dir: &Path, manifest: &Manifest, previous: Option<&Manifest>) {
    let keep: HashSet<&str> = manifest
        .files()
        .chain(previous.into_iter().flat_map(Manifest::files))
        .collect();
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().to_string();
        let ours = ["networks.", "optimizers.", "replay."]
            .iter()
            .any(|p| name.starts_with(p));
        if ours && !keep.contains(name.as_str()) {
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
        save(dir.path(), &sac, &mut replay, &extras).unwrap();
        // A second save writes new network files, keeps the first generation's as its fallback,
        // and keeps the replay segments nothing was pushed into since.
        let saved = save(dir.path(), &sac, &mut replay, &extras).unwrap();
        assert_eq!(saved.manifest.generation, 2);
        assert_eq!(
            (saved.replay_files_written, saved.replay_bytes_written),
            (0, 0)
        );
        let mut names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
            .collect();
        names.sort();
        assert_eq!(
            names,
            [
                "learner.json",
                "learner.prev.json",
                "networks.1.safetensors",
                "networks.2.safetensors",
                "optimizers.1.safetensors",
                "optimizers.2.safetensors",
                "replay.1.offline.0.bin",
                "replay.1.online.0.bin",
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

    fn extras_for<'a>(progress: &'a Progress, limiter: &'a UtdLimiter) -> Extras<'a> {
        Extras {
            run_name: "t",
            config_yaml: "name: t\n",
            progress,
            limiter,
        }
    }

    /// A checkpoint with the default progress and the limiter every test here uses.
    fn try_save(dir: &Path, sac: &Sac, replay: &mut Replay) -> Result<Saved> {
        let limiter = UtdLimiter::new(UtdMode::Sync, 4, 2, 0);
        save(
            dir,
            sac,
            replay,
            &extras_for(&Progress::default(), &limiter),
        )
    }

    fn save_plain(dir: &Path, sac: &Sac, replay: &mut Replay) -> Saved {
        try_save(dir, sac, replay).unwrap()
    }

    fn push_rows(buffer: &mut ReplayBuffer, range: std::ops::Range<usize>) {
        for i in range {
            let x = i as f32;
            buffer
                .push(
                    &[x, -x, x * 0.5],
                    &[0.1 * x, 0.2],
                    x,
                    1.0,
                    &[x + 1.0, 0.0, 2.0],
                )
                .unwrap();
        }
    }

    fn replay_files(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
            .filter(|n| n.starts_with("replay."))
            .collect();
        names.sort();
        names
    }

    fn assert_same_buffer(a: &ReplayBuffer, b: &ReplayBuffer) {
        assert_eq!(
            (a.len(), a.cursor(), a.capacity(), a.segment_rows()),
            (b.len(), b.cursor(), b.capacity(), b.segment_rows())
        );
        assert_eq!(a.storage(), b.storage());
    }

    #[test]
    fn a_checkpoint_after_a_few_new_rows_writes_only_the_changed_segment() {
        let (cfg, net) = small();
        let sac = Sac::new(3, 2, &cfg, &net, 5).unwrap();
        let mut online = ReplayBuffer::new("online", 100, 3, 2).unwrap();
        online.set_segment_rows(10).unwrap();
        push_rows(&mut online, 0..35);
        let mut offline = ReplayBuffer::new("offline", 12, 3, 2).unwrap();
        offline.set_segment_rows(10).unwrap();
        push_rows(&mut offline, 100..112);
        let mut replay = Replay::new(online, Some(offline), 1);
        let dir = tempfile::tempdir().unwrap();

        let first = save_plain(dir.path(), &sac, &mut replay);
        let row = ReplayBuffer::record_bytes(3, 2) as u64;
        assert_eq!(first.replay_files_written, 4 + 2);
        assert_eq!(first.replay_bytes_written, (35 + 12) * row);

        // Rows 35..38 land in online segment 3 (rows 30..40): only it is written again.
        push_rows(&mut replay.online, 35..38);
        let second = save_plain(dir.path(), &sac, &mut replay);
        assert_eq!(second.replay_files_written, 1);
        assert_eq!(second.replay_bytes_written, 8 * row);
        assert_eq!(second.manifest.replay_bytes, (38 + 12) * row);
        assert_eq!(
            replay_files(dir.path()),
            [
                "replay.1.offline.0.bin",
                "replay.1.offline.1.bin",
                "replay.1.online.0.bin",
                "replay.1.online.1.bin",
                "replay.1.online.2.bin",
                // The fallback (generation 1) still names its own segment 3.
                "replay.1.online.3.bin",
                "replay.2.online.3.bin",
            ]
        );
        // Nothing new: nothing written.
        let third = save_plain(dir.path(), &sac, &mut replay);
        assert_eq!(third.replay_files_written, 0);

        let manifest = read_manifest(dir.path()).unwrap().unwrap();
        let mut fresh = Sac::new(3, 2, &cfg, &net, 99).unwrap();
        let restored = restore(dir.path(), &manifest, &mut fresh).unwrap();
        assert_same_buffer(&replay.online, &restored.online);
        assert_same_buffer(
            replay.offline.as_ref().unwrap(),
            restored.offline.as_ref().unwrap(),
        );
    }

    #[test]
    fn a_wrapped_buffer_round_trips_exactly_and_rewrites_only_overwritten_segments() {
        let (cfg, net) = small();
        let sac = Sac::new(3, 2, &cfg, &net, 5).unwrap();
        // Capacity 10 in segments of 4: rows 0-3, 4-7, 8-9.
        let mut online = ReplayBuffer::new("online", 10, 3, 2).unwrap();
        online.set_segment_rows(4).unwrap();
        push_rows(&mut online, 0..23);
        assert_eq!((online.len(), online.cursor()), (10, 3));
        let mut replay = Replay::new(online, None, 1);
        let dir = tempfile::tempdir().unwrap();
        let first = save_plain(dir.path(), &sac, &mut replay);
        assert_eq!(first.replay_files_written, 3);

        // Slots 3, 4, 5 are overwritten: segments 0 and 1 change, segment 2 does not.
        push_rows(&mut replay.online, 23..26);
        let second = save_plain(dir.path(), &sac, &mut replay);
        assert_eq!(second.replay_files_written, 2);
        assert_eq!(
            replay_files(dir.path()),
            [
                // Generation 1's segments 0 and 1 stay for the fallback.
                "replay.1.online.0.bin",
                "replay.1.online.1.bin",
                "replay.1.online.2.bin",
                "replay.2.online.0.bin",
                "replay.2.online.1.bin"
            ]
        );

        let manifest = read_manifest(dir.path()).unwrap().unwrap();
        let mut fresh = Sac::new(3, 2, &cfg, &net, 99).unwrap();
        let mut restored = restore(dir.path(), &manifest, &mut fresh).unwrap();
        assert_same_buffer(&replay.online, &restored.online);
        assert_eq!(replay.sample(2, 4).unwrap(), restored.sample(2, 4).unwrap());
        // The restored buffer knows its files: its next checkpoint writes no replay segment.
        let again = save_plain(dir.path(), &fresh, &mut restored);
        assert_eq!(again.replay_files_written, 0);

        // A damaged segment is refused, naming the file: by restore, and by read_manifest, since
        // the fallback generation names the same segment.
        let manifest = read_manifest(dir.path()).unwrap().unwrap();
        let path = dir.path().join("replay.2.online.1.bin");
        let mut raw = std::fs::read(&path).unwrap();
        raw[5] ^= 0x40;
        std::fs::write(&path, raw).unwrap();
        let err = restore(dir.path(), &manifest, &mut fresh).unwrap_err();
        assert!(
            matches!(&err, CheckpointError::Corrupt { path: p, problem } if p == &path && problem.contains("CRC-32C")),
            "{err}"
        );
        let err = read_manifest(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains("both generations are damaged") && err.contains("replay.2.online.1.bin"),
            "{err}"
        );
    }

    /// Two generations, the second with other counters; `damage` breaks something of the second.
    fn two_generations(
        damage: impl FnOnce(&Path),
    ) -> (tempfile::TempDir, Result<Option<Manifest>>) {
        let (cfg, net) = small();
        let sac = Sac::new(3, 2, &cfg, &net, 5).unwrap();
        let mut replay = filled_replay(1);
        let limiter = UtdLimiter::new(UtdMode::Sync, 4, 2, 0);
        let dir = tempfile::tempdir().unwrap();
        for env_steps in [28_368, 30_112] {
            let progress = Progress {
                env_steps,
                ..Progress::default()
            };
            save(
                dir.path(),
                &sac,
                &mut replay,
                &extras_for(&progress, &limiter),
            )
            .unwrap();
        }
        damage(dir.path());
        let read = read_manifest(dir.path());
        (dir, read)
    }

    #[test]
    fn an_undamaged_checkpoint_reads_as_its_newest_generation() {
        let (_dir, read) = two_generations(|_| {});
        let m = read.unwrap().unwrap();
        assert_eq!((m.generation, m.progress.env_steps), (2, 30_112));
    }

    #[test]
    fn a_flipped_bit_in_the_manifest_falls_back_to_the_generation_before() {
        // One bit: '3' (0x33) -> '7' (0x37) in progress.env_steps, as a flaky disk did.
        let (dir, read) = two_generations(|dir| {
            let path = dir.join(MANIFEST);
            let text = std::fs::read_to_string(&path).unwrap();
            let flipped = text.replace("\"env_steps\": 30112", "\"env_steps\": 70112");
            assert_ne!(text, flipped);
            std::fs::write(&path, flipped).unwrap();
        });
        let m = read.unwrap().unwrap();
        assert_eq!((m.generation, m.progress.env_steps), (1, 28_368));
        // Its files are all there: it restores.
        let (cfg, net) = small();
        let mut fresh = Sac::new(3, 2, &cfg, &net, 99).unwrap();
        restore(dir.path(), &m, &mut fresh).unwrap();
        // The next checkpoint is generation 3 and keeps the whole one (1) as its fallback.
        let mut replay = filled_replay(1);
        let saved = save_plain(dir.path(), &fresh, &mut replay);
        assert_eq!(saved.manifest.generation, 3);
        let previous = read_one(dir.path(), PREVIOUS).unwrap().unwrap();
        assert_eq!(previous.generation, 1);
    }

    #[test]
    fn a_damaged_network_file_falls_back_and_two_damaged_generations_are_refused() {
        let flip = |path: &Path| {
            let mut raw = std::fs::read(path).unwrap();
            let last = raw.len() - 1;
            raw[last] ^= 0x01;
            std::fs::write(path, raw).unwrap();
        };
        let (dir, read) = two_generations(|dir| flip(&dir.join("networks.2.safetensors")));
        assert_eq!(read.unwrap().unwrap().generation, 1);
        flip(&dir.path().join("optimizers.1.safetensors"));
        let err = read_manifest(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains("both generations are damaged")
                && err.contains("networks.2.safetensors")
                && err.contains("optimizers.1.safetensors")
                && err.contains("move this directory aside"),
            "{err}"
        );
        // The first checkpoint of a run has no generation before it.
        std::fs::remove_file(dir.path().join(PREVIOUS)).unwrap();
        let err = read_manifest(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains("networks.2.safetensors")
                && err.contains("no generation before it to fall back to")
                && err.contains("move this directory aside"),
            "{err}"
        );
    }

    #[test]
    fn a_checkpoint_of_the_format_before_checksums_still_reads() {
        let (dir, _) = two_generations(|_| {});
        let mut m = read_one(dir.path(), MANIFEST).unwrap().unwrap();
        m.format = FORMAT_V2.into();
        (m.checksum, m.networks_crc32c, m.optimizers_crc32c) = (None, None, None);
        let mut v = serde_json::to_value(&m).unwrap();
        for field in ["checksum", "networks_crc32c", "optimizers_crc32c"] {
            v.as_object_mut().unwrap().remove(field);
        }
        std::fs::write(dir.path().join(MANIFEST), v.to_string()).unwrap();
        let read = read_manifest(dir.path()).unwrap().unwrap();
        assert_eq!((read.generation, read.format.as_str()), (2, FORMAT_V2));
    }

    #[test]
    fn non_finite_weights_are_never_checkpointed() {
        let (cfg, net) = small();
        let sac = Sac::new(3, 2, &cfg, &net, 5).unwrap();
        let mut replay = filled_replay(1);
        let dir = tempfile::tempdir().unwrap();
        let first = save_plain(dir.path(), &sac, &mut replay);
        let (name, var) = sac.critic_vars().variables().into_iter().next().unwrap();
        tch::no_grad(|| {
            let _ = var.shallow_clone().fill_(f64::NAN);
        });
        let err = try_save(dir.path(), &sac, &mut replay).unwrap_err();
        assert!(
            matches!(&err, CheckpointError::NonFinite { tensor } if *tensor == format!("critic/{name}")),
            "{err}"
        );
        // The previous checkpoint is untouched.
        let manifest = read_manifest(dir.path()).unwrap().unwrap();
        assert_eq!(manifest.generation, first.manifest.generation);
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
