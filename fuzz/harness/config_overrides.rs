//! Fuzz body of `config_overrides`: the run-config resolver (`rfcl_core::config::resolve_file`,
//! what `rfcl train CONFIG --set KEY=VALUE ...` runs) on arbitrary text. Shared by
//! `fuzz/fuzz_targets/config_overrides.rs` and `core/tests/fuzz_regressions.rs` (included by
//! `#[path]`).
//!
//! The input (lossy UTF-8) is split at the first line that is exactly `%%`: before it, the YAML
//! file; after it, one dotted `key=value` override per line. The YAML is written to `run.yml` in
//! a fresh temporary directory (a relative `base_config` resolves there).
//!
//! Properties: no panic; a refusal is a `ConfigError` whose message names its origin (the file
//! or the override) or the key; an accepted config validates and survives `to_yaml` and back.
use rfcl_core::config::{resolve_file, to_yaml, ConfigError};

/// The separator line between the YAML file and the overrides.
pub const SEPARATOR: &str = "%%";

/// Resolves the input; returns the refusal's message, if any.
pub fn run(data: &[u8]) -> Vec<String> {
    let text = String::from_utf8_lossy(data);
    let (yaml, overrides) = split(&text);
    let dir = tempfile::tempdir().expect("a temporary directory");
    let path = dir.path().join("run.yml");
    std::fs::write(&path, yaml).expect("writing the config");
    match resolve_file(&path, &overrides) {
        Ok(config) => {
            config.validate().expect("a resolved config is valid");
            // The resolved config, written back as a run directory keeps it, resolves the same.
            let again = dir.path().join("resolved.yml");
            std::fs::write(&again, to_yaml(&config)).expect("writing the resolved config");
            let back = resolve_file(&again, &[])
                .unwrap_or_else(|e| panic!("the resolved config does not resolve again: {e}"));
            assert_eq!(to_yaml(&back), to_yaml(&config));
            Vec::new()
        }
        Err(e) => vec![describe(&e)],
    }
}

/// The YAML part and the override lines of an input.
pub fn split(text: &str) -> (&str, Vec<String>) {
    let mut offset = 0;
    for line in text.split_inclusive('\n') {
        if line.trim_end_matches(['\n', '\r']) == SEPARATOR {
            let overrides = text[offset + line.len()..]
                .lines()
                .map(str::to_owned)
                .collect();
            return (&text[..offset], overrides);
        }
        offset += line.len();
    }
    (text, Vec::new())
}

/// The error's one-line message.
fn describe(e: &ConfigError) -> String {
    e.to_string()
}
