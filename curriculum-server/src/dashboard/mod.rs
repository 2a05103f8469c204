//! The curriculum dashboard: one self-refreshing HTML page (no JavaScript build step, charts drawn
//! server-side as SVG with plotters), the same data as JSON, and Prometheus text.
//!
//! Rendering is pure: [`DashboardView`] in, strings out. The service builds the view under its lock
//! and renders outside it.
//!
//! * [`view`]: the view model, which `/api/state` serves as JSON and the root crate reads.
//! * [`charts`]: the SVG charts.
//! * [`html`]: the page.
//! * [`metrics`]: the Prometheus text of `/metrics`.
pub mod charts;
pub mod html;
pub mod metrics;
pub mod view;

pub use charts::{
    demo_bars_svg, demo_frontiers_svg, level_probabilities_svg, maze_heatmap_svg, progress_svg,
};
pub use html::render_html;
pub use metrics::metrics_text;
pub use view::{
    ActorRow, DashboardView, DemoBar, DemoDifficulty, EvalPoint, LearnerPanel, LearnerWindowView,
    LevelRow, MazeCell, MazeSnapshot, MazeView, ProgressPoint, RefusedReports, RunState,
    TimeShares, VideoLink,
};

#[cfg(test)]
mod tests;
