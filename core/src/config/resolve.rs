//! Resolution: YAML files with `base_config` inheritance, dotted command-line overrides, checks,
//! and the way back to YAML. See `docs/CONFIG.md` ("Resolution") for the rules in user terms.
//!
//! Every file and every override is one *layer*. Each layer is checked on its own (unknown keys,
//! types) so that an error names the file or override that holds the bad value; the layers are
//! then deep-merged in order (bases first, the file itself, then the overrides) and the result is
//! deserialized and validated. Validation errors name the layer that last set the key.
use std::collections::BTreeMap;
use std::fs;
use std::path::{Component, Path, PathBuf};

use serde_json::{Map, Value};

use super::error::{ConfigError, DidYouMean, Source};
use super::keys::{apply_aliases, check_keys, closest, schema};
use super::tree::{get, leaves, merge, parse_yaml, set, take};
use super::RunConfig;

/// The key naming a file's base(s): one path or a list, relative to the file.
const BASE_KEY: &str = "base_config";
/// The one path-valued option rebased onto the directory of the layer that sets it.
const DATASET_PATH: &str = "train.dataset_path";

/// Resolves the run config in `path`: follows its `base_config` chain, applies the dotted
/// `overrides` (`sac.batch_size=512`, `network.actor_features=[64,64]`, `train.dataset_path=null`)
/// in order, checks every key and type, and validates the result ([`RunConfig::validate`]).
///
/// A relative `train.dataset_path` is taken relative to the directory of the file that sets it
/// (the working directory for an override) and comes back absolute.
pub fn resolve_file(path: &Path, overrides: &[String]) -> Result<RunConfig, ConfigError> {
    let schema = schema();
    let mut layers = Vec::new();
    load(path, &schema, &mut Vec::new(), &mut layers)?;
    for arg in overrides {
        layers.push(override_layer(arg, &schema)?);
    }

    let mut merged = Value::Object(Map::new());
    let mut set_by = BTreeMap::new();
    for Layer { origin, tree } in layers {
        for key in leaves(&tree) {
            set_by.insert(key, origin.clone());
        }
        merge(&mut merged, tree);
    }
    let config = deserialize(&merged, &Source::File(normalize(path)))?;
    config.validate().map_err(|error| match error {
        ConfigError::Invalid {
            origin: None,
            key,
            message,
        } => ConfigError::Invalid {
            origin: set_by.get(&key).cloned(),
            key,
            message,
        },
        other => other,
    })?;
    Ok(config)
}

/// A fully resolved config as YAML; [`resolve_file`] on it gives back the same config.
pub fn to_yaml(config: &RunConfig) -> String {
    let body = serde_saphyr::to_string(config).expect("a RunConfig always serializes to YAML");
    format!("# rfcl run configuration, fully resolved (keys: docs/CONFIG.md)\n{body}")
}

/// One file's or one override's tree, checked, with where it came from.
struct Layer {
    origin: Source,
    tree: Value,
}

/// Loads `path` and its bases (depth first, in order) into `layers`. `chain` holds the files
/// being loaded, (canonical, as shown), to detect cycles. Files are opened by the path as joined;
/// messages show it with `.` and `..` folded.
fn load(
    path: &Path,
    schema: &Value,
    chain: &mut Vec<(PathBuf, PathBuf)>,
    layers: &mut Vec<Layer>,
) -> Result<(), ConfigError> {
    let shown = normalize(path);
    let read_error = |error| ConfigError::Read {
        path: shown.clone(),
        error,
    };
    let canonical = fs::canonicalize(path).map_err(read_error)?;
    if chain.iter().any(|(seen, _)| *seen == canonical) {
        let mut cycle: Vec<PathBuf> = chain.iter().map(|(_, shown)| shown.clone()).collect();
        cycle.push(shown);
        return Err(ConfigError::Cycle { chain: cycle });
    }
    let origin = Source::File(shown.clone());
    let text = fs::read_to_string(path).map_err(read_error)?;
    let mut tree = parse_yaml(&text).map_err(|message| ConfigError::Yaml {
        origin: origin.clone(),
        message,
    })?;
    if tree.is_null() {
        tree = Value::Object(Map::new());
    }
    if !tree.is_object() {
        return Err(ConfigError::Malformed {
            origin,
            // Name the kind, never the content: a mistaken base_config may point at anything.
            message: format!(
                "expected a YAML mapping of sections at the top level (env:, sac:, ...), got {}",
                json_kind(&tree)
            ),
        });
    }
    let bases = take_bases(&mut tree, &origin)?;
    let real_dir = canonical
        .parent()
        .expect("a canonical file path has a parent");
    let layer = prepare(tree, origin, real_dir, schema)?;

    chain.push((canonical, shown.clone()));
    let dir = path.parent().unwrap_or(Path::new(""));
    for base in bases {
        let base_path = dir.join(&base);
        if !base_path.is_file() {
            return Err(ConfigError::MissingBase {
                file: shown,
                base,
                resolved: normalize(&base_path),
            });
        }
        load(&base_path, schema, chain, layers)?;
    }
    chain.pop();
    layers.push(layer);
    Ok(())
}

