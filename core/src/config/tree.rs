//! The generic YAML tree (a `serde_json::Value`) that config files are parsed into before they
//! become a [`RunConfig`](super::RunConfig): parsing, deep merge and dotted paths.
use serde_json::{Map, Value};

/// Parses YAML text (a whole file or one override value) into a tree. An empty document is
/// `null`. The error is the parser's one-line message with its line and column.
pub(super) fn parse_yaml(text: &str) -> Result<Value, String> {
    let mut options = serde_saphyr::Options::default();
    options.with_snippet = false;
    serde_saphyr::from_str_with_options(text, options).map_err(|e| {
        // The parser's advice on its own options means nothing to a config author.
        let message = e.to_string().replace('\n', " ");
        message.replace(", set DuplicateKeyPolicy in Options if acceptable", "")
    })
}

/// Deep merge: mapping keys of `over` override those of `base` recursively; anything else
/// (scalars, sequences, `null`) replaces the base value whole.
pub(super) fn merge(base: &mut Value, over: Value) {
    match (base, over) {
        (Value::Object(base), Value::Object(over)) => {
            for (key, value) in over {
                match base.get_mut(&key) {
                    Some(slot) => merge(slot, value),
                    None => {
                        base.insert(key, value);
                    }
                }
            }
        }
        (base, over) => *base = over,
    }
}

/// The dotted paths of the leaves of `tree`: every value that is not a non-empty mapping.
pub(super) fn leaves(tree: &Value) -> Vec<String> {
    fn walk(tree: &Value, prefix: &str, out: &mut Vec<String>) {
        match tree {
            Value::Object(map) if !map.is_empty() => {
                for (key, value) in map {
                    walk(value, &join(prefix, key), out);
                }
            }
            _ => out.push(prefix.to_owned()),
        }
    }
    let mut out = Vec::new();
    walk(tree, "", &mut out);
    out
}

/// The value at a dotted path.
pub(super) fn get<'a>(tree: &'a Value, dotted: &str) -> Option<&'a Value> {
    dotted.split('.').try_fold(tree, |node, key| node.get(key))
}

/// Removes and returns the value at a dotted path.
pub(super) fn take(tree: &mut Value, dotted: &str) -> Option<Value> {
    let (parent, key) = match dotted.rsplit_once('.') {
        Some((parent, key)) => (get_mut(tree, parent)?, key),
        None => (tree, dotted),
    };
    parent.as_object_mut()?.remove(key)
}

/// Sets the value at a dotted path, creating the mappings on the way.
pub(super) fn set(tree: &mut Value, dotted: &str, value: Value) {
    let mut over = value;
    for key in dotted.rsplit('.') {
        over = Value::Object(Map::from_iter([(key.to_owned(), over)]));
    }
    merge(tree, over);
}

fn get_mut<'a>(tree: &'a mut Value, dotted: &str) -> Option<&'a mut Value> {
    dotted
        .split('.')
        .try_fold(tree, |node, key| node.get_mut(key))
}

/// `prefix.key`, or `key` at the top.
pub(super) fn join(prefix: &str, key: &str) -> String {
    if prefix.is_empty() {
        key.to_owned()
    } else {
        format!("{prefix}.{key}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn merge_overrides_mapping_keys_and_replaces_everything_else() {
        let mut base = json!({"a": {"x": 1, "y": [1, 2]}, "b": 2, "c": {"z": 1}});
        merge(
            &mut base,
            json!({"a": {"y": [3], "w": 4}, "b": {"k": 1}, "c": null}),
        );
        assert_eq!(
            base,
            json!({"a": {"x": 1, "y": [3], "w": 4}, "b": {"k": 1}, "c": null})
        );
    }

    #[test]
    fn leaves_are_dotted_and_include_empty_mappings() {
        let tree = json!({"a": {"x": 1, "y": {}}, "b": [1]});
        assert_eq!(leaves(&tree), ["a.x", "a.y", "b"]);
    }

    #[test]
    fn set_take_and_get_use_dotted_paths() {
        let mut tree = json!({"a": {"x": 1}});
        set(&mut tree, "a.b.c", json!(2));
        assert_eq!(get(&tree, "a.b.c"), Some(&json!(2)));
        assert_eq!(take(&mut tree, "a.x"), Some(json!(1)));
        assert_eq!(take(&mut tree, "a.nope"), None);
        assert_eq!(tree, json!({"a": {"b": {"c": 2}}}));
    }

    #[test]
    fn yaml_errors_are_one_line_with_a_position() {
        let message = parse_yaml("a: [1,\n").unwrap_err();
        assert!(!message.contains('\n'));
        assert!(message.contains("line 1"), "{message}");
        assert_eq!(parse_yaml("").unwrap(), Value::Null);
        assert_eq!(parse_yaml("[64, 64]").unwrap(), json!([64, 64]));
    }
}
