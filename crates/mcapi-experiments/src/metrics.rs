//! Per-trial metrics and their summary over trials (the `summary.json`
//! contract of the experiments).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::dominance::DominanceTracker;
use super::paper::TrialRecord;

/// Window after which an agent confined to at most two states is "stuck".
pub const STUCK_WINDOW: usize = 1000;

/// mean, sd (sample, n−1), min and max of a metric over trials.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Stat {
    /// Mean.
    pub mean: f64,
    /// Sample standard deviation (0 for one trial).
    pub sd: f64,
    /// Minimum.
    pub min: f64,
    /// Maximum.
    pub max: f64,
}

impl Stat {
    /// Summarises values (which must be non-empty).
    pub fn of(values: &[f64]) -> Self {
        let n = values.len() as f64;
        let mean = values.iter().sum::<f64>() / n;
        let var = if values.len() > 1 {
            values.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / (n - 1.0)
        } else {
            0.0
        };
        Self {
            mean,
            sd: var.sqrt(),
            min: values.iter().copied().fold(f64::INFINITY, f64::min),
            max: values.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        }
    }
}

/// The metrics of one trial, by name.
pub type TrialMetrics = BTreeMap<String, f64>;

/// Cumulative stimulus per dimension at the end of a trial.
pub fn cumulative_stimulus(rec: &TrialRecord) -> Vec<f64> {
    let mut cum = vec![0.0; rec.dims];
    for row in rec.stimulus.chunks_exact(rec.dims) {
        for (c, x) in cum.iter_mut().zip(row) {
            *c += x;
        }
    }
    cum
}

fn median(mut xs: Vec<f64>) -> Option<f64> {
    if xs.is_empty() {
        return None;
    }
    xs.sort_by(f64::total_cmp);
    let m = xs.len() / 2;
    Some(if xs.len() % 2 == 1 {
        xs[m]
    } else {
        0.5 * (xs[m - 1] + xs[m])
    })
}

/// Computes every metric of `summary.json` for one trial.
///
/// Conventions: a tick index is 1-based; "never" is `steps + 1`
/// (`first_switch`, `all_sources_found`, and `period` when no component was
/// entered twice).
pub fn trial_metrics(rec: &TrialRecord, sources: &[usize]) -> TrialMetrics {
    let steps = rec.steps();
    let never = (steps + 1) as f64;
    let mut m = TrialMetrics::new();
    m.insert("cumulative_abs_reward".into(), rec.abs_reward.iter().sum());
    let cum = cumulative_stimulus(rec);
    let hi = cum.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let lo = cum.iter().copied().fold(f64::INFINITY, f64::min);
    m.insert(
        "balance".into(),
        if hi > 0.0 { (lo / hi).max(0.0) } else { 0.0 },
    );
    m.insert("total_stimulus".into(), cum.iter().sum());

    let mut tracker = DominanceTracker::new(&rec.initial_drive);
    for t in 0..steps {
        tracker.observe(rec.drive_at(t));
    }
    let switches = tracker.switches();
    m.insert("switches".into(), switches.len() as f64);
    m.insert(
        "first_switch".into(),
        switches.first().map_or(never, |&(t, _)| t as f64),
    );
    let mut intervals = Vec::new();
    for j in 0..rec.dims {
        let into: Vec<u64> = switches.iter().filter(|s| s.1 == j).map(|s| s.0).collect();
        intervals.extend(into.windows(2).map(|w| (w[1] - w[0]) as f64));
    }
    m.insert("period".into(), median(intervals).unwrap_or(never));

    let mut found = vec![None; sources.len()];
    for (i, &src) in sources.iter().enumerate() {
        if src == rec.start {
            found[i] = Some(0);
        }
    }
    for (t, &s) in rec.states.iter().enumerate() {
        for (i, &src) in sources.iter().enumerate() {
            if found[i].is_none() && s as usize == src {
                found[i] = Some(t + 1);
            }
        }
    }
    let all_found = found
        .iter()
        .try_fold(0usize, |acc, f| f.map(|t| acc.max(t)))
        .map_or(never, |t| t as f64);
    m.insert("all_sources_found".into(), all_found);
    m.insert("stuck".into(), f64::from(u8::from(is_stuck(&rec.states))));
    for (i, &src) in sources.iter().enumerate() {
        let at = rec.states.iter().filter(|&&s| s as usize == src).count();
        m.insert(
            format!("fraction_at_source_{i}"),
            at as f64 / steps.max(1) as f64,
        );
    }
    let err_mean = rec.lstdq_error.iter().sum::<f64>() / steps.max(1) as f64;
    m.insert("lstdq_error_mean".into(), err_mean);
    m.insert("factorisation_reuse".into(), rec.reuse_fraction);
    // How much of the model is known at the end, and from which tick on
    // all of it (docs/algorithm.md §8; 1 and tick 1 for a known model).
    m.insert(
        "model_known".into(),
        rec.known.last().map_or(1.0, |&k| f64::from(k)),
    );
    m.insert(
        "model_known_tick".into(),
        rec.known
            .iter()
            .position(|&k| k >= 1.0)
            .map_or(never, |t| (t + 1) as f64),
    );
    m
}

