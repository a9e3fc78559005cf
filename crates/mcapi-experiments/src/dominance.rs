//! Which drive component dominates, with hysteresis: the drive switches the
//! experiments count and the paper's figures mark.

/// Hysteresis of drive switches: the dominant component changes to j only
/// when |d_j| >= SWITCH_RATIO |d_current|.
pub const SWITCH_RATIO: f64 = 1.5;

/// Tracks the dominant drive component with hysteresis.
#[derive(Debug, Clone)]
pub struct DominanceTracker {
    current: usize,
    ticks: u64,
    since: u64,
    /// (tick, new dominant component) of every switch.
    switches: Vec<(u64, usize)>,
}

fn argmax_abs(d: &[f64]) -> usize {
    (0..d.len())
        .max_by(|&a, &b| d[a].abs().total_cmp(&d[b].abs()).then(b.cmp(&a)))
        .unwrap_or(0)
}

impl DominanceTracker {
    /// Starts with the largest |d_j| of the initial drive as dominant.
    pub fn new(d0: &[f64]) -> Self {
        Self {
            current: argmax_abs(d0),
            ticks: 0,
            since: 0,
            switches: Vec::new(),
        }
    }

    /// Feeds the drive after one more tick.
    pub fn observe(&mut self, d: &[f64]) {
        self.ticks += 1;
        let threshold = SWITCH_RATIO * d[self.current].abs();
        let best = argmax_abs(d);
        if best != self.current && d[best].abs() >= threshold {
            self.current = best;
            self.since = self.ticks;
            self.switches.push((self.ticks, best));
        }
    }

    /// The dominant component.
    pub fn current(&self) -> usize {
        self.current
    }

    /// Ticks the current component has dominated.
    pub fn held(&self) -> u64 {
        self.ticks - self.since
    }

    /// Every switch as (tick, new component).
    pub fn switches(&self) -> &[(u64, usize)] {
        &self.switches
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hysteresis_ignores_small_leads() {
        let mut t = DominanceTracker::new(&[0.8, 0.6]);
        t.observe(&[0.6, 0.8]); // 0.8 < 1.5 * 0.6
        assert_eq!(t.current(), 0);
        t.observe(&[0.5, 0.86]); // 0.86 >= 0.75
        assert_eq!(t.current(), 1);
        assert_eq!(t.switches(), &[(2, 1)]);
        t.observe(&[-0.9, 0.3]); // signs do not matter
        assert_eq!(t.switches(), &[(2, 1), (3, 0)]);
        assert_eq!(t.held(), 0);
    }
}
