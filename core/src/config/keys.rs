//! Key checks against the schema: unknown keys (with a "did you mean") and the reference's option
//! names, some accepted as aliases, some only suggested.
use serde_json::{Map, Value};

use super::error::{ConfigError, DidYouMean, Source};
use super::tree::{get, join, set, take};
use super::RunConfig;

/// The reference's names accepted here as aliases of ours: `(alias, key)`. `sac.num_qs` is the
/// reference's name of the target pool (spec 5.1, deviation 2).
pub(super) const ALIASES: &[(&str, &str)] = &[("sac.num_qs", "sac.target_pool")];

/// Names used by the reference or its docs for options that are spelled differently here: `(their
/// last key segment, our dotted key)`. Used for suggestions only.
pub(super) const RENAMED: &[(&str, &str)] = &[
    ("num_eval_envs", "eval_env.num_envs"),
    ("eval_use_orig_env", "train.use_orig_env_for_eval"),
    ("save_eval_video", "eval_env.video_every"),
];

/// Similarity (normalised Damerau-Levenshtein) a key needs to be suggested for a typo.
const SUGGEST_THRESHOLD: f64 = 0.7;

/// The schema as a tree: [`RunConfig::default`] serialized. Its keys are exactly the keys a file
/// may set.
pub(super) fn schema() -> Value {
    serde_json::to_value(RunConfig::default()).expect("the default config serializes to a tree")
}

/// Every dotted key of the schema (sections and leaves), in schema order.
pub(super) fn all_keys() -> Vec<String> {
    fn walk(map: &Map<String, Value>, prefix: &str, out: &mut Vec<String>) {
        for (key, value) in map {
            let dotted = join(prefix, key);
            out.push(dotted.clone());
            if let Value::Object(inner) = value {
                walk(inner, &dotted, out);
            }
        }
    }
    let mut out = Vec::new();
    if let Value::Object(map) = schema() {
        walk(&map, "", &mut out);
    }
    out
}

/// Rewrites the aliases of [`ALIASES`] in a file's or override's tree to our keys.
pub(super) fn apply_aliases(tree: &mut Value, origin: &Source) -> Result<(), ConfigError> {
    for (alias, key) in ALIASES {
        if let Some(value) = take(tree, alias) {
            if get(tree, key).is_some() {
                return Err(ConfigError::Malformed {
                    origin: origin.clone(),
                    message: format!("'{alias}' is the reference's name of '{key}': set only one"),
                });
            }
            set(tree, key, value);
        }
    }
    Ok(())
}

/// Fails on the first key of `tree` that `schema` does not have. A mapping whose default is empty
/// (`env.env_kwargs`) is free-form: its keys are not checked.
pub(super) fn check_keys(tree: &Value, schema: &Value, origin: &Source) -> Result<(), ConfigError> {
    fn walk(
        user: &Map<String, Value>,
        known: &Map<String, Value>,
        prefix: &str,
        origin: &Source,
    ) -> Result<(), ConfigError> {
        for (key, value) in user {
            let dotted = join(prefix, key);
            match (known.get(key), value) {
                (None, _) => {
                    return Err(ConfigError::UnknownKey {
                        origin: origin.clone(),
                        hint: DidYouMean(suggest(&dotted)),
                        key: dotted,
                    })
                }
                (Some(Value::Object(known)), Value::Object(user)) if !known.is_empty() => {
                    walk(user, known, &dotted, origin)?
                }
                // A leaf, a free-form mapping, or a type mismatch that deserialization reports.
                _ => {}
            }
        }
        Ok(())
    }
    match (tree, schema) {
        (Value::Object(user), Value::Object(known)) => walk(user, known, "", origin),
        _ => Ok(()),
    }
}

/// The key a user most likely meant by the unknown `key`: the reference's name for it
/// ([`RENAMED`]), a key with the same last segment in another section (`batch_size` ->
/// `sac.batch_size`), or the closest key by spelling.
pub(super) fn suggest(key: &str) -> Option<String> {
    let last = last_segment(key);
    if let Some((_, ours)) = RENAMED.iter().find(|(theirs, _)| *theirs == last) {
        return Some((*ours).to_owned());
    }
    let candidates = all_keys()
        .into_iter()
        .chain(ALIASES.iter().map(|(alias, _)| (*alias).to_owned()));
    candidates
        .map(|candidate| {
            let similarity = strsim::normalized_damerau_levenshtein(key, &candidate);
            let moved = last_segment(&candidate) == last;
            (if moved { 1.0 + similarity } else { similarity }, candidate)
        })
        .filter(|(score, _)| *score >= SUGGEST_THRESHOLD)
        .max_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, candidate)| candidate)
}

/// The best spelling match among `names` (enum variants), if any is close enough.
pub(super) fn closest<'a>(word: &str, names: impl IntoIterator<Item = &'a str>) -> Option<String> {
    names
        .into_iter()
        .map(|name| (strsim::normalized_damerau_levenshtein(word, name), name))
        .filter(|(score, _)| *score >= 0.5)
        .max_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, name)| name.to_owned())
}

fn last_segment(key: &str) -> &str {
    key.rsplit('.').next().unwrap_or(key)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn suggestions_cover_typos_moved_keys_and_reference_names() {
        assert_eq!(suggest("sac.batch_sise").as_deref(), Some("sac.batch_size"));
        assert_eq!(suggest("batch_size").as_deref(), Some("sac.batch_size"));
        assert_eq!(suggest("train.discount").as_deref(), Some("sac.discount"));
        assert_eq!(suggest("num_envs").as_deref(), Some("env.num_envs"));
        assert_eq!(suggest("sac.num_q").as_deref(), Some("sac.num_qs"));
        assert_eq!(
            suggest("train.eval_use_orig_env").as_deref(),
            Some("train.use_orig_env_for_eval")
        );
        assert_eq!(
            suggest("num_eval_envs").as_deref(),
            Some("eval_env.num_envs")
        );
        assert_eq!(suggest("completely.unrelated"), None);
    }

    #[test]
    fn all_keys_has_sections_and_leaves() {
        let keys = all_keys();
        assert!(keys.contains(&"sac".to_owned()));
        assert!(keys.contains(&"sac.target_pool".to_owned()));
        assert!(keys.contains(&"env.env_kwargs".to_owned()));
    }

    #[test]
    fn closest_picks_a_near_variant() {
        let variants = ["rankmin", "rank", "constant"];
        assert_eq!(closest("rank_min", variants).as_deref(), Some("rankmin"));
        assert_eq!(closest("zzzzzzzz", variants), None);
    }
}