/// 1 if from some tick t <= steps − 1000 on the agent occupies at most 2
/// distinct states.
pub fn is_stuck(states: &[u32]) -> bool {
    let steps = states.len();
    if steps < STUCK_WINDOW {
        return false;
    }
    // Walk back from the end while the suffix holds at most two states.
    let mut seen: [Option<u32>; 2] = [None, None];
    let mut earliest = steps;
    for (t, &s) in states.iter().enumerate().rev() {
        if seen.contains(&Some(s)) {
            earliest = t;
            continue;
        }
        match seen.iter().position(Option::is_none) {
            Some(i) => {
                seen[i] = Some(s);
                earliest = t;
            }
            None => break,
        }
    }
    // `earliest` is the 0-based index of tick earliest + 1.
    earliest < steps - STUCK_WINDOW
}

/// Summarises per-trial metrics into `{metric: Stat}`.
pub fn summarise(trials: &[TrialMetrics]) -> BTreeMap<String, Stat> {
    let mut out = BTreeMap::new();
    if let Some(first) = trials.first() {
        for key in first.keys() {
            let values: Vec<f64> = trials.iter().filter_map(|t| t.get(key).copied()).collect();
            out.insert(key.clone(), Stat::of(&values));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stuck_needs_a_long_two_state_tail() {
        let mut states: Vec<u32> = (0..500).collect();
        states.extend(std::iter::repeat_n([7u32, 8], 600).flatten());
        assert!(is_stuck(&states), "two states for the last 1200 ticks");
        let mut short: Vec<u32> = (0..1200).collect();
        short.extend(std::iter::repeat_n([7u32, 8], 400).flatten());
        assert!(!is_stuck(&short), "only 800 ticks in two states");
        let three: Vec<u32> = std::iter::repeat_n([1u32, 2, 3], 1000).flatten().collect();
        assert!(!is_stuck(&three));
    }

    #[test]
    fn metrics_of_a_tiny_trial() {
        let rec = TrialRecord {
            dims: 2,
            start: 5,
            initial_drive: vec![1.0, 0.0],
            states: vec![10, 10, 40, 40],
            actions: vec![0; 4],
            drive: vec![1.0, 0.0, 0.9, 0.1, 0.1, 0.9, 0.9, 0.2],
            abs_reward: vec![1.0, 2.0, 3.0, 4.0],
            stimulus: vec![6.0, 0.0, 6.0, 0.0, 0.0, 4.0, 0.0, 8.0],
            lstdq_error: vec![1.0, 1.0, 0.0, 0.0],
            source_values: vec![],
            snapshots: vec![],
            reuse_fraction: 0.5,
            known: vec![0.25, 0.5, 1.0, 1.0],
        };
        let m = trial_metrics(&rec, &[10, 40]);
        assert_eq!(m["cumulative_abs_reward"], 10.0);
        assert_eq!(m["balance"], 1.0);
        assert_eq!(m["total_stimulus"], 24.0);
        assert_eq!(m["switches"], 2.0);
        assert_eq!(m["first_switch"], 3.0);
        assert_eq!(m["period"], 5.0, "no component entered twice");
        assert_eq!(m["all_sources_found"], 3.0);
        assert_eq!(m["fraction_at_source_1"], 0.5);
        assert_eq!(m["lstdq_error_mean"], 0.5);
        assert_eq!(m["model_known"], 1.0);
        assert_eq!(m["model_known_tick"], 3.0);
        let s = Stat::of(&[1.0, 3.0]);
        assert_eq!((s.mean, s.min, s.max), (2.0, 1.0, 3.0));
        assert!((s.sd - 2f64.sqrt()).abs() < 1e-15);
    }
}
