//! The one error type of config resolution and validation. Every message is a single line that
//! names where the offending value came from and the dotted key, so a user knows what to edit.
use std::fmt;
use std::path::PathBuf;

/// Where a config value came from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Source {
    /// A YAML file, spelled as the user or the including file's `base_config` gave it.
    File(PathBuf),
    /// A `key=value` command-line override, as typed.
    Override(String),
}

impl fmt::Display for Source {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Source::File(path) => write!(f, "{}", path.display()),
            Source::Override(arg) => write!(f, "command-line override '{arg}'"),
        }
    }
}

/// An optional "did you mean" hint, printed as ` (did you mean 'x'?)` or not at all.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct DidYouMean(pub Option<String>);

impl fmt::Display for DidYouMean {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.0 {
            Some(guess) => write!(f, " (did you mean '{guess}'?)"),
            None => Ok(()),
        }
    }
}

/// Why a config could not be resolved or is not valid. `Display` is one line.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// A config file could not be read.
    #[error("{}: cannot read: {error}", path.display())]
    Read {
        path: PathBuf,
        error: std::io::Error,
    },
    /// A file or an override value is not valid YAML.
    #[error("{origin}: invalid YAML: {message}")]
    Yaml { origin: Source, message: String },
    /// A `base_config` names a file that does not exist.
    #[error("{}: base_config '{base}' not found (looked for {})", file.display(), resolved.display())]
    MissingBase {
        file: PathBuf,
        base: String,
        resolved: PathBuf,
    },
    /// `base_config` chains loop back to a file already being loaded.
    #[error("base_config cycle: {}", chain.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(" -> "))]
    Cycle { chain: Vec<PathBuf> },
    /// A file or override is shaped wrongly (not a mapping, `key=value` missing, ...).
    #[error("{origin}: {message}")]
    Malformed { origin: Source, message: String },
    /// A key the schema does not have.
    #[error("{origin}: unknown key '{key}'{hint}")]
    UnknownKey {
        origin: Source,
        key: String,
        hint: DidYouMean,
    },
    /// A value of the wrong type.
    #[error("{origin}: {key}: expected {expected}, got {got}")]
    WrongType {
        origin: Source,
        key: String,
        expected: String,
        got: String,
    },
    /// A value out of its allowed range or in conflict with another option. `origin` is `None`
    /// when [`RunConfig::validate`](super::RunConfig::validate) runs on a config built in code, or
    /// when the value is a default.
    #[error("{}{key}: {message}", OriginPrefix(origin))]
    Invalid {
        origin: Option<Source>,
        key: String,
        message: String,
    },
}

impl ConfigError {
    /// The dotted key the error is about, where there is one.
    pub fn key(&self) -> Option<&str> {
        match self {
            ConfigError::UnknownKey { key, .. }
            | ConfigError::WrongType { key, .. }
            | ConfigError::Invalid { key, .. } => Some(key),
            _ => None,
        }
    }
}

/// Prints `origin: ` or nothing.
struct OriginPrefix<'a>(&'a Option<Source>);

impl fmt::Display for OriginPrefix<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.0 {
            Some(origin) => write!(f, "{origin}: "),
            None => Ok(()),
        }
    }
}
