//! Compiles proto/rfcl.proto with protox (pure Rust), so no system protoc is needed.
fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=proto/rfcl.proto");
    let fds = protox::compile(["rfcl.proto"], ["proto"])?;
    tonic_prost_build::configure()
        // Policy weights as `bytes::Bytes`: the learner hands one immutable buffer to every
        // WatchPolicy subscriber, and cloning a message only bumps a reference count (a `Vec<u8>`
        // would copy the whole network per subscriber and per version).
        .bytes(".rfcl.v1.PolicyWeights.safetensors")
        .compile_fds(fds)?;
    Ok(())
}
