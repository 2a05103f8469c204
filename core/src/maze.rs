//! The fixed 12×12 PointMaze layout (spec 7.5): walls, the goal cell, the start cells that the
//! forward curriculum's seeds map to, and shortest paths to the goal. It lives in rfcl-core so
//! that the curriculum server's dashboard can draw the maze without the actor crate.
//!
//! Coordinates: cell `(row, col)` is the unit square centred on `x = col`, `y = row`, so `y` grows
//! downwards on the map, like the row index.

use std::collections::VecDeque;
use std::sync::LazyLock;

/// A maze cell as `(row, col)`.
pub type Cell = (usize, usize);

/// Rows and columns of the maze.
pub const SIZE: usize = 12;

/// The layout: `#` wall, `X` hazard wall, `.` open start cell, `G` the goal cell.
///
/// A serpentine corridor leads from the goal (top left) down to the far end of the bottom corridor,
/// with three dead ends. Walls between corridors are two cells thick, so cells that look close to the
/// goal (row 4) are 10 or more cells away along the corridors.
///
/// Every wall blocks the point. Only hazard walls (`X`, the spec's "2" cells) count as a collision
/// (spec 7.5: within 0.65 of a "2" cell, after which the episode earns nothing): the wall behind the
/// goal and the caps of the three dead ends, so overshooting the end of a corridor is fatal.
/// Measured (2026-11-23) with every wall a hazard: a stochastic policy that meets an unvisited
/// corridor cell drives into a wall within a step or two, so stage 2 never found the first success
/// from the cells next to the solved ones (10 cells at 0 returns over 830 episodes each) and eval
/// success stayed at 70 %.
pub const MAP: &str = "\
############
XG......####
#######.##X#
#######.##.#
##.........#
##.#########
##.#########
##.......###
###.####.###
###.####.###
###X#X...###
############";

/// The parsed layout with goal distances. Use [`maze`] for the one fixed instance.
#[derive(Debug)]
pub struct Maze {
    walls: [[bool; SIZE]; SIZE],
    hazards: [[bool; SIZE]; SIZE],
    goal: Cell,
    start_cells: Vec<Cell>,
    distance: [[Option<usize>; SIZE]; SIZE],
}

static MAZE: LazyLock<Maze> = LazyLock::new(|| Maze::parse(MAP));

/// The fixed PointMaze layout.
pub fn maze() -> &'static Maze {
    &MAZE
}

impl Maze {
    /// Parses [`MAP`]. Panics on a malformed map: the map is a constant checked by the tests.
    fn parse(map: &str) -> Self {
        let rows: Vec<&[u8]> = map.lines().map(str::as_bytes).collect();
        assert_eq!(rows.len(), SIZE, "the map has {SIZE} rows");
        let mut walls = [[false; SIZE]; SIZE];
        let mut hazards = [[false; SIZE]; SIZE];
        let mut goal = None;
        let mut start_cells = Vec::new();
        for (r, row) in rows.iter().enumerate() {
            assert_eq!(row.len(), SIZE, "map row {r} has {SIZE} columns");
            for (c, &ch) in row.iter().enumerate() {
                match ch {
                    b'#' => walls[r][c] = true,
                    b'X' => (walls[r][c], hazards[r][c]) = (true, true),
                    b'.' => start_cells.push((r, c)),
                    b'G' => {
                        assert!(goal.replace((r, c)).is_none(), "the map has one goal");
                    }
                    other => panic!("unknown map character {:?} at {:?}", other as char, (r, c)),
                }
            }
        }
        let goal = goal.expect("the map has a goal");
        let mut maze = Self {
            walls,
            hazards,
            goal,
            start_cells,
            distance: [[None; SIZE]; SIZE],
        };
        maze.distance = maze.bfs_from_goal();
        maze
    }

    /// Breadth-first search from the goal over open cells (4-connected).
    fn bfs_from_goal(&self) -> [[Option<usize>; SIZE]; SIZE] {
        let mut distance = [[None; SIZE]; SIZE];
        distance[self.goal.0][self.goal.1] = Some(0);
        let mut queue = VecDeque::from([self.goal]);
        while let Some(cell) = queue.pop_front() {
            let d = distance[cell.0][cell.1].expect("queued cells have a distance");
            for next in self.open_neighbours(cell) {
                if distance[next.0][next.1].is_none() {
                    distance[next.0][next.1] = Some(d + 1);
                    queue.push_back(next);
                }
            }
        }
        distance
    }

