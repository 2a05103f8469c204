//! `docs/CONFIG.md` documents every key of the schema exactly once, with its real default.
use std::collections::BTreeMap;
use std::path::Path;

use rfcl_core::config::RunConfig;
use serde_json::Value;

/// The schema's leaf keys with their defaults.
fn defaults() -> BTreeMap<String, Value> {
    fn walk(value: &Value, prefix: &str, out: &mut BTreeMap<String, Value>) {
        match value {
            Value::Object(map) if !map.is_empty() => {
                for (key, value) in map {
                    let dotted = if prefix.is_empty() {
                        key.clone()
                    } else {
                        format!("{prefix}.{key}")
                    };
                    walk(value, &dotted, out);
                }
            }
            _ => {
                out.insert(prefix.to_owned(), value.clone());
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(
        &serde_json::to_value(RunConfig::default()).unwrap(),
        "",
        &mut out,
    );
    out
}

/// The rows of the tables under "## Keys": `| `key` | `default` | ...` as (key, default parsed as
/// YAML).
fn documented() -> Vec<(String, Value)> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/CONFIG.md");
    let text = std::fs::read_to_string(path).unwrap();
    let (_, keys) = text.split_once("\n## Keys\n").expect("a '## Keys' section");
    let keys = keys.split("\n## ").next().unwrap();
    keys.lines()
        .filter_map(|line| {
            let cells: Vec<&str> = line.split('|').map(str::trim).collect();
            let key = cells.get(1)?.strip_prefix('`')?.strip_suffix('`')?;
            let default = cells.get(2)?.strip_prefix('`')?.strip_suffix('`')?;
            let value: Value = serde_saphyr::from_str(default)
                .unwrap_or_else(|e| panic!("default of {key} is not YAML: {e}"));
            Some((key.to_owned(), value))
        })
        .collect()
}

/// Equal as config values: numbers compare numerically (`1.0` documents the float 1).
fn same(a: &Value, b: &Value) -> bool {
    match (a, b) {
        (Value::Number(a), Value::Number(b)) => a.as_f64() == b.as_f64(),
        (Value::Array(a), Value::Array(b)) => {
            a.len() == b.len() && a.iter().zip(b).all(|(a, b)| same(a, b))
        }
        _ => a == b,
    }
}

#[test]
fn every_key_is_documented_once_with_its_default() {
    let defaults = defaults();
    let rows = documented();
    let mut seen = BTreeMap::new();
    for (key, documented) in &rows {
        if seen.insert(key.clone(), ()).is_some() {
            panic!("{key} is documented twice");
        }
        let default = defaults
            .get(key)
            .unwrap_or_else(|| panic!("{key} is documented but not in the schema"));
        assert!(
            same(default, documented),
            "{key}: documented {documented}, default {default}"
        );
    }
    let missing: Vec<&String> = defaults
        .keys()
        .filter(|key| !seen.contains_key(*key))
        .collect();
    assert!(missing.is_empty(), "undocumented keys: {missing:?}");
}