/// Removes `base_config` from a file's tree: no base, one path, or a list of paths.
fn take_bases(tree: &mut Value, origin: &Source) -> Result<Vec<String>, ConfigError> {
    let malformed = || ConfigError::Malformed {
        origin: origin.clone(),
        message: format!("{BASE_KEY} must be a path or a list of paths"),
    };
    match take(tree, BASE_KEY) {
        None | Some(Value::Null) => Ok(Vec::new()),
        Some(Value::String(base)) => Ok(vec![base]),
        Some(Value::Array(bases)) => bases
            .into_iter()
            .map(|base| match base {
                Value::String(base) => Ok(base),
                _ => Err(malformed()),
            })
            .collect(),
        Some(_) => Err(malformed()),
    }
}

/// Parses `key=value` (the value as YAML) into a layer; relative paths are taken from the
/// working directory.
fn override_layer(arg: &str, schema: &Value) -> Result<Layer, ConfigError> {
    let origin = Source::Override(arg.to_owned());
    let malformed = |message: &str| ConfigError::Malformed {
        origin: origin.clone(),
        message: message.to_owned(),
    };
    let (key, value) = arg
        .split_once('=')
        .ok_or_else(|| malformed("expected KEY=VALUE, e.g. sac.batch_size=512"))?;
    let key = key.trim();
    if key.split('.').any(|segment| segment.trim().is_empty()) {
        return Err(malformed(
            "the key must be dotted names, e.g. sac.batch_size",
        ));
    }
    let value = parse_yaml(value).map_err(|message| ConfigError::Yaml {
        origin: origin.clone(),
        message,
    })?;
    let mut tree = Value::Object(Map::new());
    set(&mut tree, key, value);
    let cwd = std::env::current_dir().map_err(|e| ConfigError::Malformed {
        origin: origin.clone(),
        message: format!("cannot read the working directory: {e}"),
    })?;
    prepare(tree, origin, &cwd, schema)
}

/// Checks one layer on its own: aliases, unknown keys, types; and rebases a relative dataset path
/// on `dir`, an absolute directory (canonical for files, so folding `..` lexically is exact up to
/// it).
fn prepare(
    mut tree: Value,
    origin: Source,
    dir: &Path,
    schema: &Value,
) -> Result<Layer, ConfigError> {
    apply_aliases(&mut tree, &origin)?;
    check_keys(&tree, schema, &origin)?;
    if let Some(Value::String(dataset)) = get(&tree, DATASET_PATH) {
        if !dataset.is_empty() && Path::new(dataset).is_relative() {
            let absolute = normalize(&dir.join(dataset));
            let absolute = absolute.to_str().ok_or_else(|| ConfigError::Invalid {
                origin: Some(origin.clone()),
                key: DATASET_PATH.into(),
                message: format!("{} is not valid UTF-8", absolute.display()),
            })?;
            set(&mut tree, DATASET_PATH, Value::String(absolute.to_owned()));
        }
    }
    deserialize(&tree, &origin)?;
    Ok(Layer { origin, tree })
}

/// Deserializes a (possibly partial) tree into a [`RunConfig`]; a type error names the key, what
/// was expected and what the tree holds there.
fn deserialize(tree: &Value, origin: &Source) -> Result<RunConfig, ConfigError> {
    serde_path_to_error::deserialize(tree).map_err(|error| {
        let got = error
            .path()
            .iter()
            .try_fold(tree, |node, segment| match segment {
                serde_path_to_error::Segment::Map { key } => node.get(key),
                serde_path_to_error::Segment::Seq { index } => node.get(index),
                _ => None,
            })
            .cloned()
            .unwrap_or(Value::Null);
        type_error(
            error.path().to_string(),
            error.inner().to_string(),
            &got,
            origin,
        )
    })
}

