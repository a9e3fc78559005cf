//! The history ring of a session: its recent ticks (drive, reward, state,
//! LSTDQ error, curiosity), compact in memory, as the API shows them
//! ([`HistoryEntry`]) and as a snapshot keeps them ([`TickRecord`]).
//!
//! The ring is also the window of exactly-once delivery (docs/sessions.md,
//! "Delivery guarantees"): each entry keeps everything its reply carried
//! (the policy version besides what the history shows) and a digest of the
//! observation that made it, so an observation sent again with its `seq`
//! is answered with the recorded reply, and one whose content differs is
//! told apart. A session's first observation carries no stimulus and is no
//! tick; its entry rides in the ring too (history reads skip it) until a
//! tick pushes it out, so seq 0 is replayable while it is in the window.

use std::collections::VecDeque;

use super::durable::TickRecord;
use super::wire::{HistoryEntry, ObservationIn, StepOut, TickCuriosity};
use mcapi_core::spec::ActionRef;

/// One tick of the history ring as kept in memory: D and the stimulus in
/// the entry itself as far as they fit ([`Values`]), the curiosity part boxed
/// (plain sessions have none). [`HistoryEntry`] is what readers get,
/// [`TickRecord`] what snapshots keep.
#[derive(Debug, Clone, PartialEq)]
pub struct RingTick {
    tick: u64,
    state: u32,
    action: u32,
    reward: f64,
    lstdq_error: f64,
    /// D, then the stimulus if there was one, then the known fraction of a
    /// learned model (docs/algorithm.md §8) if [`KNOWN_FLAG`] is set.
    values: Values,
    /// How many of `values` are in its head.
    head_len: u8,
    /// Components of D in `values`, and [`KNOWN_FLAG`], [`FIRST_FLAG`],
    /// [`REPLAYABLE_FLAG`].
    drive_len: u32,
    /// What only some sessions have, boxed so the others pay one pointer.
    extra: Option<Box<Extra>>,
    /// The policy version the reply reported (valid with
    /// [`REPLAYABLE_FLAG`]).
    policy_version: u64,
    /// [`digest`] of the observation; 0 when unknown (an entry rebuilt
    /// from a log written before digests were kept), which any content
    /// matches.
    digest: u64,
}

/// The numbers of a tick (D, the stimulus, the known fraction): the first
/// [`HEAD`] in the entry, the rest, if any, in an allocation of their own.
/// A session of one or two stimuli (D and ξ are at most four numbers) then
/// allocates nothing per tick, and frees nothing when its ring drops its
/// oldest tick (a free that reached memory as cold as the tick it freed);
/// one of three or more allocates as before, for four numbers fewer. The
/// entry is 32 bytes larger than with all of them behind a pointer, what
/// an allocation of four numbers took: a ring of two or more stimuli is
/// no larger than it was, one of a single stimulus 16 bytes a tick larger.
#[derive(Debug, Clone, PartialEq)]
struct Values {
    /// The first numbers; `RingTick::head_len` of them are used, the
    /// others are 0.
    head: [f64; HEAD],
    /// The numbers after the first [`HEAD`].
    tail: Option<Box<[f64]>>,
}

/// Numbers a tick keeps in its entry: D and ξ of two stimuli.
const HEAD: usize = 4;

