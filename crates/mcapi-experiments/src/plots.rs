//! Figures of the experiments (docs/algorithm.md §6), as PNG and SVG, drawn with
//! plotters and the bundled DejaVu Sans font (no system fonts needed).
//!
//! Hallway: Fig. 2(b) cumulative |r| (mean ± sd, MCA-PI vs Brownian),
//! 2(c) the drive over time, 2(d) the LSTDQ error (one run and the mean),
//! 2(e) V(10) and V(40). Maze: Fig. 3(b) cumulative stimulus per source,
//! 3(c) the drive, 3(d) the LSTDQ error, 3(e-g) value function and policy
//! over the map at three instants, each when a different drive dominates.
//! Curiosity room: Fig. 4(j) estimation error, 4(k) cumulative |r| EM+IM vs
//! EM-only, 4(l) cumulative stimulus per dimension, 4(m) occupancy of the map
//! per period between module freezes. The continuous experiments draw
//! with the same charts (`continuous::figures`).

use std::path::{Path, PathBuf};
use std::sync::Once;

use anyhow::{Result, anyhow};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::colors::colormaps::{ColorMap, ViridisRGB};
use plotters::style::text_anchor::{HPos, Pos, VPos};

use mcapi_core::model::GridMap;

use super::curiosity::room::{CuriosityRecord, Room, STIMULI};
use super::paper::{Experiment, ExperimentKind, Snapshot, TrialRecord};

const FONT: &str = "sans-serif";
pub(crate) const SIZE: (u32, u32) = (900, 520);
/// Most points drawn per series; longer series are averaged in windows.
const MAX_POINTS: usize = 1500;
/// Ticks shown in the time-series panels of single runs.
const WINDOW: usize = 1000;
pub(crate) const PALETTE: [RGBColor; 5] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
];

static FONT_ONCE: Once = Once::new();

fn register_font() {
    FONT_ONCE.call_once(|| {
        let bytes = include_bytes!("../../../assets/fonts/DejaVuSans.ttf");
        if plotters::style::register_font(FONT, FontStyle::Normal, bytes).is_err() {
            tracing::error!("bundled font could not be registered; figures will lack text");
        }
    });
}

/// One line, optionally with a shaded band (x, low, high).
pub(crate) struct Series {
    label: String,
    color: RGBColor,
    width: u32,
    points: Vec<(f64, f64)>,
    band: Option<Vec<(f64, f64, f64)>>,
}

pub(crate) struct LineChart {
    pub(crate) title: String,
    pub(crate) x_label: String,
    pub(crate) y_label: String,
    pub(crate) series: Vec<Series>,
}

/// Averages `ys` (values at ticks 1..) into at most MAX_POINTS points.
fn decimate(ys: &[f64]) -> Vec<(f64, f64)> {
    let w = ys.len().div_ceil(MAX_POINTS).max(1);
    ys.chunks(w)
        .enumerate()
        .map(|(i, c)| {
            (
                (i * w + c.len()) as f64,
                c.iter().sum::<f64>() / c.len() as f64,
            )
        })
        .collect()
}

pub(crate) fn cumsum(xs: impl Iterator<Item = f64>) -> Vec<f64> {
    xs.scan(0.0, |acc, x| {
        *acc += x;
        Some(*acc)
    })
    .collect()
}

/// Per-tick mean and sd over trials of a per-trial series.
fn mean_sd(series: &[Vec<f64>]) -> (Vec<f64>, Vec<f64>) {
    let n = series.len() as f64;
    let len = series.iter().map(Vec::len).min().unwrap_or(0);
    let mut mean = vec![0.0; len];
    let mut sd = vec![0.0; len];
    for t in 0..len {
        let m = series.iter().map(|s| s[t]).sum::<f64>() / n;
        let var = if series.len() > 1 {
            series.iter().map(|s| (s[t] - m).powi(2)).sum::<f64>() / (n - 1.0)
        } else {
            0.0
        };
        mean[t] = m;
        sd[t] = var.sqrt();
    }
    (mean, sd)
}

