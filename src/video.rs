//! Eval episodes as videos: PointMaze drawn by us (the maze, the goal, the point and its trail) and
//! written as an animated GIF, which any browser plays and which needs no encoder on the machine.
//!
//! Drawing is pure ([`pointmaze_frames`]: positions in, indexed pixels out); [`write_gif`] does the
//! file.
use std::borrow::Cow;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use rfcl_core::maze::{self, Maze};

/// Pixels per maze cell.
pub const CELL_PX: usize = 20;
/// One frame every this many env steps (a 300-step episode is 101 frames).
pub const STEPS_PER_FRAME: usize = 3;
/// Display time of one frame, in GIF units of 1/100 s.
const FRAME_DELAY: u16 = 4;
/// The point is drawn larger than its radius (0.1 cells, 2 pixels) so that it can be seen.
const POINT_DRAWN_RADIUS_PX: f32 = 6.0;
/// Radius of the trail's dots.
const TRAIL_RADIUS_PX: f32 = 1.5;

/// The palette, by index: floor, wall, hazard wall, goal, trail, point, point after a collision.
const PALETTE: [[u8; 3]; 7] = [
    [250, 250, 250],
    [60, 60, 60],
    [170, 40, 40],
    [40, 160, 70],
    [140, 180, 230],
    [20, 80, 200],
    [230, 120, 0],
];
const FLOOR: u8 = 0;
const WALL: u8 = 1;
const HAZARD: u8 = 2;
const GOAL: u8 = 3;
const TRAIL: u8 = 4;
const POINT: u8 = 5;
const POINT_COLLIDED: u8 = 6;

/// One step of an episode as drawn: the point's `(x, y)` (cell `(row, col)` is centred on
/// `x = col`, `y = row`) and whether it has touched a hazard wall so far.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointStep {
    pub xy: [f32; 2],
    pub collided: bool,
}

impl PointStep {
    /// From a PointMaze observation `x, y, vx, vy, goal_x, goal_y, collided_once`.
    pub fn from_obs(obs: &[f32]) -> Option<PointStep> {
        Some(PointStep {
            xy: [*obs.first()?, *obs.get(1)?],
            collided: *obs.get(6)? > 0.5,
        })
    }
}

/// Frame size in pixels (the maze is square).
pub fn frame_side() -> usize {
    maze::SIZE * CELL_PX
}

/// The frames of one episode (`steps[0]` is the reset state): one every [`STEPS_PER_FRAME`] steps
/// and always the last, each `frame_side()²` palette indices, row-major from the top-left (row 0
/// of the map at the top).
pub fn pointmaze_frames(steps: &[PointStep]) -> Vec<Vec<u8>> {
    let background = background(maze::maze());
    let side = frame_side();
    let mut picked: Vec<usize> = (0..steps.len()).step_by(STEPS_PER_FRAME).collect();
    if steps.len() > 1 && picked.last() != Some(&(steps.len() - 1)) {
        picked.push(steps.len() - 1);
    }
    picked
        .into_iter()
        .map(|upto| {
            let mut frame = background.clone();
            for s in &steps[..upto] {
                disc(&mut frame, side, s.xy, TRAIL_RADIUS_PX, TRAIL);
            }
            let now = steps[upto];
            let colour = if now.collided { POINT_COLLIDED } else { POINT };
            disc(&mut frame, side, now.xy, POINT_DRAWN_RADIUS_PX, colour);
            frame
        })
        .collect()
}

/// The maze without the point: walls, hazard walls and the goal cell.
fn background(m: &Maze) -> Vec<u8> {
    let side = frame_side();
    let mut px = vec![FLOOR; side * side];
    let goal = m.goal_cell();
    for r in 0..maze::SIZE {
        for c in 0..maze::SIZE {
            let colour = if m.is_hazard((r, c)) {
                HAZARD
            } else if m.is_wall((r, c)) {
                WALL
            } else if (r, c) == goal {
                GOAL
            } else {
                continue;
            };
            for y in r * CELL_PX..(r + 1) * CELL_PX {
                px[y * side + c * CELL_PX..y * side + (c + 1) * CELL_PX].fill(colour);
            }
        }
    }
    px
}

