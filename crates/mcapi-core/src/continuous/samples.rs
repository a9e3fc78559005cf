//! The bounded sample store of a continuous world (docs/algorithm.md
//! §9.4): the transitions (s, a, s′) the planner evaluates policies on,
//! and the visit counts that say which (region, action) pairs are known.
//!
//! The box is cut into `cells_per_dim`^d cells (hashed when there are
//! more than fit a u64 key exactly). Each (cell, action) slot keeps its
//! visit count and at most `per_slot` transitions, the newest replacing
//! the oldest and standing for its visits too; the whole store keeps at most `max_samples`, and a full
//! store gives the slot of its oldest transition to the new one. So the
//! store covers what the agent has seen evenly instead of holding the
//! last N ticks, and its size is bounded whatever the agent does.
//!
//! A (cell, action) pair visited fewer than `known_after` times is
//! unknown: the planner treats it optimistically, as the discrete learned
//! model treats an unknown pair (docs/algorithm.md §8, R-max).

use std::collections::HashMap;

use serde::{Deserialize, Serialize};

/// One stored transition; its features live in the store's feature
/// matrices, row for row ([`SampleStore::get`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    /// Normalised s.
    pub s: Vec<f64>,
    /// The action taken.
    pub a: usize,
    /// Normalised s′.
    pub s_next: Vec<f64>,
    /// The mean stimulus ξ of the visits it stands for (what Ξ is refitted
    /// to when the basis is rebuilt).
    pub xi: Vec<f64>,
    /// The slot it lives in.
    slot: (u64, usize),
    /// The tick it was stored at (the oldest goes first when full).
    stored_at: u64,
    /// The visits it stands for: 1, plus the weight of the transition it
    /// replaced in a full slot. A slot's weights sum to its visits, so the
    /// planner weighs the store as it would the whole history.
    pub weight: f64,
}

/// What the planner reads of a stored transition: its action, its weight
/// in visits, and the features v(s) and v(s′).
#[derive(Debug, Clone, Copy)]
pub struct SampleRef<'a> {
    /// The action taken.
    pub a: usize,
    /// The visits it stands for.
    pub weight: f64,
    /// v(s).
    pub v: &'a [f64],
    /// v(s′).
    pub v_next: &'a [f64],
}

/// A transition an insertion replaced, with its features.
#[derive(Debug, Clone, PartialEq)]
pub struct Replaced {
    /// The action taken.
    pub a: usize,
    /// The visits it stood for.
    pub weight: f64,
    /// v(s).
    pub v: Vec<f64>,
    /// v(s′).
    pub v_next: Vec<f64>,
}

impl Replaced {
    /// The planner's view of it.
    pub fn as_ref(&self) -> SampleRef<'_> {
        SampleRef {
            a: self.a,
            weight: self.weight,
            v: &self.v,
            v_next: &self.v_next,
        }
    }
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
struct Slot {
    visits: u64,
    /// Indices into the store, oldest first.
    samples: Vec<usize>,
}

/// What an insertion did: the index written, and the transition it
/// replaced there, if any.
#[derive(Debug)]
pub struct Inserted {
    /// Where the new transition is.
    pub index: usize,
    /// The transition that was at `index` before.
    pub replaced: Option<Replaced>,
}

/// The sample store and the visit counts.
///
/// The features of the stored transitions are kept in two row-major
/// N × k matrices, v(s) and v(s′), so the planner's passes over the store
/// read memory in order (docs/algorithm.md §9.5).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SampleStore {
    d: usize,
    /// Features per point.
    k: usize,
    cells_per_dim: u32,
    per_slot: usize,
    max_samples: usize,
    known_after: u64,
    samples: Vec<Sample>,
    /// v(s_i), row i. Not in a snapshot: recomputed from s_i
    /// ([`SampleStore::restore_features`]).
    #[serde(skip)]
    v: Vec<f64>,
    /// v(s′_i), row i.
    #[serde(skip)]
    v_next: Vec<f64>,
    slots: HashMap<(u64, usize), Slot>,
}

impl SampleStore {
    /// An empty store of points of dimension `d` with `k` features each.
    pub fn new(
        d: usize,
        k: usize,
        cells_per_dim: u32,
        per_slot: usize,
        max_samples: usize,
        known_after: u64,
    ) -> Self {
        Self {
            d,
            k,
            cells_per_dim,
            per_slot,
            max_samples,
            known_after,
            samples: Vec::new(),
            v: Vec::new(),
            v_next: Vec::new(),
            slots: HashMap::new(),
        }
    }

