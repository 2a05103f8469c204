//! The `rfcl` binary links libtorch (`rfcl eval` runs the policy network, through rfcl-actor and
//! rfcl-learner): it and this package's tests get an rpath to libtorch's lib dir.
include!("build/libtorch_rpath.rs");

fn main() {
    libtorch_rpath("rfcl");
}
