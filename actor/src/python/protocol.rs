//! The frames between a [`super::PythonEnv`] and its `rfcl-sim-worker` process (and, in process,
//! between Rust and `rfcl_sim.bridge.Bridge.handle`, which decodes the payloads on the Python side).
//!
//! A frame is `u8 tag, u32 len, len payload bytes`, little-endian. A request's tag is an op, a
//! response's a status. Vectors are packed little-endian `f32`s: no JSON on the step path.
//!
//! | op | request payload | OK response payload |
//! |---|---|---|
//! | [`OP_HELLO`] | empty | the adapter's description, JSON ([`Hello`]) |
//! | [`OP_RESET`] | `u8 has_seed, u64 seed, u32 n, n bytes options JSON, f32 state…` (no state: reset only) | obs |
//! | [`OP_STEP`] | `f32 action…` | `u8 success, f32 obs…` |
//! | [`OP_GET_STATE`] | empty | state |
//! | [`OP_RENDER`] | empty | `u32 width, u32 height`, then `height × width × 3` bytes of RGB, top row first |
//!
//! Statuses: [`STATUS_OK`], [`STATUS_BAD_INPUT`] (the adapter's message: bad input, the worker is
//! fine), [`STATUS_EXCEPTION`] (a Python traceback). The worker writes one unsolicited response
//! when it starts: its hello, or the traceback of the failure to make the adapter.
use std::io::{self, Read, Write};

pub const OP_HELLO: u8 = 0;
pub const OP_RESET: u8 = 1;
pub const OP_STEP: u8 = 2;
pub const OP_GET_STATE: u8 = 3;
pub const OP_RENDER: u8 = 4;

pub const STATUS_OK: u8 = 0;
pub const STATUS_BAD_INPUT: u8 = 1;
pub const STATUS_EXCEPTION: u8 = 2;

/// Larger frames are refused as corrupt (a state or observation is at most a few thousand floats).
pub const MAX_FRAME: u32 = 64 << 20;

/// One frame: a tag (op or status) and its payload.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Frame {
    pub tag: u8,
    pub payload: Vec<u8>,
}

/// Writes one frame and flushes.
pub fn write_frame(w: &mut impl Write, tag: u8, payload: &[u8]) -> io::Result<()> {
    let len = u32::try_from(payload.len())
        .ok()
        .filter(|&n| n <= MAX_FRAME)
        .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "frame too large"))?;
    let mut head = [0u8; 5];
    head[0] = tag;
    head[1..].copy_from_slice(&len.to_le_bytes());
    w.write_all(&head)?;
    w.write_all(payload)?;
    w.flush()
}