    /// The cell key of a normalised point: exact mixed-radix coordinates
    /// while they fit, an FNV-1a hash of them beyond.
    pub fn cell(&self, s: &[f64]) -> u64 {
        let c = self.cells_per_dim as u64;
        let mut exact: Option<u64> = Some(0);
        let mut hash: u64 = 0xcbf2_9ce4_8422_2325;
        for &x in s.iter().take(self.d) {
            let i = ((x * c as f64).floor() as u64).min(c - 1);
            exact = exact
                .and_then(|e| e.checked_mul(c))
                .and_then(|e| e.checked_add(i));
            hash = (hash ^ i).wrapping_mul(0x0000_0100_0000_01b3);
        }
        // Exact keys stay below c^d; hashed ones are marked by the top bit.
        exact.filter(|e| e >> 63 == 0).unwrap_or(hash | 1 << 63)
    }

    /// Visits of (the cell of s, a).
    pub fn visits(&self, s: &[f64], a: usize) -> u64 {
        self.slots
            .get(&(self.cell(s), a))
            .map_or(0, |slot| slot.visits)
    }

    /// Whether (the cell of s, a) has been visited `known_after` times.
    pub fn is_known(&self, s: &[f64], a: usize) -> bool {
        self.visits(s, a) >= self.known_after
    }

    /// The stored transitions.
    pub fn samples(&self) -> &[Sample] {
        &self.samples
    }