impl Values {
    /// The numbers, and how many of them are in the head.
    fn new(mut values: impl Iterator<Item = f64>) -> (Self, u8) {
        let mut head = [0.0; HEAD];
        let mut len = 0;
        for slot in &mut head {
            let Some(x) = values.next() else { break };
            *slot = x;
            len += 1;
        }
        let tail: Box<[f64]> = values.collect();
        let tail = (!tail.is_empty()).then_some(tail);
        (Self { head, tail }, len)
    }
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

/// Set in `RingTick::drive_len` for the entry of a session's first
/// observation: not a tick (no stimulus), kept only so that seq 0 can be
/// replayed; history reads skip it.
const FIRST_FLAG: u32 = 1 << 30;

/// Set in `RingTick::drive_len` when the entry holds its whole reply (its
/// policy version): entries restored from a snapshot written before
/// sequence numbers do not, and cannot be replayed.
const REPLAYABLE_FLAG: u32 = 1 << 29;

/// The flags of `RingTick::drive_len`.
const FLAGS: u32 = KNOWN_FLAG | FIRST_FLAG | REPLAYABLE_FLAG;

/// A 64-bit FNV-1a digest of an observation's content (state or
/// observation vector, stimulus, action taken, signal and its source; not
/// `seq`), over the f64 bits, so a resent observation can be told from a
/// different one with the same seq (`seq_conflict`). Fast, no dependency,
/// not cryptographic: it guards against client mistakes, not forgery (a
/// client can only conflict with its own session). Never 0, which stands
/// for "unknown".
pub fn digest(obs: &ObservationIn) -> u64 {
    const PRIME: u64 = 0x0000_0100_0000_01b3;
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut eat = |x: u64| {
        for b in x.to_le_bytes() {
            h = (h ^ u64::from(b)).wrapping_mul(PRIME);
        }
    };
    // Each field is tagged and length-prefixed, so no two different
    // observations feed the same words.
    let numbers = |tag: u64, xs: Option<&[f64]>, eat: &mut dyn FnMut(u64)| match xs {
        None => eat(tag),
        Some(xs) => {
            eat(tag | 1 << 32);
            eat(xs.len() as u64);
            for x in xs {
                eat(x.to_bits());
            }
        }
    };
    match obs.state {
        None => eat(1),
        Some(s) => {
            eat(2);
            eat(s as u64);
        }
    }
    numbers(3, obs.observation.as_deref(), &mut eat);
    numbers(4, obs.stimulus.as_deref(), &mut eat);
    match &obs.action_taken {
        None => eat(5),
        Some(ActionRef::Index(a)) => {
            eat(6);
            eat(*a as u64);
        }
        Some(ActionRef::Name(name)) => {
            eat(7);
            eat(name.len() as u64);
            for b in name.bytes() {
                eat(u64::from(b));
            }
        }
    }
    numbers(8, obs.signal.as_deref(), &mut eat);
    match obs.signal_source {
        None => eat(9),
        Some(s) => {
            eat(10);
            eat(s as u64);
        }
    }
    h.max(1)
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
        known_fraction: Option<f64>,
    ) -> Self {
        let stimulus = stimulus.into_iter().flatten().copied();
        let (values, head_len) = Values::new(
            drive
                .iter()
                .copied()
                .chain(stimulus)
                .chain(xi_cur)
                .chain(known_fraction),
        );
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
            values,
            head_len,
            drive_len: (index32(drive.len()) & !FLAGS) | flag,
            extra: curiosity.map(|c| Box::new(Extra::Curiosity(c))),
            policy_version: 0,
            digest: 0,
        }
    }

    /// This entry with the rest of its reply and its observation's
    /// [`digest`] (0: unknown): it can then be replayed.
    pub fn with_reply(mut self, policy_version: u64, digest: u64) -> Self {
        self.policy_version = policy_version;
        self.digest = digest;
        self.drive_len |= REPLAYABLE_FLAG;
        self
    }

    /// This entry as the one of a session's first observation (not a
    /// tick: history reads skip it).
    pub fn as_first(mut self) -> Self {
        self.drive_len |= FIRST_FLAG;
        self
    }

    /// Whether this is the entry of a session's first observation.
    pub fn is_first(&self) -> bool {
        self.drive_len & FIRST_FLAG != 0
    }

    /// The seq of the observation that made this entry: its tick (the
    /// first observation, seq 0, has tick 0; every later one is a tick).
    pub fn seq(&self) -> u64 {
        self.tick
    }

    /// The reply as it was sent, marked `replayed`; `None` if this entry
    /// does not hold it all.
    pub fn replay(&self, actions: &[String]) -> Option<StepOut> {
        if self.drive_len & REPLAYABLE_FLAG == 0 {
            return None;
        }
        let e = self.entry();
        Some(StepOut {
            tick: e.tick,
            action: actions.get(e.action)?.clone(),
            action_index: e.action,
            drive: e.drive,
            reward: e.reward,
            policy_version: self.policy_version,
            curiosity: e.curiosity,
            replayed: true,
        })
    }

    /// Whether `digest` is the digest of this entry's observation (or the
    /// entry does not know its own).
    pub fn matches(&self, digest: u64) -> bool {
        self.digest == 0 || self.digest == digest
    }

    /// The policy version and digest, if this entry is replayable.
    pub fn reply(&self) -> Option<(u64, u64)> {
        (self.drive_len & REPLAYABLE_FLAG != 0).then_some((self.policy_version, self.digest))
    }

    /// This tick with a continuous world's observation (such a session
    /// has no curiosity channel).
    pub fn with_observation(mut self, observation: &[f64]) -> Self {
        self.extra = Some(Box::new(Extra::Observation(observation.into())));
        self
    }

    /// A continuous world's observation that made this tick.
    pub fn observation(&self) -> Option<&[f64]> {
        match self.extra.as_deref() {
            Some(Extra::Observation(x)) => Some(x),
            Some(Extra::Curiosity(_)) | None => None,
        }
    }

    /// The known fraction of a learned model after this tick.
    pub fn known_fraction(&self) -> Option<f64> {
        (self.drive_len & KNOWN_FLAG != 0)
            .then(|| self.numbers().0.last())
            .flatten()
    }

    /// This tick with the known fraction a snapshot kept for it (a
    /// [`TickRecord`] does not hold it; a learned snapshot keeps it aside).
    pub fn with_known_fraction(self, known_fraction: Option<f64>) -> Self {
        let e = self.entry();
        let flags = self.drive_len & (FIRST_FLAG | REPLAYABLE_FLAG);
        let mut tick = Self::new(
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
        );
        tick.drive_len |= flags;
        tick.policy_version = self.policy_version;
        tick.digest = self.digest;
        tick
    }

    /// D, the stimulus and the known fraction, in order, and how many.
    fn numbers(&self) -> (impl Iterator<Item = f64> + Clone + '_, usize) {
        let head = &self.values.head[..usize::from(self.head_len)];
        let tail = self.values.tail.as_deref().unwrap_or_default();
        (head.iter().chain(tail).copied(), head.len() + tail.len())
    }

    /// The entry readers get.
    pub fn entry(&self) -> HistoryEntry {
        let known_fraction = self.known_fraction();
        let (numbers, len) = self.numbers();
        let end = len - usize::from(known_fraction.is_some());
        let d = ((self.drive_len & !FLAGS) as usize).min(end);
        let drive: Vec<f64> = numbers.clone().take(d).collect();
        let stimulus: Vec<f64> = numbers.skip(d).take(end - d).collect();
        HistoryEntry {
            tick: self.tick,
            state: self.state as usize,
            action: self.action as usize,
            drive,
            reward: self.reward,
            lstdq_error: self.lstdq_error,
            stimulus: (!stimulus.is_empty()).then_some(stimulus),
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
        let tick = Self::new(
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
        );
        let tick = match t.reply {
            Some((policy_version, digest)) => tick.with_reply(policy_version, digest),
            None => tick,
        };
        if t.first { tick.as_first() } else { tick }
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
            // Kept aside by a continuous snapshot (`ContinuousRecord`).
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
            reply: t.reply(),
            first: t.is_first(),
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
    push_tick_from(ring, cap, RING_FIRST, tick);
}

/// Room for this many ticks is what a ring reserves at its first tick.
pub const RING_FIRST: usize = 4;

/// [`push_tick`] with the first reservation `first` (at least one tick):
/// the ring then doubles from there. Rings grown in lockstep (a group's
/// members, stepped together) would all copy themselves into fresh memory
/// at the same tick, each doubling a step in which the group waits; first
/// reservations that differ ([`group_ring_first`]) spread the doublings
/// over several ticks.
pub fn push_tick_from(ring: &mut VecDeque<RingTick>, cap: usize, first: usize, tick: RingTick) {
    if cap == 0 {
        return;
    }
    if ring.len() >= cap {
        ring.pop_front();
    } else if ring.len() == ring.capacity() {
        let want = ring.capacity().saturating_mul(2).max(first.max(1)).min(cap);
        ring.reserve_exact(want - ring.len());
    }
    ring.push_back(tick);
}

/// The first reservation of the ring of member `index` of a group of
/// `size`: 8 to 15 ticks, spread over the members, so that the rings of
/// eight cohorts double at eight different ticks (at 8-15, 16-30, ..., the
/// last to 256 at 128-240 ticks) instead of all at once.
pub fn group_ring_first(index: u32, size: u32) -> usize {
    8 + usize::try_from(super::membership::spread(index, size, 8)).unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn four_numbers_stay_in_the_entry_and_the_rest_are_given_back_in_order() {
        let tick = |drive: &[f64], stimulus: Option<&[f64]>, known: Option<f64>| {
            RingTick::new(1, 2, 0, drive, stimulus, None, 0.5, 0.0, None, known)
        };
        // Two stimuli: D and ξ are four numbers, all in the entry.
        let two = tick(&[0.6, 0.8], Some(&[1.0, -2.0]), None);
        assert_eq!((two.head_len, two.values.tail.is_none()), (4, true));
        let e = two.entry();
        assert_eq!(
            (e.drive, e.stimulus),
            (vec![0.6, 0.8], Some(vec![1.0, -2.0]))
        );
        // The first observation has no stimulus.
        let first = tick(&[0.6, 0.8], None, None);
        assert_eq!((first.head_len, first.values.tail.is_none()), (2, true));
        assert_eq!(first.entry().stimulus, None);
        // Three stimuli: four numbers in the entry, two after them.
        let three = tick(&[0.0, 0.6, 0.8], Some(&[1.0, 2.0, 3.0]), None);
        assert_eq!(three.head_len, 4);
        assert_eq!(three.values.tail.as_deref(), Some(&[2.0, 3.0][..]));
        let e = three.entry();
        assert_eq!(e.drive, vec![0.0, 0.6, 0.8]);
        assert_eq!(e.stimulus, Some(vec![1.0, 2.0, 3.0]));
        // A learned model's known fraction, the last number, beyond the head.
        let learned = tick(&[0.6, 0.8], Some(&[1.0, -2.0]), Some(0.25));
        assert_eq!(learned.values.tail.as_deref(), Some(&[0.25][..]));
        assert_eq!(learned.known_fraction(), Some(0.25));
        assert_eq!(learned.entry().stimulus, Some(vec![1.0, -2.0]));
        assert_eq!(two.known_fraction(), None);
        // Through a snapshot's record and back, the same entries.
        for t in [&two, &first, &three] {
            assert_eq!(*t, RingTick::from(&TickRecord::from(t)));
        }
        assert_ne!(two, first);
    }

    #[test]
    fn ring_ticks_are_compact_and_give_back_their_entries() {
        // Four numbers of D and ξ in the entry, the rest behind a
        // pointer; the curiosity part boxed; the reply's policy version and
        // the observation's digest (exactly-once delivery) 16 bytes.
        assert!(std::mem::size_of::<RingTick>() <= 112);
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
        assert!(std::mem::size_of::<RingTick>() <= 112);
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
        assert!(std::mem::size_of::<RingTick>() <= 112);
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

    #[test]
    fn a_groups_rings_double_at_different_ticks() {
        let tick =
            |t: u64| RingTick::new(t, 0, 0, &[1.0], Some(&[0.0]), None, 0.0, 0.0, None, None);
        // The tick (ring length) at which each member's ring grows.
        let growths = |first: usize| {
            let mut ring = VecDeque::new();
            let mut at = Vec::new();
            for t in 0..400 {
                let before = ring.capacity();
                push_tick_from(&mut ring, 256, first, tick(t));
                if ring.capacity() != before {
                    at.push(t);
                }
                assert!(
                    ring.capacity() <= 256,
                    "member of first {first}: {}",
                    ring.capacity()
                );
            }
            assert_eq!(ring.len(), 256);
            at
        };
        let size = 10_000u32;
        let firsts: Vec<usize> = (0..size).map(|i| group_ring_first(i, size)).collect();
        assert_eq!(firsts.iter().min(), Some(&8));
        assert_eq!(firsts.iter().max(), Some(&15));
        // How many members grow at the busiest tick after the first (where
        // every ring makes its first, small reservation, with nothing to
        // copy).
        let mut per_tick = vec![0u32; 400];
        for &f in &firsts {
            for t in growths(f).into_iter().filter(|&t| t > 0) {
                per_tick[t as usize] += 1;
            }
        }
        let busiest = per_tick.iter().max().copied().unwrap_or(0);
        assert!(
            busiest <= size / 8 + 1,
            "{busiest} members grow in one tick"
        );
        // A lone ring grows as before: 4, 8, 16, ...
        assert_eq!(growths(RING_FIRST), vec![0, 4, 8, 16, 32, 64, 128]);
        // Absurd inputs stay in range.
        assert_eq!(group_ring_first(u32::MAX, u32::MAX), 15);
        assert_eq!(group_ring_first(0, 0), 8);
        assert_eq!(group_ring_first(7, 3), group_ring_first(2, 3));
    }
}
