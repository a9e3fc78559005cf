//! Figures of the continuous experiments, with the discrete experiments'
//! charts: cumulative |r| (mean ± sd, MCA-PI against the random walk),
//! cumulative stimulus per source, the drive of the first trial, and its
//! coordinates over time (the trajectory: x for the hallway, x and y for
//! the three-room).

use std::path::{Path, PathBuf};

use anyhow::Result;

use super::ContinuousTrial;
use crate::plots::{LineChart, PALETTE, SIZE, cumsum, line, mean_band, save};

/// Ticks shown in the single-run panels.
const WINDOW: usize = 2000;

/// Draws every figure into `out`; returns the files written.
pub fn draw(
    name: &str,
    stimuli: &[String],
    mca: &[ContinuousTrial],
    random: &[ContinuousTrial],
    out: &Path,
) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    let Some(first) = mca.first() else {
        return Ok(files);
    };
    let cum_r = |t: &ContinuousTrial| cumsum(t.abs_reward.iter().copied());
    let fig = LineChart {
        title: format!("{name}: cumulative |r|"),
        x_label: "tick".into(),
        y_label: "cumulative |r|".into(),
        series: vec![
            mean_band(
                "MCA-PI",
                PALETTE[0],
                &mca.iter().map(cum_r).collect::<Vec<_>>(),
            ),
            mean_band(
                "random walk",
                PALETTE[1],
                &random.iter().map(cum_r).collect::<Vec<_>>(),
            ),
        ],
    };
    files.extend(save(&fig, out, "cumulative_reward", SIZE)?);

    let n = first.dims;
    let per_source = |j: usize| {
        mca.iter()
            .map(|t| cumsum(t.stimulus.iter().skip(j).step_by(n).copied()))
            .collect::<Vec<_>>()
    };
    let fig = LineChart {
        title: format!("{name}: cumulative stimulus per source (MCA-PI)"),
        x_label: "tick".into(),
        y_label: "cumulative stimulus".into(),
        series: (0..n)
            .map(|j| mean_band(&stimuli[j], PALETTE[j % PALETTE.len()], &per_source(j)))
            .collect(),
    };
    files.extend(save(&fig, out, "cumulative_stimulus", SIZE)?);

    let window = first.abs_reward.len().min(WINDOW);
    let component = |data: &[f64], width: usize, j: usize| -> Vec<f64> {
        data.iter()
            .skip(j)
            .step_by(width)
            .take(window)
            .copied()
            .collect()
    };
    let fig = LineChart {
        title: format!("{name}: the drive D, first trial, first {window} ticks"),
        x_label: "tick".into(),
        y_label: "D".into(),
        series: (0..n)
            .map(|j| {
                line(
                    format!("D[{}]", stimuli[j]),
                    PALETTE[j % PALETTE.len()],
                    2,
                    &component(&first.drive, n, j),
                )
            })
            .collect(),
    };
    files.extend(save(&fig, out, "drive", SIZE)?);

    let axes = ["x", "y", "z"];
    let fig = LineChart {
        title: format!("{name}: the trajectory, first trial, first {window} ticks"),
        x_label: "tick".into(),
        y_label: "coordinate".into(),
        series: (0..first.d.min(axes.len()))
            .map(|j| {
                line(
                    axes[j],
                    PALETTE[j % PALETTE.len()],
                    2,
                    &component(&first.points, first.d, j),
                )
            })
            .collect(),
    };
    files.extend(save(&fig, out, "trajectory", SIZE)?);
    Ok(files)
}