    /// Transitions stored.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// Whether none is stored.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// Transition i as the planner reads it.
    pub fn get(&self, i: usize) -> SampleRef<'_> {
        let k = self.k;
        SampleRef {
            a: self.samples[i].a,
            weight: self.samples[i].weight,
            v: &self.v[i * k..(i + 1) * k],
            v_next: &self.v_next[i * k..(i + 1) * k],
        }
    }

    /// v(s′_i) of every stored transition, row-major (`len() × k`).
    pub fn v_next_rows(&self) -> &[f64] {
        &self.v_next[..self.samples.len() * self.k]
    }

    /// Every stored transition as the planner reads it, in index order.
    pub fn iter(&self) -> impl Iterator<Item = SampleRef<'_>> {
        let k = self.k.max(1);
        self.samples
            .iter()
            .zip(self.v.chunks_exact(k).zip(self.v_next.chunks_exact(k)))
            .map(|(s, (v, v_next))| SampleRef {
                a: s.a,
                weight: s.weight,
                v,
                v_next,
            })
    }

    /// Whether a store read from a snapshot fits an agent of dimension
    /// `d`, `k` features, `actions` actions and `n` stimuli: every length
    /// and index the store relies on.
    pub fn fits(&self, d: usize, k: usize, actions: usize, n: usize) -> bool {
        let len = self.samples.len();
        self.d == d
            && self.k == k
            && len <= self.max_samples
            && self.samples.iter().all(|s| {
                s.s.len() == d
                    && s.s_next.len() == d
                    && s.xi.len() == n
                    && s.a < actions
                    && s.weight.is_finite()
            })
            && self
                .slots
                .values()
                .all(|slot| slot.samples.iter().all(|&i| i < len))
    }

    /// The features of every stored transition, recomputed from its points
    /// (a store read from a snapshot keeps the points only). The features
    /// are a function of the points, so they are the bits the store held.
    pub fn restore_features(&mut self, features: impl FnMut(&[f64], &mut [f64])) {
        let n = self.samples.len() * self.k;
        self.v = vec![0.0; n];
        self.v_next = vec![0.0; n];
        self.refeature(features);
    }

    /// Recomputes v and v′ of every stored transition with `features`
    /// (after the basis was rebuilt).
    pub fn refeature(&mut self, mut features: impl FnMut(&[f64], &mut [f64])) {
        let k = self.k.max(1);
        for ((sample, v), v_next) in self
            .samples
            .iter()
            .zip(self.v.chunks_exact_mut(k))
            .zip(self.v_next.chunks_exact_mut(k))
        {
            features(&sample.s, v);
            features(&sample.s_next, v_next);
        }
    }

    /// Number of (cell, action) slots visited.
    pub fn slots(&self) -> usize {
        self.slots.len()
    }

    /// Counts a visit of (s, a) and stores the transition to s′.
    #[allow(clippy::too_many_arguments)]
    pub fn insert(
        &mut self,
        tick: u64,
        s: &[f64],
        a: usize,
        s_next: &[f64],
        v: &[f64],
        v_next: &[f64],
        xi: &[f64],
    ) -> Inserted {
        debug_assert_eq!((v.len(), v_next.len()), (self.k, self.k));
        let key = (self.cell(s), a);
        let mut sample = Sample {
            s: s.to_vec(),
            a,
            s_next: s_next.to_vec(),
            xi: xi.to_vec(),
            slot: key,
            stored_at: tick,
            weight: 1.0,
        };
        let slot = self.slots.entry(key).or_default();
        slot.visits += 1;
        if slot.samples.len() >= self.per_slot {
            // The slot is full: its oldest transition makes way, and its weight passes on.
            let index = slot.samples.remove(0);
            slot.samples.push(index);
            let old = &self.samples[index];
            sample.weight += old.weight;
            for (x, o) in sample.xi.iter_mut().zip(&old.xi) {
                *x += (o - *x) * (old.weight / sample.weight);
            }
            let replaced = self.replace(index, sample, v, v_next);
            return Inserted {
                index,
                replaced: Some(replaced),
            };
        }
        if self.samples.len() < self.max_samples {
            let index = self.samples.len();
            slot.samples.push(index);
            self.samples.push(sample);
            if self.v.len() == self.v.capacity() {
                // Double, but never past `max_samples` rows: a full store
                // holds exactly what the cost model prices.
                let rows = index.max(16).min(self.max_samples - index);
                self.v.reserve_exact(rows * self.k);
                self.v_next.reserve_exact(rows * self.k);
            }
            self.v.extend_from_slice(v);
            self.v_next.extend_from_slice(v_next);
            return Inserted {
                index,
                replaced: None,
            };
        }
        // The store is full: the oldest transition anywhere makes way.
        let index = (0..self.samples.len())
            .min_by_key(|&i| (self.samples[i].stored_at, i))
            .unwrap_or(0);
        let old_key = self.samples[index].slot;
        if let Some(old) = self.slots.get_mut(&old_key) {
            old.samples.retain(|&i| i != index);
        }
        if let Some(slot) = self.slots.get_mut(&key) {
            slot.samples.push(index);
        }
        let replaced = self.replace(index, sample, v, v_next);
        Inserted {
            index,
            replaced: Some(replaced),
        }
    }

    /// Puts `sample` with its features at `index`, returning what was there.
    fn replace(&mut self, index: usize, sample: Sample, v: &[f64], v_next: &[f64]) -> Replaced {
        let rows = index * self.k..(index + 1) * self.k;
        let old = std::mem::replace(&mut self.samples[index], sample);
        let replaced = Replaced {
            a: old.a,
            weight: old.weight,
            v: self.v[rows.clone()].to_vec(),
            v_next: self.v_next[rows.clone()].to_vec(),
        };
        self.v[rows.clone()].copy_from_slice(v);
        self.v_next[rows].copy_from_slice(v_next);
        replaced
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_store_is_bounded_per_slot_and_in_total() {
        let mut store = SampleStore::new(1, 1, 10, 2, 5, 2);
        let f = [1.0];
        // Three visits of one slot: two kept, the first replaced.
        for t in 0..3 {
            let ins = store.insert(t, &[0.05], 0, &[0.06], &f, &f, &[t as f64]);
            assert_eq!(ins.replaced.is_some(), t == 2);
        }
        assert_eq!(store.samples().len(), 2);
        // The third replaced the first and stands for both: ξ is their mean.
        assert_eq!(store.samples()[0].weight, 2.0);
        assert!((store.samples()[0].xi[0] - 1.0).abs() < 1e-12);
        assert_eq!(store.visits(&[0.01], 0), 3);
        assert!(
            store.is_known(&[0.09], 0) && !store.is_known(&[0.09], 1) && !store.is_known(&[0.5], 0)
        );
        for t in 3..20 {
            store.insert(t, &[(t as f64) / 20.0], 1, &[0.5], &f, &f, &f);
        }
        assert_eq!(store.samples().len(), 5);
        assert_eq!(
            store.v.capacity(),
            5,
            "the feature rows stop at max_samples"
        );
        // Every stored sample is listed in exactly its slot.
        let listed: usize = store.slots.values().map(|s| s.samples.len()).sum();
        assert_eq!(listed, 5);
    }

    #[test]
    fn cells_are_exact_until_they_overflow_then_hashed() {
        let low = SampleStore::new(2, 1, 10, 1, 10, 1);
        assert_eq!(low.cell(&[0.0, 0.0]), 0);
        assert_eq!(low.cell(&[0.15, 0.95]), 19);
        assert_eq!(low.cell(&[1.0, 1.0]), 99);
        let high = SampleStore::new(64, 1, 16, 1, 10, 1);
        let a = high.cell(&[0.5; 64]);
        assert!(a >> 63 == 1);
        assert_ne!(a, high.cell(&[0.4; 64]));
    }
}