/// Reads one frame; `Ok(None)` at a clean end of stream (before a frame's first byte).
pub fn read_frame(r: &mut impl Read) -> io::Result<Option<Frame>> {
    let mut head = [0u8; 5];
    let mut got = 0;
    while got < head.len() {
        match r.read(&mut head[got..]) {
            Ok(0) if got == 0 => return Ok(None),
            Ok(0) => return Err(io::ErrorKind::UnexpectedEof.into()),
            Ok(n) => got += n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    let len = u32::from_le_bytes([head[1], head[2], head[3], head[4]]);
    if len > MAX_FRAME {
        return Err(io::Error::new(
            io::ErrorKind::InvalidData,
            format!("frame of {len} bytes exceeds {MAX_FRAME}: the stream is corrupt"),
        ));
    }
    let mut payload = vec![0u8; len as usize];
    r.read_exact(&mut payload)?;
    Ok(Some(Frame {
        tag: head[0],
        payload,
    }))
}

/// Appends `v` as little-endian `f32`s.
pub fn put_f32s(out: &mut Vec<u8>, v: &[f32]) {
    out.reserve(v.len() * 4);
    for x in v {
        out.extend_from_slice(&x.to_le_bytes());
    }
}

/// Little-endian `f32`s; `None` when the length is not a multiple of 4.
pub fn get_f32s(bytes: &[u8]) -> Option<Vec<f32>> {
    if !bytes.len().is_multiple_of(4) {
        return None;
    }
    Some(
        bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect(),
    )
}

/// The payload of an [`OP_RESET`]: reset with `seed` and `options`, then set `state` if not empty.
pub fn reset_request(seed: Option<u64>, options_json: &str, state: &[f32]) -> Vec<u8> {
    let mut p = Vec::with_capacity(13 + options_json.len() + 4 * state.len());
    p.push(u8::from(seed.is_some()));
    p.extend_from_slice(&seed.unwrap_or(0).to_le_bytes());
    p.extend_from_slice(&(options_json.len() as u32).to_le_bytes());
    p.extend_from_slice(options_json.as_bytes());
    put_f32s(&mut p, state);
    p
}

/// The image of an [`OP_RENDER`] answer.
pub fn render_answer(bytes: &[u8]) -> Result<crate::video::Frame, String> {
    let (head, rgb) = bytes
        .split_at_checked(8)
        .ok_or_else(|| format!("{} bytes, shorter than the 8-byte size header", bytes.len()))?;
    let width = u32::from_le_bytes([head[0], head[1], head[2], head[3]]);
    let height = u32::from_le_bytes([head[4], head[5], head[6], head[7]]);
    crate::video::Frame::new(width, height, rgb.to_vec()).map_err(|e| e.to_string())
}

/// The adapter's description (the [`OP_HELLO`] answer).
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
pub struct Hello {
    pub suite: String,
    pub env_id: String,
    pub obs_dim: usize,
    pub action_dim: usize,
    pub horizon: usize,
    /// `[name, kind, len]` triples, kinds as in `rfcl_core::demo::StateKind` (snake case).
    pub state_layout: Vec<(String, String, usize)>,
    /// The worker's Python version.
    #[serde(default)]
    pub python: String,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_round_trip_and_corrupt_lengths_are_refused() {
        let mut buf = Vec::new();
        write_frame(&mut buf, OP_STEP, &[1, 2, 3]).unwrap();
        write_frame(&mut buf, STATUS_OK, &[]).unwrap();
        let mut r = &buf[..];
        assert_eq!(read_frame(&mut r).unwrap().unwrap().payload, vec![1, 2, 3]);
        assert_eq!(read_frame(&mut r).unwrap().unwrap().tag, STATUS_OK);
        assert!(read_frame(&mut r).unwrap().is_none());
        // A frame cut short is an error, not a clean end.
        let mut r = &buf[..4];
        assert!(read_frame(&mut r).is_err());
        let huge = [0u8, 0xff, 0xff, 0xff, 0xff];
        assert!(read_frame(&mut &huge[..]).is_err());
    }

    #[test]
    fn reset_requests_and_vectors_are_packed() {
        let p = reset_request(Some(7), "{}", &[1.5]);
        assert_eq!(p[0], 1);
        assert_eq!(u64::from_le_bytes(p[1..9].try_into().unwrap()), 7);
        assert_eq!(u32::from_le_bytes(p[9..13].try_into().unwrap()), 2);
        assert_eq!(&p[13..15], b"{}");
        assert_eq!(get_f32s(&p[15..]).unwrap(), vec![1.5]);
        assert!(get_f32s(&[0, 0, 0]).is_none());
    }

    #[test]
    fn render_answers_are_sized_by_their_header() {
        let mut p = Vec::new();
        p.extend_from_slice(&2u32.to_le_bytes());
        p.extend_from_slice(&1u32.to_le_bytes());
        p.extend_from_slice(&[1, 2, 3, 4, 5, 6]);
        let f = render_answer(&p).unwrap();
        assert_eq!((f.width, f.height, f.rgb), (2, 1, vec![1, 2, 3, 4, 5, 6]));
        let err = render_answer(&p[..13]).unwrap_err();
        assert!(err.contains("has 5 bytes of RGB, not 6"), "{err}");
        assert!(render_answer(&p[..5]).unwrap_err().contains("header"));
    }
}
