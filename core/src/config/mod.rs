//! Run configuration: schema, resolution and validation.
//!
//! * [`RunConfig`] and its sections: every option of the spec; `Default` is the reference
//!   behaviour.
//! * [`resolve_file`]: a YAML file with its `base_config` chain and dotted command-line
//!   overrides, checked key by key and validated.
//! * [`RunConfig::validate`]: ranges and rules between options.
//! * [`to_yaml`]: a resolved config back to YAML (what a run directory keeps).
//!
//! `docs/CONFIG.md` is the user's reference of every key and of these rules.
mod error;
mod keys;
mod resolve;
mod schema;
mod tree;
mod validate;

pub use error::{ConfigError, DidYouMean, Source};
pub use resolve::{resolve_file, to_yaml};
pub use schema::*;
