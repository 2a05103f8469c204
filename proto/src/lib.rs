//! The rfcl wire protocol, package `rfcl.v1`, generated from `proto/rfcl.proto` at build time.
//!
//! Wire types stay at the edges: services convert them into rfcl-core's domain types once, in
//! `rfcl_core::wire`-free code paths (see each service's `convert` module).
#![forbid(unsafe_code)]

pub mod v1 {
    tonic::include_proto!("rfcl.v1");
}
pub use v1::*;
