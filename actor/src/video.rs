//! Eval episodes as videos: frames from an env's own renderer ([`crate::env::Env::render`]),
//! one every [`STEPS_PER_FRAME`] steps and the last, encoded as an animated GIF, which every
//! browser plays and which needs no encoder on the machine.
//!
//! Pure: frames in, bytes out. `rfcl eval --video` writes the bytes to files; the eval actor sends
//! them to the curriculum server, which serves them from the dashboard.

/// One env step drawn every this many (a 300-step episode is 101 frames).
pub const STEPS_PER_FRAME: u32 = 3;
/// Display time of one frame, in GIF units of 1/100 s.
pub const FRAME_DELAY_CS: u16 = 4;
/// The most frames one video holds: longer episodes keep their first frames and their last.
pub const MAX_FRAMES: usize = 400;
/// The largest frame side an env may render, in pixels.
pub const MAX_SIDE: u32 = 1024;
/// NeuQuant's speed (1-30) for frames with more than 256 colours: 10 is the crate's suggested
/// balance of speed and quality.
const QUANTIZER_SPEED: i32 = 10;

/// An RGB image: `height` rows of `width` pixels from the top-left, 3 bytes each.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<u8>,
}

/// Why frames could not become a video.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum VideoError {
    #[error("a frame of {width}x{height} pixels has {got} bytes of RGB, not {expected}")]
    FrameBytes {
        width: u32,
        height: u32,
        expected: usize,
        got: usize,
    },
    #[error("a frame of {width}x{height} pixels is empty or over {MAX_SIDE} pixels a side")]
    FrameSize { width: u32, height: u32 },
    #[error("frame {index} is {got:?} pixels, the video's first frame {expected:?}")]
    SizeChanged {
        index: usize,
        expected: (u32, u32),
        got: (u32, u32),
    },
    #[error("a video needs at least one frame")]
    NoFrames,
    #[error("encoding the GIF: {0}")]
    Encode(String),
}

impl Frame {
    /// Checks the byte count against the size.
    pub fn new(width: u32, height: u32, rgb: Vec<u8>) -> Result<Frame, VideoError> {
        check(width, height, rgb.len())?;
        Ok(Frame { width, height, rgb })
    }
}

fn check(width: u32, height: u32, bytes: usize) -> Result<(), VideoError> {
    if width == 0 || height == 0 || width > MAX_SIDE || height > MAX_SIDE {
        return Err(VideoError::FrameSize { width, height });
    }
    let expected = width as usize * height as usize * 3;
    if bytes != expected {
        return Err(VideoError::FrameBytes {
            width,
            height,
            expected,
            got: bytes,
        });
    }
    Ok(())
}

/// Which states of one episode are drawn: the reset state, every [`STEPS_PER_FRAME`]-th step's
/// and the last step's, at most [`MAX_FRAMES`] (the last always among them).
#[derive(Debug, Default)]
pub struct Recorder {
    steps: u32,
    frames: Vec<Frame>,
}

impl Recorder {
    /// A recording whose first frame is the reset state.
    pub fn new(first: Frame) -> Recorder {
        Recorder {
            steps: 0,
            frames: vec![first],
        }
    }

    /// Counts one step; whether the state after it is to be drawn (`last`: the episode ended on
    /// it).
    pub fn step(&mut self, last: bool) -> bool {
        self.steps += 1;
        last || self.steps.is_multiple_of(STEPS_PER_FRAME)
    }

    /// Adds the frame of the step [`Recorder::step`] asked for. Past [`MAX_FRAMES`] the newest
    /// replaces the one before it, so the episode's end is always shown.
    pub fn push(&mut self, frame: Frame) {
        if self.frames.len() == MAX_FRAMES {
            self.frames.pop();
        }
        self.frames.push(frame);
    }

    pub fn steps(&self) -> u32 {
        self.steps
    }

    pub fn frames(&self) -> &[Frame] {
        &self.frames
    }
}

/// The frames as an animated GIF that loops, [`FRAME_DELAY_CS`] per frame. Frames of up to 256
/// colours keep them exactly; others are quantized per frame.
pub fn encode_gif(frames: &[Frame]) -> Result<Vec<u8>, VideoError> {
    let first = frames.first().ok_or(VideoError::NoFrames)?;
    let size = (first.width, first.height);
    check(size.0, size.1, first.rgb.len())?;
    // MAX_SIDE fits in a u16.
    let (w, h) = (size.0 as u16, size.1 as u16);
    let mut out = Vec::new();
    {
        let err = |e: gif::EncodingError| VideoError::Encode(e.to_string());
        let mut encoder = gif::Encoder::new(&mut out, w, h, &[]).map_err(err)?;
        encoder.set_repeat(gif::Repeat::Infinite).map_err(err)?;
        for (index, f) in frames.iter().enumerate() {
            if (f.width, f.height) != size {
                return Err(VideoError::SizeChanged {
                    index,
                    expected: size,
                    got: (f.width, f.height),
                });
            }
            // The fields are public: the encoder would panic on a wrong byte count.
            check(f.width, f.height, f.rgb.len())?;
            let mut frame = gif::Frame::from_rgb_speed(w, h, &f.rgb, QUANTIZER_SPEED);
            frame.delay = FRAME_DELAY_CS;
            encoder.write_frame(&frame).map_err(err)?;
        }
    }
    Ok(out)
}