pub(crate) fn mean_band(label: &str, color: RGBColor, series: &[Vec<f64>]) -> Series {
    let (mean, sd) = mean_sd(series);
    let lo: Vec<f64> = mean.iter().zip(&sd).map(|(m, s)| m - s).collect();
    let hi: Vec<f64> = mean.iter().zip(&sd).map(|(m, s)| m + s).collect();
    let band = decimate(&lo)
        .into_iter()
        .zip(decimate(&hi))
        .map(|((x, l), (_, h))| (x, l, h))
        .collect();
    Series {
        label: format!("{label} (mean ± sd)"),
        color,
        width: 2,
        points: decimate(&mean),
        band: Some(band),
    }
}

pub(crate) fn line(label: impl Into<String>, color: RGBColor, width: u32, ys: &[f64]) -> Series {
    Series {
        label: label.into(),
        color,
        width,
        points: decimate(ys),
        band: None,
    }
}

/// Something drawable on any plotters backend.
pub(crate) trait Figure {
    fn title(&self) -> &str;
    fn draw<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
    ) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>>;
}

/// Draws `fig` to `<out>/<stem>.png` and `<out>/<stem>.svg`.
pub(crate) fn save(
    fig: &impl Figure,
    out: &Path,
    stem: &str,
    size: (u32, u32),
) -> Result<Vec<PathBuf>> {
    register_font();
    let png = out.join(format!("{stem}.png"));
    let svg = out.join(format!("{stem}.svg"));
    {
        let root = BitMapBackend::new(&png, size).into_drawing_area();
        fig.draw(&root)
            .and_then(|()| root.present())
            .map_err(|e| anyhow!("drawing {} ({}): {e:?}", fig.title(), png.display()))?;
    }
    {
        let root = SVGBackend::new(&svg, size).into_drawing_area();
        fig.draw(&root)
            .and_then(|()| root.present())
            .map_err(|e| anyhow!("drawing {} ({}): {e:?}", fig.title(), svg.display()))?;
    }
    Ok(vec![png, svg])
}

impl Figure for LineChart {
    fn title(&self) -> &str {
        &self.title
    }

    fn draw<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
    ) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
        root.fill(&WHITE)?;
        let mut x_max: f64 = 1.0;
        let (mut y_min, mut y_max) = (f64::INFINITY, f64::NEG_INFINITY);
        for s in &self.series {
            for &(x, y) in &s.points {
                x_max = x_max.max(x);
                y_min = y_min.min(y);
                y_max = y_max.max(y);
            }
            for &(_, l, h) in s.band.iter().flatten() {
                y_min = y_min.min(l);
                y_max = y_max.max(h);
            }
        }
        if !y_min.is_finite() || !y_max.is_finite() {
            (y_min, y_max) = (0.0, 1.0);
        }
        let pad = ((y_max - y_min) * 0.05).max(1e-9);
        let mut ctx = ChartBuilder::on(root)
            .caption(&self.title, (FONT, 22))
            .margin(14)
            .x_label_area_size(44)
            .y_label_area_size(72)
            .build_cartesian_2d(0.0..x_max, (y_min - pad)..(y_max + pad))?;
        let span = y_max - y_min;
        let y_fmt = move |y: &f64| {
            if span >= 20.0 {
                format!("{y:.0}")
            } else if span >= 2.0 {
                format!("{y:.1}")
            } else {
                format!("{y:.2}")
            }
        };
        ctx.configure_mesh()
            .x_label_formatter(&|x| format!("{x:.0}"))
            .y_label_formatter(&y_fmt)
            .x_desc(self.x_label.as_str())
            .y_desc(self.y_label.as_str())
            .label_style((FONT, 14))
            .axis_desc_style((FONT, 16))
            .light_line_style(WHITE.mix(0.0))
            .draw()?;
        for s in &self.series {
            if let Some(band) = &s.band {
                let mut poly: Vec<(f64, f64)> = band.iter().map(|&(x, _, h)| (x, h)).collect();
                poly.extend(band.iter().rev().map(|&(x, l, _)| (x, l)));
                ctx.draw_series(std::iter::once(Polygon::new(poly, s.color.mix(0.18))))?;
            }
        }
        for s in &self.series {
            let color = s.color;
            ctx.draw_series(LineSeries::new(
                s.points.iter().copied(),
                color.stroke_width(s.width),
            ))?
            .label(s.label.as_str())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 22, y)], color.stroke_width(3))
            });
        }
        ctx.configure_series_labels()
            .position(SeriesLabelPosition::UpperLeft)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.4))
            .label_font((FONT, 14))
            .draw()?;
        Ok(())
    }
}

