//! The history ring of a session: its recent ticks (drive, reward, state,
//! LSTDQ error, curiosity), compact in memory, as the API shows them
//! ([`HistoryEntry`]) and as a snapshot keeps them ([`TickRecord`]).

use std::collections::VecDeque;

use super::durable::TickRecord;
use super::wire::{HistoryEntry, TickCuriosity};

/// One tick of the history ring as kept in memory: D and the stimulus in
/// one allocation and the curiosity part boxed (plain sessions have none),
/// so a full ring costs about what it did before ticks kept their stimulus.
/// [`HistoryEntry`] is what readers get, [`TickRecord`] what snapshots keep.
#[derive(Debug, Clone, PartialEq)]
pub struct RingTick {
    tick: u64,
    state: u32,
    action: u32,
    reward: f64,
    lstdq_error: f64,
    /// D, then the stimulus if there was one.
    values: Box<[f64]>,
    /// Components of D in `values`.
    drive_len: u32,
    curiosity: Option<Box<TickCuriosity>>,
}

/// State and action indices fit u32: the model indexes pairs with u32.
fn index32(i: usize) -> u32 {
    u32::try_from(i).unwrap_or(u32::MAX)
}

impl RingTick {
    /// A tick from its parts: D, the stimulus the client sent and, for a
    /// curious session, the ξ_cur the server appended to it.
    #[expect(
        clippy::too_many_arguments,
        reason = "one call site per path (live, replayed), every argument named there"
    )]
    pub fn new(
        tick: u64,
        state: usize,
        action: usize,
        drive: &[f64],
        stimulus: Option<&[f64]>,
        xi_cur: Option<f64>,
        reward: f64,
        lstdq_error: f64,
        curiosity: Option<TickCuriosity>,
    ) -> Self {
        let stimulus = stimulus.into_iter().flatten().copied();
        Self {
            tick,
            state: index32(state),
            action: index32(action),
            reward,
            lstdq_error,
            values: drive
                .iter()
                .copied()
                .chain(stimulus)
                .chain(xi_cur)
                .collect(),
            drive_len: index32(drive.len()),
            curiosity: curiosity.map(Box::new),
        }
    }

    /// The entry readers get.
    pub fn entry(&self) -> HistoryEntry {
        let (drive, stimulus) = self.values.split_at(self.drive_len as usize);
        HistoryEntry {
            tick: self.tick,
            state: self.state as usize,
            action: self.action as usize,
            drive: drive.to_vec(),
            reward: self.reward,
            lstdq_error: self.lstdq_error,
            stimulus: (!stimulus.is_empty()).then(|| stimulus.to_vec()),
            curiosity: self.curiosity.as_deref().copied(),
        }
    }
}

impl From<&TickRecord> for RingTick {
    fn from(t: &TickRecord) -> Self {
        Self::new(
            t.tick,
            t.state,
            t.action,
            &t.drive,
            t.stimulus.as_deref(),
            None,
            t.reward,
            t.lstdq_error,
            t.curiosity,
        )
    }
}

impl From<&RingTick> for TickRecord {
    fn from(t: &RingTick) -> Self {
        let HistoryEntry {
            tick,
            state,
            action,
            drive,
            reward,
            lstdq_error,
            stimulus,
            curiosity,
        } = t.entry();
        Self {
            tick,
            state,
            action,
            drive,
            reward,
            lstdq_error,
            stimulus,
            curiosity,
        }
    }
}

/// Appends a tick to a history ring of capacity `cap` (none kept at 0),
/// dropping the oldest when full: the live and the replayed path.
pub fn push_tick(ring: &mut VecDeque<RingTick>, cap: usize, tick: RingTick) {
    if cap == 0 {
        return;
    }
    if ring.len() >= cap {
        ring.pop_front();
    }
    ring.push_back(tick);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ring_ticks_are_compact_and_give_back_their_entries() {
        // D and ξ in one allocation; the curiosity part boxed.
        assert!(std::mem::size_of::<RingTick>() <= 64);
        let curious = RingTick::new(
            7,
            3,
            2,
            &[0.6, 0.0, 0.8],
            Some(&[1.0, 0.0]),
            Some(2.5),
            0.25,
            0.125,
            Some(TickCuriosity {
                xi_cur: 2.5,
                epsilon: 0.9,
                modules: 1,
                source: Some(0),
            }),
        );
        let e = curious.entry();
        assert_eq!(e.drive, vec![0.6, 0.0, 0.8]);
        assert_eq!(e.stimulus, Some(vec![1.0, 0.0, 2.5]));
        assert_eq!((e.tick, e.state, e.action), (7, 3, 2));
        assert_eq!(RingTick::from(&TickRecord::from(&curious)), curious);
        // A tick restored from a format-2 snapshot has no stimulus.
        let old = RingTick::new(7, 3, 2, &[0.6, 0.8], None, None, 0.25, 0.125, None);
        assert_eq!(old.entry().stimulus, None);
        assert_eq!(RingTick::from(&TickRecord::from(&old)), old);
    }
}
