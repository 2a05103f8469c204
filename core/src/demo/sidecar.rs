//! The JSON sidecar of a trajectory file (spec 6.1): `env_info` and `episodes[]`.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use serde::de::Error as _;
use serde::{Deserialize, Deserializer};
use serde_json::{json, Map, Value};

use super::{DemoError, DemoSet, ResetArgs};

/// What the reader keeps of a sidecar.
pub(super) struct Sidecar {
    pub path: PathBuf,
    pub env_info: Value,
    pub episodes: HashMap<u64, Episode>,
    /// The first `control_mode` found in `episodes[]`.
    pub first_control_mode: Option<String>,
}

/// What the reader keeps of one `episodes[]` entry.
pub(super) struct Episode {
    pub reset: ResetArgs,
    /// Top-level `success` (MS3), else `info.success` (MS2, Adroit, MetaWorld).
    pub success: Option<bool>,
}

#[derive(Deserialize)]
struct File {
    env_info: Value,
    episodes: Vec<EpisodeEntry>,
}

#[derive(Deserialize)]
struct EpisodeEntry {
    episode_id: u64,
    #[serde(default)]
    reset_kwargs: ResetKwargs,
    #[serde(default, deserialize_with = "seed")]
    episode_seed: Option<u64>,
    #[serde(default)]
    success: Option<bool>,
    #[serde(default)]
    info: Option<EpisodeInfo>,
    #[serde(default)]
    control_mode: Option<String>,
}

#[derive(Deserialize, Default)]
struct ResetKwargs {
    #[serde(default, deserialize_with = "seed")]
    seed: Option<u64>,
    #[serde(default, deserialize_with = "options")]
    options: Option<Map<String, Value>>,
}

#[derive(Deserialize)]
struct EpisodeInfo {
    #[serde(default)]
    success: Option<bool>,
}

/// A seed: null, a non-negative integer, or a one-element list of one (batched resets).
fn seed<'de, D: Deserializer<'de>>(d: D) -> Result<Option<u64>, D::Error> {
    let value = Value::deserialize(d)?;
    let seed = match &value {
        Value::Null => return Ok(None),
        Value::Array(items) if items.len() == 1 => &items[0],
        other => other,
    };
    seed.as_u64().map(Some).ok_or_else(|| {
        D::Error::custom(format!("expected a non-negative integer seed, got {value}"))
    })
}

/// Reset options: null or a JSON object.
fn options<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Map<String, Value>>, D::Error> {
    match Value::deserialize(d)? {
        Value::Null => Ok(None),
        Value::Object(map) => Ok(Some(map)),
        other => Err(D::Error::custom(format!(
            "expected reset options as a JSON object, got {other}"
        ))),
    }
}

/// Reads the sidecar of `h5_path`; `Ok(None)` when there is none.
pub(super) fn read(h5_path: &Path) -> Result<Option<Sidecar>, DemoError> {
    let path = DemoSet::sidecar_path(h5_path);
    let text = match std::fs::read_to_string(&path) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(error) => return Err(DemoError::Io { path, error }),
    };
    let file: File = serde_json::from_str(&text).map_err(|error| DemoError::Sidecar {
        path: path.clone(),
        error,
    })?;
    let first_control_mode = file.episodes.iter().find_map(|e| e.control_mode.clone());
    let mut episodes = HashMap::with_capacity(file.episodes.len());
    for entry in file.episodes {
        let episode = Episode {
            reset: ResetArgs {
                seed: entry.reset_kwargs.seed.or(entry.episode_seed),
                options: Value::Object(entry.reset_kwargs.options.unwrap_or_default()),
            },
            success: entry.success.or(entry.info.and_then(|i| i.success)),
        };
        if episodes.insert(entry.episode_id, episode).is_some() {
            let message = format!(
                "episode_id {} appears twice in episodes[]",
                entry.episode_id
            );
            return Err(DemoError::format(&path, message));
        }
    }
    Ok(Some(Sidecar {
        path,
        env_info: file.env_info,
        episodes,
        first_control_mode,
    }))
}

/// The sidecar of `set` in ManiSkill's form: `env_info` and one `episodes[]` entry per demo.
pub(super) fn to_json(set: &DemoSet) -> Value {
    let mut env_info = match &set.env_info {
        Value::Object(map) => map.clone(),
        _ => Map::new(),
    };
    if let Some(env_id) = &set.env_id {
        env_info.insert("env_id".into(), json!(env_id));
    }
    let episodes: Vec<Value> = set
        .demos
        .iter()
        .map(|demo| {
            let mut entry = json!({
                "episode_id": demo.episode_id,
                "reset_kwargs": { "seed": demo.reset.seed, "options": demo.reset.options },
                "elapsed_steps": demo.len(),
                "success": demo.succeeded,
            });
            if let Some(seed) = demo.reset.seed {
                entry["episode_seed"] = json!(seed);
            }
            if let Some(mode) = &set.control_mode {
                entry["control_mode"] = json!(mode);
            }
            entry
        })
        .collect();
    json!({ "env_info": env_info, "episodes": episodes })
}