/// Value function and greedy policy over a grid map.
struct ValueMap<'a> {
    title: String,
    grid: &'a GridMap,
    snapshot: &'a Snapshot,
    /// (mark, state) of each source.
    sources: Vec<(char, usize)>,
}

impl Figure for ValueMap<'_> {
    fn title(&self) -> &str {
        &self.title
    }

    fn draw<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
    ) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
        root.fill(&WHITE)?;
        let (rows, cols) = (self.grid.rows() as f64, self.grid.cols() as f64);
        let values = &self.snapshot.values;
        let lo = values.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let hi = if hi > lo { hi } else { lo + 1.0 };
        let mut ctx = ChartBuilder::on(root)
            .caption(&self.title, (FONT, 20))
            .margin(12)
            .build_cartesian_2d(0.0..cols, 0.0..rows)?;
        // Row r of the map is drawn from y = rows − r (top) to rows − r − 1.
        let cell = |r: usize, c: usize| {
            [
                (c as f64, rows - r as f64),
                (c as f64 + 1.0, rows - r as f64 - 1.0),
            ]
        };
        let centre = |s: usize| {
            let (r, c) = self.grid.cell_of(s);
            (c as f64 + 0.5, rows - r as f64 - 0.5)
        };
        let mut cells = Vec::new();
        for r in 0..self.grid.rows() {
            for c in 0..self.grid.cols() {
                let style = match self.grid.state_at(r, c) {
                    None => RGBColor(40, 40, 40).filled(),
                    Some(s) => ViridisRGB.get_color_normalized(values[s], lo, hi).filled(),
                };
                cells.push(Rectangle::new(cell(r, c), style));
            }
        }
        ctx.draw_series(cells)?;
        // Greedy action per state: an arrow (shaft and head), a dot for stay.
        let mut shafts = Vec::new();
        let mut heads = Vec::new();
        let mut stays = Vec::new();
        for s in 0..values.len() {
            let (x, y) = centre(s);
            let (dx, dy) = match self.snapshot.actions[s] {
                0 => (-1.0, 0.0),
                1 => (1.0, 0.0),
                2 => (0.0, 1.0),
                3 => (0.0, -1.0),
                _ => {
                    stays.push(Circle::new((x, y), 3, WHITE.filled()));
                    continue;
                }
            };
            let tip = (x + 0.38 * dx, y + 0.38 * dy);
            let base = (x + 0.1 * dx, y + 0.1 * dy);
            shafts.push(PathElement::new(
                vec![(x - 0.3 * dx, y - 0.3 * dy), base],
                WHITE.stroke_width(2),
            ));
            // The head: a triangle from `base` to `tip`, 0.36 wide.
            let (px, py) = (-dy * 0.18, dx * 0.18);
            heads.push(Polygon::new(
                vec![tip, (base.0 + px, base.1 + py), (base.0 - px, base.1 - py)],
                WHITE.filled(),
            ));
        }
        ctx.draw_series(shafts)?;
        ctx.draw_series(heads)?;
        ctx.draw_series(stays)?;
        let label_style = (FONT, 22)
            .into_font()
            .style(FontStyle::Bold)
            .color(&RED)
            .pos(Pos::new(HPos::Center, VPos::Center));
        let labels = self.sources.iter().map(|&(mark, s)| {
            let (x, y) = centre(s);
            Text::new(mark.to_string(), (x, y), label_style.clone())
        });
        ctx.draw_series(labels)?;
        ctx.draw_series(std::iter::once(Circle::new(
            centre(self.snapshot.state),
            9,
            RED.stroke_width(3),
        )))?;
        Ok(())
    }
}