    /// The 4-connected open neighbours of `cell`.
    fn open_neighbours(&self, (r, c): Cell) -> impl Iterator<Item = Cell> + '_ {
        [
            (r.wrapping_sub(1), c),
            (r + 1, c),
            (r, c.wrapping_sub(1)),
            (r, c + 1),
        ]
        .into_iter()
        .filter(|&(r, c)| r < SIZE && c < SIZE && !self.walls[r][c])
    }

    /// Whether `cell` is a wall. Cells outside the grid count as walls.
    pub fn is_wall(&self, (r, c): Cell) -> bool {
        r >= SIZE || c >= SIZE || self.walls[r][c]
    }

    /// Whether `cell` is a hazard wall (the spec's "2" cells): touching it is a collision. Cells
    /// outside the grid count as hazards, so leaving the grid is a collision too.
    pub fn is_hazard(&self, (r, c): Cell) -> bool {
        r >= SIZE || c >= SIZE || self.hazards[r][c]
    }

    /// The hazard walls among `cell` and its 8 neighbours.
    pub fn hazards_around(&self, cell: Cell) -> impl Iterator<Item = Cell> + '_ {
        self.walls_around(cell).filter(|&wall| self.is_hazard(wall))
    }

    /// The goal cell; the goal position is its centre.
    pub fn goal_cell(&self) -> Cell {
        self.goal
    }

    /// The open non-goal cells in row-major order: the possible start cells. Seed `s` starts in
    /// `start_cells()[s % start_cells().len()]` (spec 7.5).
    pub fn start_cells(&self) -> &[Cell] {
        &self.start_cells
    }

    /// The start cell of a seeded reset: `start_cells()[seed mod #start cells]`.
    pub fn seed_cell(&self, seed: u64) -> Cell {
        let n = self.start_cells.len() as u64;
        self.start_cells[(seed % n) as usize]
    }

    /// Number of cells on the shortest corridor path from `cell` to the goal; `None` for walls and
    /// unreachable cells.
    pub fn distance_to_goal(&self, (r, c): Cell) -> Option<usize> {
        self.distance.get(r)?.get(c).copied().flatten()
    }

    /// A shortest path of cells from `cell` to the goal, both included; `None` if `cell` is a wall
    /// or cannot reach the goal.
    pub fn path_to_goal(&self, cell: Cell) -> Option<Vec<Cell>> {
        let mut d = self.distance_to_goal(cell)?;
        let mut path = vec![cell];
        let mut here = cell;
        while d > 0 {
            here = self
                .open_neighbours(here)
                .find(|&n| self.distance_to_goal(n) == Some(d - 1))
                .expect("a cell at distance d > 0 has a neighbour at d - 1");
            path.push(here);
            d -= 1;
        }
        Some(path)
    }

    /// The wall cells among `cell` and its 8 neighbours. A point inside `cell` can only touch these.
    pub fn walls_around(&self, (r, c): Cell) -> impl Iterator<Item = Cell> + '_ {
        let rows = r.saturating_sub(1)..=(r + 1).min(SIZE - 1);
        rows.flat_map(move |r| {
            let cols = c.saturating_sub(1)..=(c + 1).min(SIZE - 1);
            cols.map(move |c| (r, c))
        })
        .filter(|&cell| self.is_wall(cell))
    }
}

/// Centre `[x, y]` of a cell: `x = col`, `y = row`.
pub fn cell_centre((r, c): Cell) -> [f32; 2] {
    [c as f32, r as f32]
}

/// The cell containing position `[x, y]` (nearest centre), or `None` outside the grid.
pub fn cell_at([x, y]: [f32; 2]) -> Option<Cell> {
    let (r, c) = (y.round(), x.round());
    let range = 0.0..SIZE as f32;
    (range.contains(&r) && range.contains(&c)).then_some((r as usize, c as usize))
}
