//! Run configuration: schema, resolution and validation.
mod schema;
pub use schema::*;
