//! This package's tests link libtorch (the actor MLP): they get an rpath to libtorch's lib dir.
include!("../build/libtorch_rpath.rs");

fn main() {
    libtorch_rpath("rfcl-policy");
}