/// Cumulative sums of a per-tick series of every trial.
fn cumulative_per_trial(
    recs: &[TrialRecord],
    f: impl Fn(&TrialRecord) -> Vec<f64>,
) -> Vec<Vec<f64>> {
    recs.iter().map(|r| cumsum(f(r).into_iter())).collect()
}

fn component(rec: &TrialRecord, j: usize, data: &[f64], width: usize) -> Vec<f64> {
    data.iter()
        .skip(j)
        .step_by(width)
        .take(rec.steps())
        .copied()
        .collect()
}

/// Draws every figure of an experiment into `out`; returns the files.
pub fn draw_experiment(
    exp: &Experiment,
    grouped: &[(&'static str, Vec<TrialRecord>)],
    out: &Path,
) -> Result<Vec<PathBuf>> {
    match exp.kind {
        ExperimentKind::Hallway => draw_hallway(exp, grouped, out),
        ExperimentKind::ThreeRoom => draw_maze(exp, grouped, out),
    }
}

fn records<'a>(
    grouped: &'a [(&'static str, Vec<TrialRecord>)],
    name: &str,
) -> Result<&'a [TrialRecord]> {
    grouped
        .iter()
        .find(|(n, _)| *n == name)
        .map(|(_, r)| r.as_slice())
        .filter(|r| !r.is_empty())
        .ok_or_else(|| anyhow!("no trials of {name}"))
}

fn drive_chart(title: String, exp: &Experiment, rec: &TrialRecord) -> LineChart {
    let n = rec.dims;
    let window = rec.steps().min(WINDOW);
    let series = exp
        .preset
        .model
        .stimuli()
        .iter()
        .enumerate()
        .map(|(j, name)| {
            let d: Vec<f64> = component(rec, j, &rec.drive, n)
                .iter()
                .take(window)
                .map(|x| x.abs())
                .collect();
            line(format!("|d_{name}|"), PALETTE[j % PALETTE.len()], 2, &d)
        })
        .collect();
    LineChart {
        title,
        x_label: "tick".into(),
        y_label: "drive component |d_j|".into(),
        series,
    }
}

fn error_chart(title: String, recs: &[TrialRecord]) -> LineChart {
    let per_trial: Vec<Vec<f64>> = recs.iter().map(|r| r.lstdq_error.clone()).collect();
    let (mean, _) = mean_sd(&per_trial);
    LineChart {
        title,
        x_label: "tick".into(),
        y_label: "||Q_t - Q_t+1||".into(),
        series: vec![
            line("one run", RGBColor(150, 150, 150), 1, &recs[0].lstdq_error),
            // Width 1: plotters' thick polylines spike at sharp turns.
            line(format!("mean of {} runs", recs.len()), PALETTE[0], 1, &mean),
        ],
    }
}

/// Panels (c) and (d) of both experiments' figures: the drive of one run
/// and the LSTDQ error (one run and the mean), as `fig<number>c_drive` and
/// `fig<number>d_lstdq_error`.
fn drive_and_error(
    exp: &Experiment,
    recs: &[TrialRecord],
    number: &str,
    world: &str,
    out: &Path,
) -> Result<Vec<PathBuf>> {
    let window = recs[0].steps().min(WINDOW);
    let fig_c = drive_chart(
        format!("Fig. {number}(c) {world}: drive D, first {window} ticks"),
        exp,
        &recs[0],
    );
    let mut files = save(&fig_c, out, &format!("fig{number}c_drive"), SIZE)?;
    let fig_d = error_chart(format!("Fig. {number}(d) {world}: LSTDQ error"), recs);
    files.extend(save(
        &fig_d,
        out,
        &format!("fig{number}d_lstdq_error"),
        SIZE,
    )?);
    Ok(files)
}

