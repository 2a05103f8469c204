//! PointMaze drawn by us, for [`crate::env::Env::render`]: the maze, the goal, the point and the
//! trail of where it has been since the reset.
use super::maze::{self, Maze};
use crate::video::Frame;

/// Pixels per maze cell.
pub const CELL_PX: usize = 20;
/// The point is drawn larger than its radius (0.1 cells, 2 pixels) so that it can be seen.
const POINT_DRAWN_RADIUS_PX: f32 = 6.0;
/// Radius of the trail's dots.
const TRAIL_RADIUS_PX: f32 = 1.5;

pub const FLOOR: [u8; 3] = [250, 250, 250];
pub const WALL: [u8; 3] = [60, 60, 60];
pub const HAZARD: [u8; 3] = [170, 40, 40];
pub const GOAL: [u8; 3] = [40, 160, 70];
pub const TRAIL: [u8; 3] = [140, 180, 230];
pub const POINT: [u8; 3] = [20, 80, 200];
/// The point once it has touched a wall (the episode can no longer succeed).
pub const POINT_COLLIDED: [u8; 3] = [230, 120, 0];

/// Frame side in pixels (the maze is square).
pub fn frame_side() -> usize {
    maze::SIZE * CELL_PX
}

/// The point at `now` (cell `(row, col)` is centred on `x = col`, `y = row`), the trail of its
/// earlier positions, row 0 of the map at the top.
pub fn draw(trail: &[[f32; 2]], now: [f32; 2], collided: bool) -> Frame {
    let side = frame_side();
    let mut px = background(maze::maze());
    for &xy in trail {
        disc(&mut px, side, xy, TRAIL_RADIUS_PX, TRAIL);
    }
    let colour = if collided { POINT_COLLIDED } else { POINT };
    disc(&mut px, side, now, POINT_DRAWN_RADIUS_PX, colour);
    Frame::new(side as u32, side as u32, px.concat()).expect("the maze fits a frame")
}

/// The maze without the point: walls, hazard walls and the goal cell.
fn background(m: &Maze) -> Vec<[u8; 3]> {
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
fn disc(px: &mut [[u8; 3]], side: usize, [x, y]: [f32; 2], radius: f32, colour: [u8; 3]) {
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

#[cfg(test)]
mod tests {
    use super::*;

    fn at(f: &Frame, x: usize, y: usize) -> [u8; 3] {
        let i = 3 * (y * f.width as usize + x);
        [f.rgb[i], f.rgb[i + 1], f.rgb[i + 2]]
    }

    #[test]
    fn the_point_is_drawn_in_its_cell_and_turns_orange_after_a_collision() {
        // Cell (row 1, col 1) is open floor; its centre (x 1, y 1) is pixel (1.5 * 20, 1.5 * 20).
        assert!(!maze::maze().is_wall((1, 1)));
        let free = draw(&[], [1.0, 1.0], false);
        assert_eq!(free.width as usize, frame_side());
        assert_eq!(at(&free, 30, 30), POINT);
        assert_eq!(at(&draw(&[], [1.0, 1.0], true), 30, 30), POINT_COLLIDED);
        // The top-left cell is a wall.
        assert!(maze::maze().is_wall((0, 0)));
        assert_eq!(at(&free, 0, 0), WALL);
        // The trail: a dot where the point was, in an open cell away from the point.
        let (r, c) = maze::maze()
            .start_cells()
            .iter()
            .copied()
            .find(|&(r, c)| r.abs_diff(1) + c.abs_diff(1) >= 2)
            .unwrap();
        let (x, y) = (c * CELL_PX + CELL_PX / 2, r * CELL_PX + CELL_PX / 2);
        let was = [c as f32, r as f32];
        assert_eq!(at(&free, x, y), FLOOR);
        assert_eq!(at(&draw(&[was], [1.0, 1.0], false), x, y), TRAIL);
    }
}