/// Turns serde's message into ours: `expected an unsigned integer, got "abc"`, or for an enum
/// `unknown value "foo", expected one of: a, b (did you mean 'a'?)`.
fn type_error(key: String, message: String, got: &Value, origin: &Source) -> ConfigError {
    if message.starts_with("unknown variant") {
        // "unknown variant `x`, expected one of `a`, `b`": the quoted words after the first.
        let variants: Vec<&str> = message.split('`').skip(3).step_by(2).collect();
        let hint = DidYouMean(
            got.as_str()
                .and_then(|word| closest(word, variants.iter().copied())),
        );
        return ConfigError::Invalid {
            origin: Some(origin.clone()),
            key,
            message: format!(
                "unknown value {got}, expected one of: {}{hint}",
                variants.join(", ")
            ),
        };
    }
    match message.rsplit_once(", expected ") {
        Some((_, expected)) => ConfigError::WrongType {
            origin: origin.clone(),
            key,
            expected: describe(expected, got),
            got: got.to_string(),
        },
        None => ConfigError::Invalid {
            origin: Some(origin.clone()),
            key,
            message,
        },
    }
}

/// serde's name of an expected type in words a config author uses.
fn describe(expected: &str, got: &Value) -> String {
    let unsigned = |max: u64| match got.is_i64() || got.is_u64() {
        true => format!("an unsigned integer in [0, {max}]"),
        false => "an unsigned integer".to_owned(),
    };
    match expected {
        "u8" => unsigned(u8::MAX.into()),
        "u16" => unsigned(u16::MAX.into()),
        "u32" => unsigned(u32::MAX.into()),
        "u64" | "usize" => unsigned(u64::MAX),
        "i8" | "i16" | "i32" | "i64" | "isize" => "an integer".to_owned(),
        "f32" | "f64" => "a number".to_owned(),
        "a sequence" => "a list".to_owned(),
        // What serde's enums expect; the variant list follows once a string is given.
        "string or map" => "a string".to_owned(),
        "a map" => "a mapping".to_owned(),
        other if other.starts_with("struct ") => "a mapping".to_owned(),
        other => other.to_owned(),
    }
}

/// Removes `.` and folds `..` into the preceding name, without touching the file system.
fn normalize(path: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for component in path.components() {
        match (component, out.components().next_back()) {
            (Component::CurDir, _) => {}
            (Component::ParentDir, Some(Component::Normal(_))) => {
                out.pop();
            }
            (Component::ParentDir, Some(Component::RootDir)) => {}
            (other, _) => out.push(other),
        }
    }
    if out.as_os_str().is_empty() {
        out.push(".");
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn normalize_folds_dots_lexically() {
        assert_eq!(
            normalize(Path::new("configs/a/../base/./x.yml")),
            Path::new("configs/base/x.yml")
        );
        assert_eq!(normalize(Path::new("../x/../y")), Path::new("../y"));
        assert_eq!(normalize(Path::new("/a/../../b")), Path::new("/b"));
        assert_eq!(normalize(Path::new("a/..")), Path::new("."));
    }

    #[test]
    fn serde_type_names_read_as_words() {
        assert_eq!(describe("u32", &json!("abc")), "an unsigned integer");
        assert_eq!(
            describe("u16", &json!(70000)),
            "an unsigned integer in [0, 65535]"
        );
        assert_eq!(describe("f64", &json!(true)), "a number");
        assert_eq!(describe("struct SacConfig", &json!(null)), "a mapping");
        assert_eq!(describe("a boolean", &json!(1)), "a boolean");
    }

    #[test]
    fn unknown_enum_values_list_the_variants_and_suggest_one() {
        let origin = Source::Override("x".into());
        let message = "unknown variant `asynch`, expected `sync` or `async`".to_owned();
        let error = type_error("sac.utd_mode".into(), message, &json!("asynch"), &origin);
        assert_eq!(
            error.to_string(),
            "command-line override 'x': sac.utd_mode: unknown value \"asynch\", expected one of: \
             sync, async (did you mean 'async'?)"
        );
    }
}

/// What a parsed YAML document is, in words ("a string", "a list", ...).
fn json_kind(value: &Value) -> &'static str {
    match value {
        Value::Null => "nothing",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "a list",
        Value::Object(_) => "a mapping",
    }
}