fn draw_hallway(
    exp: &Experiment,
    grouped: &[(&'static str, Vec<TrialRecord>)],
    out: &Path,
) -> Result<Vec<PathBuf>> {
    let mca = records(grouped, "mca_pi")?;
    let brown = records(grouped, "brownian")?;
    let mut files = Vec::new();
    let abs_r = |r: &TrialRecord| r.abs_reward.clone();
    let mut series = vec![
        mean_band("MCA-PI", PALETTE[0], &cumulative_per_trial(mca, abs_r)),
        mean_band(
            "Brownian, 4 states/tick",
            PALETTE[1],
            &cumulative_per_trial(brown, abs_r),
        ),
    ];
    if let Ok(learned) = records(grouped, "mca_pi_learned") {
        series.push(mean_band(
            "MCA-PI, learned model",
            PALETTE[2],
            &cumulative_per_trial(learned, abs_r),
        ));
    }
    let fig_b = LineChart {
        title: "Fig. 2(b) Hallway: cumulative |r|".into(),
        x_label: "tick".into(),
        y_label: "cumulative |r|".into(),
        series,
    };
    files.extend(save(&fig_b, out, "fig2b_cumulative_reward", SIZE)?);
    files.extend(drive_and_error(exp, mca, "2", "Hallway", out)?);
    let window = mca[0].steps().min(WINDOW);
    let n_src = exp.preset.sources.len();
    let series = exp
        .preset
        .sources
        .iter()
        .enumerate()
        .map(|(i, src)| {
            let v: Vec<f64> = component(&mca[0], i, &mca[0].source_values, n_src)
                .into_iter()
                .take(window)
                .collect();
            let name = &exp.preset.model.stimuli()[src.dim];
            line(
                format!("V({}) ({name})", src.state),
                PALETTE[i % PALETTE.len()],
                2,
                &v,
            )
        })
        .collect();
    let fig_e = LineChart {
        title: format!("Fig. 2(e) Hallway: value at the sources, first {window} ticks"),
        x_label: "tick".into(),
        y_label: "V(s)".into(),
        series,
    };
    files.extend(save(&fig_e, out, "fig2e_values", SIZE)?);
    Ok(files)
}

/// Cumulative stimulus (all sources) of the known and the learned model,
/// and how much of the learned model is known (docs/algorithm.md §8).
fn learned_vs_known(
    known: &[TrialRecord],
    learned: &[TrialRecord],
    out: &Path,
) -> Result<Vec<PathBuf>> {
    let total = |r: &TrialRecord| {
        r.stimulus
            .chunks_exact(r.dims)
            .map(|x| x.iter().sum())
            .collect()
    };
    let fig = LineChart {
        title: "Three-room maze: cumulative stimulus, known vs learned model".into(),
        x_label: "tick".into(),
        y_label: "cumulative stimulus (all sources)".into(),
        series: vec![
            mean_band("known P", PALETTE[0], &cumulative_per_trial(known, total)),
            mean_band(
                "learned P-hat",
                PALETTE[2],
                &cumulative_per_trial(learned, total),
            ),
        ],
    };
    let mut files = save(&fig, out, "fig3h_learned_vs_known", SIZE)?;
    let fraction: Vec<Vec<f64>> = learned
        .iter()
        .map(|r| r.known.iter().map(|&k| f64::from(k)).collect())
        .collect();
    let fig = LineChart {
        title: "Three-room maze: fraction of state-action pairs known".into(),
        x_label: "tick".into(),
        y_label: "known pairs / valid pairs".into(),
        series: vec![mean_band("learned P-hat", PALETTE[2], &fraction)],
    };
    files.extend(save(&fig, out, "fig3i_model_known", SIZE)?);
    Ok(files)
}

fn draw_maze(
    exp: &Experiment,
    grouped: &[(&'static str, Vec<TrialRecord>)],
    out: &Path,
) -> Result<Vec<PathBuf>> {
    let ind = records(grouped, "indicator")?;
    let mut files = Vec::new();
    let n = exp.dims();
    let mut series = Vec::new();
    for src in &exp.preset.sources {
        let cum = cumulative_per_trial(ind, |r| component(r, src.dim, &r.stimulus, n));
        let name = &exp.preset.model.stimuli()[src.dim];
        let color = PALETTE[src.dim % PALETTE.len()];
        series.push(mean_band(&format!("source {name}"), color, &cum));
        // One run shows the staircase that the mean smooths away.
        series.push(line(format!("source {name} (run 1)"), color, 1, &cum[0]));
    }
    let fig_b = LineChart {
        title: "Fig. 3(b) Three-room maze: cumulative stimulus per source".into(),
        x_label: "tick".into(),
        y_label: "cumulative stimulus".into(),
        series,
    };
    files.extend(save(&fig_b, out, "fig3b_cumulative_stimulus", SIZE)?);
    if let Ok(learned) = records(grouped, "indicator_learned") {
        files.extend(learned_vs_known(ind, learned, out)?);
    }
    files.extend(drive_and_error(exp, ind, "3", "Three-room maze", out)?);
    let grid = exp
        .preset
        .grid
        .as_ref()
        .ok_or_else(|| anyhow!("three-room preset has no map"))?;
    let mut snaps: Vec<&Snapshot> = ind[0].snapshots.iter().collect();
    snaps.sort_by_key(|s| s.tick);
    let sources: Vec<(char, usize)> = grid.marks().to_vec();
    for (snap, letter) in snaps.iter().take(3).zip(['e', 'f', 'g']) {
        let name = &exp.preset.model.stimuli()[snap.dominant];
        let fig = ValueMap {
            title: format!(
                "Fig. 3({letter}) V and policy at tick {}: drive for {name} dominates",
                snap.tick
            ),
            grid,
            snapshot: snap,
            sources: sources.clone(),
        };
        let size = (grid.cols() as u32 * 34 + 24, grid.rows() as u32 * 34 + 60);
        files.extend(save(&fig, out, &format!("fig3{letter}_values"), size)?);
    }
    Ok(files)
}

// ---------------------------------------------------------------------------
// Experiment 3: Fig. 4(j)-(m)
// ---------------------------------------------------------------------------

/// Visits per state over the map during one period of a run (Fig. 4m).
struct OccupancyMap<'a> {
    title: String,
    grid: &'a GridMap,
    /// Ticks spent in each state.
    visits: Vec<f64>,
    /// (mark, state) of F, R, K, M.
    marks: Vec<(char, usize)>,
}

impl Figure for OccupancyMap<'_> {
    fn title(&self) -> &str {
        &self.title
    }

    fn draw<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
    ) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
        root.fill(&WHITE)?;
        let (rows, cols) = (self.grid.rows() as f64, self.grid.cols() as f64);
        // Colour by log(1 + visits), so rarely visited cells still show.
        let shade: Vec<f64> = self.visits.iter().map(|v| v.ln_1p()).collect();
        let hi = shade.iter().copied().fold(0.0, f64::max).max(1e-9);
        let mut ctx = ChartBuilder::on(root)
            .caption(&self.title, (FONT, 18))
            .margin(12)
            .build_cartesian_2d(0.0..cols, 0.0..rows)?;
        let mut cells = Vec::new();
        for r in 0..self.grid.rows() {
            for c in 0..self.grid.cols() {
                let style = match self.grid.state_at(r, c) {
                    None => RGBColor(40, 40, 40).filled(),
                    Some(s) => ViridisRGB.get_color_normalized(shade[s], 0.0, hi).filled(),
                };
                let corners = [
                    (c as f64, rows - r as f64),
                    (c as f64 + 1.0, rows - r as f64 - 1.0),
                ];
                cells.push(Rectangle::new(corners, style));
            }
        }
        ctx.draw_series(cells)?;
        let label_style = (FONT, 20)
            .into_font()
            .style(FontStyle::Bold)
            .color(&RED)
            .pos(Pos::new(HPos::Center, VPos::Center));
        ctx.draw_series(self.marks.iter().map(|&(mark, s)| {
            let (r, c) = self.grid.cell_of(s);
            Text::new(
                mark.to_string(),
                (c as f64 + 0.5, rows - r as f64 - 0.5),
                label_style.clone(),
            )
        }))?;
        Ok(())
    }
}

