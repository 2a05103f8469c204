//! Fuzz body of `shm_frame`: the shared-memory frame decoders (`rfcl_shm::frame`) on arbitrary
//! bytes, as a subscriber receives a sample. Shared by `fuzz/fuzz_targets/shm_frame.rs` and
//! `shm/tests/fuzz_regressions.rs` (included by `#[path]`).
//!
//! Properties: no panic; a frame is refused with a `FrameError` or decoded, and a decoded frame
//! re-encodes to the same header bytes and keeps exactly the bytes after the header.
use rfcl_shm::frame::{
    PolicyHeader, TransitionHeader, POLICY_HEADER_BYTES, TRANSITION_HEADER_BYTES,
};

/// Decodes `data` as a transition frame and as a policy frame; returns the rejection messages
/// (empty when both decoded).
pub fn run(data: &[u8]) -> Vec<String> {
    let mut rejections = Vec::new();
    match TransitionHeader::decode(data) {
        Ok((header, records)) => {
            assert_eq!(records, &data[TRANSITION_HEADER_BYTES..]);
            let mut again = [0u8; TRANSITION_HEADER_BYTES];
            header.encode(&mut again);
            assert_eq!(again[..], data[..TRANSITION_HEADER_BYTES]);
        }
        Err(e) => rejections.push(e.to_string()),
    }
    match PolicyHeader::decode(data) {
        Ok((header, weights)) => {
            assert_eq!(weights, &data[POLICY_HEADER_BYTES..]);
            let mut again = [0u8; POLICY_HEADER_BYTES];
            header.encode(&mut again);
            assert_eq!(again[..], data[..POLICY_HEADER_BYTES]);
        }
        Err(e) => rejections.push(e.to_string()),
    }
    rejections
}
