//! The rfcl wire protocol, package `rfcl.v1`, generated from `proto/rfcl.proto` at build time
//! (protox, so no system protoc is needed).
//!
//! Wire types stay at the edges: [`convert`] is the one place where they become rfcl-core's domain
//! types and back, rejecting malformed messages with an error that names the field.
#![forbid(unsafe_code)]

pub mod auth;
pub mod convert;
pub mod health;
pub mod link;

pub mod v1 {
    tonic::include_proto!("rfcl.v1");
}
pub use v1::*;