/// Draws Fig. 4(j)-(m) of Experiment 3 into `out`; returns the files.
///
/// (j) ε of the active module over time (one run and the mean); (k)
/// cumulative |r|, EM+IM vs EM-only (mean ± sd); (l) cumulative stimulus per
/// dimension of EM+IM (mean ± sd); (m) the occupancy of the map in run 1
/// during each period between module freezes (the module learned in it).
pub fn draw_curiosity(
    room: &Room,
    grouped: &[(&'static str, Vec<CuriosityRecord>)],
    out: &Path,
) -> Result<Vec<PathBuf>> {
    let find = |name: &str| {
        grouped
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, r)| r.as_slice())
            .filter(|r| !r.is_empty())
            .ok_or_else(|| anyhow!("no trials of {name}"))
    };
    let im = find("em_im")?;
    let em = find("em_only")?;
    let mut files = Vec::new();

    let eps: Vec<Vec<f64>> = im.iter().map(|r| r.epsilon.clone()).collect();
    let (mean_eps, _) = mean_sd(&eps);
    let fig_j = LineChart {
        title: "Fig. 4(j) Curiosity room: estimation error of the active module".into(),
        x_label: "tick".into(),
        y_label: "estimation error ε (a fresh, unfed module reads 1)".into(),
        series: vec![
            line("run 1", PALETTE[0], 1, &eps[0]),
            line(
                format!("mean of {} runs", eps.len()),
                PALETTE[1],
                2,
                &mean_eps,
            ),
        ],
    };
    files.extend(save(&fig_j, out, "fig4j_estimation_error", SIZE)?);

    let abs_r = |r: &CuriosityRecord| cumsum(r.base.abs_reward.iter().copied());
    let fig_k = LineChart {
        title: "Fig. 4(k) Curiosity room: cumulative |r|".into(),
        x_label: "tick".into(),
        y_label: "cumulative |r|".into(),
        series: vec![
            mean_band(
                "EM+IM",
                PALETTE[0],
                &im.iter().map(abs_r).collect::<Vec<_>>(),
            ),
            mean_band(
                "EM only",
                PALETTE[1],
                &em.iter().map(abs_r).collect::<Vec<_>>(),
            ),
        ],
    };
    files.extend(save(&fig_k, out, "fig4k_cumulative_reward", SIZE)?);

    let series = STIMULI
        .iter()
        .enumerate()
        .map(|(j, name)| {
            let cum: Vec<Vec<f64>> = im
                .iter()
                .map(|r| cumsum(component(&r.base, j, &r.base.stimulus, r.base.dims).into_iter()))
                .collect();
            mean_band(name, PALETTE[j % PALETTE.len()], &cum)
        })
        .collect();
    let fig_l = LineChart {
        title: "Fig. 4(l) Curiosity room: cumulative stimulus per dimension (EM+IM)".into(),
        x_label: "tick".into(),
        y_label: "cumulative stimulus".into(),
        series,
    };
    files.extend(save(&fig_l, out, "fig4l_cumulative_stimulus", SIZE)?);

    let run = &im[0];
    let marks = vec![
        ('F', room.food),
        ('R', room.rest),
        ('K', room.book),
        ('M', room.music),
    ];
    let steps = run.base.steps();
    let mut bounds: Vec<(usize, usize, Option<usize>)> = Vec::new();
    let mut from = 0;
    for &(tick, source) in &run.freezes {
        bounds.push((from, tick as usize, Some(source)));
        from = tick as usize;
    }
    bounds.push((from, steps, None));
    let size = (
        room.grid.cols() as u32 * 34 + 24,
        room.grid.rows() as u32 * 34 + 60,
    );
    for (i, &(a, b, source)) in bounds.iter().enumerate() {
        let mut visits = vec![0.0; room.grid.states()];
        for &s in &run.base.states[a..b] {
            visits[s as usize] += 1.0;
        }
        let what = match source {
            Some(0) => format!("module {} learns the book (K)", i + 1),
            Some(_) => format!("module {} learns the music (M)", i + 1),
            None => "after the last freeze".to_string(),
        };
        let fig = OccupancyMap {
            title: format!("Fig. 4(m) run 1, ticks {}-{b}: {what}", a + 1),
            grid: &room.grid,
            visits,
            marks: marks.clone(),
        };
        files.extend(save(
            &fig,
            out,
            &format!("fig4m_occupancy_{}", i + 1),
            size,
        )?);
    }
    Ok(files)
}