/// The file name of an eval episode's video: what it shows first (`label`, e.g. `episode003` or
/// `v000120`), then its seed, success and return, so a listing says which to watch.
pub fn video_name(label: &str, seed: u64, success: bool, episode_return: f64) -> String {
    let outcome = if success { "success" } else { "failure" };
    format!("{label}_seed{seed}_{outcome}_return{episode_return:.1}.gif")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn solid(side: u32, rgb: [u8; 3]) -> Frame {
        Frame::new(side, side, rgb.repeat((side * side) as usize)).unwrap()
    }

    fn decode(bytes: &[u8]) -> (u16, u16, Vec<Vec<u8>>) {
        let mut options = gif::DecodeOptions::new();
        options.set_color_output(gif::ColorOutput::RGBA);
        let mut decoder = options.read_info(bytes).unwrap();
        let mut frames = Vec::new();
        while let Some(f) = decoder.read_next_frame().unwrap() {
            frames.push(f.buffer.to_vec());
        }
        (decoder.width(), decoder.height(), frames)
    }

    #[test]
    fn every_third_step_and_the_last_are_drawn() {
        let mut r = Recorder::new(solid(2, [0, 0, 0]));
        // 8 steps: 3 and 6 by the rule, 8 as the last.
        let drawn: Vec<u32> = (1..=8).filter(|&s| r.step(s == 8)).collect();
        assert_eq!(drawn, [3, 6, 8]);
        // A 300-step episode: the reset state and 100 steps = 101 frames.
        let mut r = Recorder::new(solid(2, [0, 0, 0]));
        for s in 1..=300 {
            if r.step(s == 300) {
                r.push(solid(2, [1, 1, 1]));
            }
        }
        assert_eq!((r.steps(), r.frames().len()), (300, 101));
    }

    #[test]
    fn a_long_episode_keeps_its_last_frame() {
        let mut r = Recorder::new(solid(2, [0, 0, 0]));
        for i in 0..MAX_FRAMES + 10 {
            r.push(solid(2, [0, 0, (i % 200) as u8]));
        }
        assert_eq!(r.frames().len(), MAX_FRAMES);
        let last = (MAX_FRAMES + 9) % 200;
        assert_eq!(r.frames().last().unwrap().rgb[2], last as u8);
    }

    #[test]
    fn frames_are_checked() {
        assert_eq!(
            Frame::new(2, 2, vec![0; 11]),
            Err(VideoError::FrameBytes {
                width: 2,
                height: 2,
                expected: 12,
                got: 11
            })
        );
        assert!(matches!(
            Frame::new(0, 2, vec![]),
            Err(VideoError::FrameSize { .. })
        ));
        assert_eq!(encode_gif(&[]), Err(VideoError::NoFrames));
        assert!(matches!(
            encode_gif(&[solid(2, [0, 0, 0]), solid(3, [0, 0, 0])]),
            Err(VideoError::SizeChanged { index: 1, .. })
        ));
    }

    /// Few colours come back exactly; a frame of more than 256 colours is quantized, not refused.
    #[test]
    fn a_gif_decodes_to_its_frames() {
        let a = solid(4, [250, 10, 10]);
        let b = solid(4, [10, 200, 30]);
        let bytes = encode_gif(&[a, b.clone()]).unwrap();
        assert_eq!(&bytes[..6], b"GIF89a");
        let (w, h, frames) = decode(&bytes);
        assert_eq!((w, h, frames.len()), (4, 4, 2));
        assert_eq!(&frames[1][..4], &[10, 200, 30, 255]);

        let gradient: Vec<u8> = (0..32 * 32)
            .flat_map(|i| [(i % 256) as u8, (i / 4 % 256) as u8, (i * 7 % 256) as u8])
            .collect();
        let bytes = encode_gif(&[Frame::new(32, 32, gradient).unwrap()]).unwrap();
        let (w, h, frames) = decode(&bytes);
        assert_eq!((w, h, frames.len()), (32, 32, 1));
    }

    #[test]
    fn names_say_seed_outcome_and_return() {
        assert_eq!(
            video_name("episode003", 1099511627776, true, 12.34),
            "episode003_seed1099511627776_success_return12.3.gif"
        );
    }
}
