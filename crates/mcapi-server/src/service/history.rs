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
    /// D, then the stimulus if there was one, then the known fraction of a
    /// learned model (docs/algorithm.md §8) if [`KNOWN_FLAG`] is set.
    values: Box<[f64]>,
    /// Components of D in `values`, and [`KNOWN_FLAG`].
    drive_len: u32,
    /// What only some sessions have, boxed so the others pay one pointer.
    extra: Option<Box<Extra>>,
}

/// The part of a tick only some sessions have.
#[derive(Debug, Clone, PartialEq)]
enum Extra {
    /// A curious session's channel.
    Curiosity(TickCuriosity),
    /// A continuous world's observation.
    Observation(Box<[f64]>),
}

/// Set in `RingTick::drive_len` when the last of `values` is the known
/// fraction of a learned model (D has at most a few dozen components).
const KNOWN_FLAG: u32 = 1 << 31;

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
        known_fraction: Option<f64>,
    ) -> Self {
        let stimulus = stimulus.into_iter().flatten().copied();
        let flag = if known_fraction.is_some() {
            KNOWN_FLAG
        } else {
            0
        };
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
                .chain(known_fraction)
                .collect(),
            drive_len: (index32(drive.len()) & !KNOWN_FLAG) | flag,
            extra: curiosity.map(|c| Box::new(Extra::Curiosity(c))),
        }
    }

    /// This tick with a continuous world's observation (such a session
    /// has no curiosity channel).
    pub fn with_observation(mut self, observation: &[f64]) -> Self {
        self.extra = Some(Box::new(Extra::Observation(observation.into())));
        self
    }

    /// The known fraction of a learned model after this tick.
    pub fn known_fraction(&self) -> Option<f64> {
        (self.drive_len & KNOWN_FLAG != 0)
            .then(|| self.values.last().copied())
            .flatten()
    }

    /// This tick with the known fraction a snapshot kept for it (a
    /// [`TickRecord`] does not hold it; a learned snapshot keeps it aside).
    pub fn with_known_fraction(self, known_fraction: Option<f64>) -> Self {
        let e = self.entry();
        Self::new(
            e.tick,
            e.state,
            e.action,
            &e.drive,
            e.stimulus.as_deref(),
            None,
            e.reward,
            e.lstdq_error,
            e.curiosity,
            known_fraction,
        )
    }

    /// The entry readers get.
    pub fn entry(&self) -> HistoryEntry {
        let known_fraction = self.known_fraction();
        let end = self.values.len() - usize::from(known_fraction.is_some());
        let (drive, stimulus) =
            self.values[..end].split_at(((self.drive_len & !KNOWN_FLAG) as usize).min(end));
        HistoryEntry {
            tick: self.tick,
            state: self.state as usize,
            action: self.action as usize,
            drive: drive.to_vec(),
            reward: self.reward,
            lstdq_error: self.lstdq_error,
            stimulus: (!stimulus.is_empty()).then(|| stimulus.to_vec()),
            curiosity: match self.extra.as_deref() {
                Some(Extra::Curiosity(c)) => Some(*c),
                Some(Extra::Observation(_)) | None => None,
            },
            known_fraction,
            observation: match self.extra.as_deref() {
                Some(Extra::Observation(x)) => Some(x.to_vec()),
                Some(Extra::Curiosity(_)) | None => None,
            },
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
            None,
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
            // Kept aside by a learned snapshot (`LearnedRecord`).
            known_fraction: _,
            // A continuous world's session takes no snapshot: its log is
            // replayed whole.
            observation: _,
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
///
/// The ring is lazy and sized by use: it allocates nothing until its first
/// tick (an idle session pays nothing for it), then grows by doubling as a
/// `VecDeque` does, but never past `cap` (`history: 300` keeps room for
/// 300 ticks, not the 512 plain doubling would reserve).
pub fn push_tick(ring: &mut VecDeque<RingTick>, cap: usize, tick: RingTick) {
    if cap == 0 {
        return;
    }
    if ring.len() >= cap {
        ring.pop_front();
    } else if ring.len() == ring.capacity() {
        let want = ring.capacity().saturating_mul(2).max(4).min(cap);
        ring.reserve_exact(want - ring.len());
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
            None,
        );
        let e = curious.entry();
        assert_eq!(e.drive, vec![0.6, 0.0, 0.8]);
        assert_eq!(e.stimulus, Some(vec![1.0, 0.0, 2.5]));
        assert_eq!((e.tick, e.state, e.action), (7, 3, 2));
        assert_eq!(RingTick::from(&TickRecord::from(&curious)), curious);
        // A tick restored from a format-2 snapshot has no stimulus.
        let old = RingTick::new(7, 3, 2, &[0.6, 0.8], None, None, 0.25, 0.125, None, None);
        assert_eq!(old.entry().stimulus, None);
        assert_eq!(RingTick::from(&TickRecord::from(&old)), old);
        // A learned model's known fraction rides in the same allocation.
        let learned = RingTick::new(
            9,
            1,
            0,
            &[0.6, 0.8],
            Some(&[0.0, 1.0]),
            None,
            0.5,
            0.0,
            None,
            Some(0.375),
        );
        assert!(std::mem::size_of::<RingTick>() <= 64);
        let e = learned.entry();
        assert_eq!(
            (e.drive, e.stimulus),
            (vec![0.6, 0.8], Some(vec![0.0, 1.0]))
        );
        assert_eq!(e.known_fraction, Some(0.375));
        let back = RingTick::from(&TickRecord::from(&learned));
        assert_eq!(back.known_fraction(), None, "a TickRecord does not keep it");
        assert_eq!(back.with_known_fraction(Some(0.375)), learned);
        // A continuous world's observation shares the curiosity box.
        let continuous = RingTick::new(
            4,
            0,
            1,
            &[0.6, 0.8],
            Some(&[1.0, 0.0]),
            None,
            0.5,
            0.0,
            None,
            None,
        )
        .with_observation(&[0.25, -3.0]);
        assert!(std::mem::size_of::<RingTick>() <= 64);
        let e = continuous.entry();
        assert_eq!(e.observation, Some(vec![0.25, -3.0]));
        assert_eq!(e.curiosity, None);
        assert_eq!(curious.entry().observation, None);
    }

    #[test]
    fn the_ring_is_lazy_and_never_reserves_past_its_length() {
        let tick =
            |t: u64| RingTick::new(t, 0, 0, &[1.0], Some(&[0.0]), None, 0.0, 0.0, None, None);
        let mut ring = VecDeque::new();
        assert_eq!(
            ring.capacity(),
            0,
            "nothing allocated before the first tick"
        );
        push_tick(&mut ring, 0, tick(0));
        assert_eq!(ring.capacity(), 0, "history 0 keeps nothing");
        push_tick(&mut ring, 300, tick(0));
        assert!(ring.capacity() <= 4, "a first tick reserves a little");
        for t in 1..1000 {
            push_tick(&mut ring, 300, tick(t));
            assert!(
                ring.capacity() <= 300,
                "capacity {} at tick {t}",
                ring.capacity()
            );
        }
        assert_eq!(ring.len(), 300);
        assert_eq!(ring.front().map(|t| t.tick), Some(700));
        assert_eq!(ring.back().map(|t| t.tick), Some(999));
        // A short ring stays short.
        let mut short = VecDeque::new();
        for t in 0..10 {
            push_tick(&mut short, 3, tick(t));
        }
        assert_eq!(short.len(), 3);
        assert!(short.capacity() <= 3);
    }
}