/// Paints a disc of `radius` pixels centred on the maze point `xy`.
fn disc(px: &mut [u8], side: usize, [x, y]: [f32; 2], radius: f32, colour: u8) {
    let cx = (x + 0.5) * CELL_PX as f32;
    let cy = (y + 0.5) * CELL_PX as f32;
    let lo = |v: f32| (v - radius).floor().max(0.0) as usize;
    let hi = |v: f32| ((v + radius).ceil().max(0.0) as usize).min(side);
    for py in lo(cy)..hi(cy) {
        for pxl in lo(cx)..hi(cx) {
            let (dx, dy) = (pxl as f32 + 0.5 - cx, py as f32 + 0.5 - cy);
            if dx * dx + dy * dy <= radius * radius {
                px[py * side + pxl] = colour;
            }
        }
    }
}

/// Writes `frames` (each `side²` palette indices) as an animated GIF that loops.
pub fn write_gif(path: &Path, side: usize, frames: &[Vec<u8>]) -> Result<()> {
    let file = std::fs::File::create(path)
        .with_context(|| format!("creating the video {}", path.display()))?;
    let palette: Vec<u8> = PALETTE.iter().flatten().copied().collect();
    let side16 = u16::try_from(side).context("frame side over 65535 pixels")?;
    let mut encoder = gif::Encoder::new(std::io::BufWriter::new(file), side16, side16, &palette)
        .with_context(|| format!("writing {}", path.display()))?;
    encoder
        .set_repeat(gif::Repeat::Infinite)
        .with_context(|| format!("writing {}", path.display()))?;
    for pixels in frames {
        let frame = gif::Frame {
            width: side16,
            height: side16,
            delay: FRAME_DELAY,
            buffer: Cow::Borrowed(pixels),
            ..gif::Frame::default()
        };
        encoder
            .write_frame(&frame)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

/// The file name of an eval episode's video: its index, seed, success and return, so a directory
/// listing says which to watch.
pub fn video_name(episode: u32, seed: u64, success: bool, episode_return: f64) -> PathBuf {
    let outcome = if success { "success" } else { "failure" };
    PathBuf::from(format!(
        "episode{episode:03}_seed{seed}_{outcome}_return{episode_return:.1}.gif"
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_are_taken_every_few_steps_and_at_the_end() {
        let step = |x: f32| PointStep {
            xy: [x, 1.0],
            collided: false,
        };
        // 301 states (the reset and 300 steps): 0, 3, ..., 300 is 101 frames.
        let steps: Vec<PointStep> = (0..301).map(|i| step(1.0 + i as f32 * 0.01)).collect();
        assert_eq!(pointmaze_frames(&steps).len(), 101);
        // 8 states: 0, 3, 6, and the last, 7.
        assert_eq!(pointmaze_frames(&steps[..8]).len(), 4);
        let side = frame_side();
        assert!(pointmaze_frames(&steps[..8])
            .iter()
            .all(|f| f.len() == side * side));
    }

    #[test]
    fn the_point_is_drawn_in_its_cell_and_turns_orange_after_a_collision() {
        // Cell (row 1, col 1) is open floor in the map; its centre is (x 1, y 1), pixel
        // (1.5 * 20, 1.5 * 20) = (30, 30).
        assert!(!maze::maze().is_wall((1, 1)));
        let side = frame_side();
        let at = |f: &[u8]| f[30 * side + 30];
        let free = pointmaze_frames(&[PointStep {
            xy: [1.0, 1.0],
            collided: false,
        }]);
        assert_eq!(at(&free[0]), POINT);
        let hit = pointmaze_frames(&[PointStep {
            xy: [1.0, 1.0],
            collided: true,
        }]);
        assert_eq!(at(&hit[0]), POINT_COLLIDED);
        // The top-left cell is a wall.
        assert!(maze::maze().is_wall((0, 0)));
        assert_eq!(free[0][0], WALL);
    }

    #[test]
    fn names_say_seed_outcome_and_return() {
        assert_eq!(
            video_name(3, 1099511627776, true, 12.34),
            PathBuf::from("episode003_seed1099511627776_success_return12.3.gif")
        );
    }

    #[test]
    fn a_written_gif_decodes_to_its_frames() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.gif");
        let steps: Vec<PointStep> = (0..10)
            .map(|i| PointStep {
                xy: [1.0 + 0.1 * i as f32, 1.0],
                collided: false,
            })
            .collect();
        let frames = pointmaze_frames(&steps);
        write_gif(&path, frame_side(), &frames).unwrap();
        let mut decoder = gif::DecodeOptions::new()
            .read_info(std::fs::File::open(&path).unwrap())
            .unwrap();
        let mut n = 0;
        while decoder.read_next_frame().unwrap().is_some() {
            n += 1;
        }
        assert_eq!(n, frames.len());
        assert_eq!(decoder.width() as usize, frame_side());
    }
}
