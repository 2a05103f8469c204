//! The dashboard's charts, drawn server-side as SVG with plotters. A chart that fails to draw
//! becomes an error paragraph in the page rather than failing the page.
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;

use super::view::{DemoBar, EvalPoint, LevelRow, MazeSnapshot, MazeView, ProgressPoint};

const CHART_W: u32 = 640;

type Root<'a> = DrawingArea<SVGBackend<'a>, plotters::coord::Shift>;
type Drawn = Result<(), Box<dyn std::error::Error>>;

/// The SVG of a `size` chart that `draw` draws on a white background, or an error paragraph
/// when drawing fails.
fn svg_chart(size: (u32, u32), draw: impl FnOnce(&Root<'_>) -> Drawn) -> String {
    let mut svg = String::new();
    let result = (|| -> Drawn {
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        root.fill(&WHITE)?;
        draw(&root)?;
        root.present()?;
        Ok(())
    })();
    match result {
        Ok(()) => svg,
        Err(e) => format!("<p class=err>chart failed: {e:?}</p>"),
    }
}

/// Horizontal bars, one per demo: the filled part is the part of the demo the curriculum has
/// reached, (S_i - 1 - t_i) / (S_i - 1); solved demos are green.
pub fn demo_bars_svg(demos: &[DemoBar]) -> String {
    let height = 40 + 26 * demos.len().max(1) as u32;
    svg_chart((CHART_W, height), |root| {
        let n = demos.len().max(1) as i32;
        let mut chart = ChartBuilder::on(root)
            .margin(8)
            .x_label_area_size(28)
            .y_label_area_size(70)
            .build_cartesian_2d(0f64..1f64, (0..n).into_segmented())?;
        chart
            .configure_mesh()
            .disable_y_mesh()
            .x_desc("fraction of the demo reached (1 - t_i/(S_i-1))")
            .y_label_formatter(&|v| match v {
                SegmentValue::CenterOf(i) => demos
                    .get(*i as usize)
                    .map(|d| format!("demo {}", d.demo))
                    .unwrap_or_default(),
                _ => String::new(),
            })
            .draw()?;
        chart.draw_series(demos.iter().enumerate().map(|(i, d)| {
            let reached = if d.states > 1 {
                1.0 - d.t as f64 / (d.states - 1) as f64
            } else {
                1.0
            };
            let color = if d.solved {
                GREEN.mix(0.8)
            } else {
                BLUE.mix(0.6)
            };
            let i = i as i32;
            Rectangle::new(
                [
                    (0.0, SegmentValue::Exact(i)),
                    (reached, SegmentValue::Exact(i + 1)),
                ],
                color.filled(),
            )
        }))?;
        Ok(())
    })
}

/// Side of one maze cell in the heatmap, in pixels.
const MAZE_CELL_PX: u32 = 13;

/// White at 0, the page's green at 1 (opaque: a transparent colour would not be drawn at all).
fn success_color(rate: f64) -> RGBColor {
    let rate = rate.clamp(0.0, 1.0);
    let lerp = |from: u8, to: u8| (from as f64 + (to as f64 - from as f64) * rate).round() as u8;
    RGBColor(lerp(255, 26), lerp(255, 127), lerp(255, 55))
}

/// The PointMaze heatmap: one small maze per snapshot, each start cell shaded from white (never
/// solved) to green (always solved), walls dark, hazard walls dark red, the goal red, the demos'
/// paths blue (the paper's figure). Cells without eval episodes stay light grey.
pub fn maze_heatmap_svg(maze: &MazeView) -> String {
    let rows = maze.map.len().max(1) as u32;
    let cols = maze.map.iter().map(|r| r.len()).max().unwrap_or(1).max(1) as u32;
    let panels = maze.snapshots.len().max(1) as u32;
    let (caption_h, gap) = (30u32, 12u32);
    let panel_w = cols * MAZE_CELL_PX;
    let width = panels * panel_w + (panels + 1) * gap;
    let height = rows * MAZE_CELL_PX + caption_h + gap;
    svg_chart((width, height), |root| {
        let empty = MazeSnapshot::default();
        let snapshots: Vec<&MazeSnapshot> = if maze.snapshots.is_empty() {
            vec![&empty]
        } else {
            maze.snapshots.iter().collect()
        };
        for (p, snap) in snapshots.iter().enumerate() {
            let x0 = gap as i32 + p as i32 * (panel_w + gap) as i32;
            let caption = if maze.snapshots.is_empty() {
                "no eval yet".to_string()
            } else {
                format!(
                    "{} steps: {:.0}%",
                    snap.env_steps,
                    snap.success_rate * 100.0
                )
            };
            root.draw_text(
                &caption,
                &("sans-serif", 15).into_font().color(&BLACK),
                (x0, 8),
            )?;
            let grid = root
                .clone()
                .shrink((x0, caption_h as i32), (panel_w, rows * MAZE_CELL_PX));
            let mut chart = ChartBuilder::on(&grid)
                .build_cartesian_2d(-0.5f32..cols as f32 - 0.5, rows as f32 - 0.5..-0.5f32)?;
            for (r, line) in maze.map.iter().enumerate() {
                for (c, ch) in line.chars().enumerate() {
                    let color = match ch {
                        '#' => RGBColor(60, 60, 60).filled(),
                        'X' => RGBColor(150, 30, 30).filled(),
                        _ => match snap
                            .cells
                            .iter()
                            .find(|m| (m.row, m.col) == (r as u32, c as u32))
                        {
                            Some(m) if m.episodes > 0 => {
                                success_color(m.successes as f64 / m.episodes as f64).filled()
                            }
                            _ => RGBColor(235, 235, 235).filled(),
                        },
                    };
                    let (x, y) = (c as f32, r as f32);
                    chart.draw_series(std::iter::once(Rectangle::new(
                        [(x - 0.5, y - 0.5), (x + 0.5, y + 0.5)],
                        color,
                    )))?;
                    if ch == 'G' {
                        chart.draw_series(std::iter::once(Circle::new((x, y), 4, RED.filled())))?;
                    }
                }
            }
            for path in &maze.demo_paths {
                chart.draw_series(std::iter::once(PathElement::new(
                    path.iter().map(|[x, y]| (*x, *y)).collect::<Vec<_>>(),
                    BLUE.mix(0.7).stroke_width(2),
                )))?;
            }
        }
        Ok(())
    })
}

/// Sampling probability per level, as bars (at most the 60 most likely levels are drawn).
pub fn level_probabilities_svg(levels: &[LevelRow]) -> String {
    let mut top: Vec<&LevelRow> = levels.iter().collect();
    top.sort_by(|a, b| {
        b.probability
            .total_cmp(&a.probability)
            .then(a.level.cmp(&b.level))
    });
    top.truncate(60);
    svg_chart((CHART_W, 220), |root| {
        let n = top.len().max(1) as i32;
        let max_p = top.first().map(|l| l.probability).unwrap_or(1.0).max(1e-9);
        let mut chart = ChartBuilder::on(root)
            .margin(8)
            .x_label_area_size(28)
            .y_label_area_size(50)
            .build_cartesian_2d((0..n).into_segmented(), 0f64..max_p * 1.05)?;
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_desc("levels, most likely first")
            .y_desc("P(level)")
            .x_label_formatter(&|_| String::new())
            .draw()?;
        chart.draw_series(top.iter().enumerate().map(|(i, l)| {
            let i = i as i32;
            let color = match l.score as i64 {
                3 => RED.mix(0.7),
                2 => BLUE.mix(0.6),
                _ => GREEN.mix(0.6),
            };
            Rectangle::new(
                [
                    (SegmentValue::Exact(i), 0.0),
                    (SegmentValue::Exact(i + 1), l.probability),
                ],
                color.filled(),
            )
        }))?;
        Ok(())
    })
}

/// One line of the progress chart: its legend, its colour and what it plots of each sample.
type Series = (&'static str, RGBColor, fn(&ProgressPoint) -> f64);

/// The progress chart's series and their colours, for the legend the page prints under the chart
/// (drawn inside the plot, a legend covers the curves).
pub const PROGRESS_LEGEND: [(&str, &str); 4] = [
    ("start step frac (avg t_i/(S_i-1))", "#0000ff"),
    ("demos solved", "#00ff00"),
    ("train success", "#ff00ff"),
    ("eval success at end", "#ff0000"),
];

type FractionsChart<'a, 'b> =
    ChartContext<'a, SVGBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// A chart of fractions (0 to 1) against env steps, from 0 to the largest of `steps`.
fn fractions_chart<'a, 'b>(
    root: &'a Root<'b>,
    steps: impl Iterator<Item = u64>,
) -> Result<FractionsChart<'a, 'b>, Box<dyn std::error::Error>> {
    let max_x = steps.max().unwrap_or(1).max(1) as f64;
    Ok(ChartBuilder::on(root)
        .margin(8)
        .x_label_area_size(28)
        .y_label_area_size(40)
        .build_cartesian_2d(0f64..max_x, 0f64..1.02f64)?)
}

/// Curriculum progress and success rates against env steps (the page prints [`PROGRESS_LEGEND`]).
pub fn progress_svg(history: &[ProgressPoint], evals: &[EvalPoint]) -> String {
    svg_chart((CHART_W, 260), |root| {
        let steps = history.iter().map(|p| p.env_steps);
        let mut chart = fractions_chart(root, steps.chain(evals.iter().map(|e| e.env_steps)))?;
        chart.configure_mesh().x_desc("env steps").draw()?;
        let series: [Series; 3] = [
            (PROGRESS_LEGEND[0].0, BLUE, |p| p.start_step_frac_avg),
            (PROGRESS_LEGEND[1].0, GREEN, |p| p.solved_frac),
            (PROGRESS_LEGEND[2].0, MAGENTA, |p| p.train_success_rate),
        ];
        for (_, color, f) in series {
            chart.draw_series(LineSeries::new(
                history.iter().map(|p| (p.env_steps as f64, f(p))),
                color.stroke_width(2),
            ))?;
        }
        chart.draw_series(LineSeries::new(
            evals.iter().map(|e| (e.env_steps as f64, e.success_at_end)),
            RED.stroke_width(2),
        ))?;
        Ok(())
    })
}

/// The colour of demo `i` in the per-demo frontier chart and its legend.
pub fn demo_color(i: usize) -> RGBColor {
    let c = Palette99::pick(i).to_rgba();
    RGBColor(c.0, c.1, c.2)
}

/// Per-demo frontier over env steps: for each demo the part reached, 1 - t_i/(S_i-1), as a step
/// line from 0 to `now` env steps (the page prints the legend, [`demo_color`]). A stalled demo's
/// line is flat at the end while the others climb (docs/ALGORITHM.md 2.10).
pub fn demo_frontiers_svg(demos: &[DemoBar], now: u64) -> String {
    svg_chart((CHART_W, 240), |root| {
        let steps = demos
            .iter()
            .flat_map(|d| d.difficulty.frontier.iter().map(|p| p[0]));
        let mut chart = fractions_chart(root, steps.chain([now]))?;
        chart
            .configure_mesh()
            .x_desc("env steps")
            .y_desc("part reached")
            .draw()?;
        let max_x = chart.x_range().end;
        for (i, d) in demos.iter().enumerate() {
            let last = d.states.saturating_sub(1).max(1) as f64;
            let reached = |t: u64| 1.0 - t as f64 / last;
            let mut points = vec![(0.0, 0.0)];
            let mut level = 0.0;
            for &[steps, t] in &d.difficulty.frontier {
                points.push((steps as f64, level));
                level = reached(t);
                points.push((steps as f64, level));
            }
            points.push((max_x, level));
            let width = if d.difficulty.stalled { 4 } else { 2 };
            chart.draw_series(LineSeries::new(points, demo_color(i).stroke_width(width)))?;
        }
        Ok(())
    })
}
