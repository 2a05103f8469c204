//! The fixed PointMaze layout (spec 7.5): size, start cells, seeds → cells, goal paths.

use rfcl_actor::pointmaze::{self, maze, Cell, MAP, NEAR_GOAL_DISTANCE};

#[test]
fn map_is_12_by_12_with_a_wall_border() {
    let rows: Vec<&str> = MAP.lines().collect();
    assert_eq!(rows.len(), 12);
    assert!(rows.iter().all(|r| r.len() == 12));
    for i in 0..12 {
        for cell in [(0, i), (11, i), (i, 0), (i, 11)] {
            assert!(maze().is_wall(cell), "border cell {cell:?} is open");
        }
    }
    assert!(maze().is_wall((12, 3)), "outside the grid counts as wall");
}

#[test]
fn there_are_34_start_cells_in_row_major_order() {
    let cells = pointmaze::start_cells();
    assert_eq!(
        cells.len(),
        34,
        "docs/ALGORITHM.md 7.5: num_seeds 34, one seed per cell"
    );
    assert!(cells.windows(2).all(|w| w[0] < w[1]), "row-major order");
    assert!(!cells.contains(&maze().goal_cell()));
    assert!(cells.iter().all(|&c| !maze().is_wall(c)));
    let open = MAP.chars().filter(|&ch| matches!(ch, '.' | 'G')).count();
    assert_eq!(open, 35, "34 start cells and the goal");
}

#[test]
fn hazards_are_the_wall_behind_the_goal_and_the_dead_end_caps() {
    let hazards: Vec<Cell> = (0..12)
        .flat_map(|r| (0..12).map(move |c| (r, c)))
        .filter(|&cell| maze().is_hazard(cell))
        .collect();
    assert_eq!(hazards, [(1, 0), (2, 10), (10, 3), (10, 5)]);
    assert!(hazards.iter().all(|&cell| maze().is_wall(cell)));
    assert!(
        maze().is_hazard((12, 3)),
        "outside the grid counts as hazard"
    );
    // Each hazard closes the end of a corridor: one open neighbour.
    for (r, c) in hazards {
        let open = [
            (r.wrapping_sub(1), c),
            (r + 1, c),
            (r, c.wrapping_sub(1)),
            (r, c + 1),
        ]
        .into_iter()
        .filter(|&n| !maze().is_wall(n))
        .count();
        assert_eq!(open, 1, "hazard {:?}", (r, c));
    }
}

#[test]
fn seed_maps_to_its_cell_modulo_34() {
    let cells = pointmaze::start_cells();
    for seed in 0..34u64 {
        assert_eq!(pointmaze::seed_cell(seed), cells[seed as usize]);
        assert_eq!(pointmaze::seed_cell(seed + 34), cells[seed as usize]);
        assert_eq!(pointmaze::seed_cell(seed + 34 * 1000), cells[seed as usize]);
    }
    assert_eq!(
        pointmaze::seed_cell(u64::MAX),
        cells[(u64::MAX % 34) as usize]
    );
}

#[test]
fn goal_is_reachable_from_every_open_cell_along_adjacent_cells() {
    let goal = maze().goal_cell();
    assert_eq!(maze().distance_to_goal(goal), Some(0));
    for &cell in &pointmaze::start_cells() {
        let d = maze().distance_to_goal(cell).expect("reachable");
        let path = maze().path_to_goal(cell).expect("a path");
        assert_eq!(path.len(), d + 1, "shortest path of {cell:?}");
        assert_eq!(path[0], cell);
        assert_eq!(*path.last().unwrap(), goal);
        for pair in path.windows(2) {
            let ((r0, c0), (r1, c1)) = (pair[0], pair[1]);
            assert_eq!(
                r0.abs_diff(r1) + c0.abs_diff(c1),
                1,
                "{pair:?} are not adjacent"
            );
            assert!(!maze().is_wall(pair[1]));
        }
    }
    assert_eq!(maze().path_to_goal((0, 0)), None, "walls have no path");
}

#[test]
fn the_goal_is_far_from_most_start_cells() {
    let distances: Vec<usize> = pointmaze::start_cells()
        .iter()
        .map(|&c| maze().distance_to_goal(c).unwrap())
        .collect();
    let far = distances.iter().filter(|&&d| d >= 10).count();
    assert!(
        far * 3 >= distances.len() * 2,
        "at least 2/3 of the cells are 10+ cells away"
    );
    assert_eq!(distances.iter().max(), Some(&28));
    let near = distances
        .iter()
        .filter(|&&d| d <= NEAR_GOAL_DISTANCE)
        .count();
    assert_eq!(near, 5, "the cells an unseeded reset mostly avoids");
    // Row 4 looks close to the goal but is separated from it by two rows of wall.
    let looks_close: Cell = (4, 2);
    assert!(maze().distance_to_goal(looks_close).unwrap() >= 10);
}

#[test]
fn cell_centres_and_cells_invert() {
    for &cell in &pointmaze::start_cells() {
        let [x, y] = pointmaze::cell_centre(cell);
        assert_eq!((x, y), (cell.1 as f32, cell.0 as f32));
        assert_eq!(pointmaze::cell_at([x + 0.49, y - 0.49]), Some(cell));
    }
    assert_eq!(pointmaze::cell_at([-0.6, 3.0]), None);
    assert_eq!(pointmaze::cell_at([3.0, f32::NAN]), None);
    assert_eq!(pointmaze::goal_position(), [1.0, 1.0]);
}
