//! The session table: sessions by id, each resident (in memory) or evicted
//! to the store (docs/sessions.md, "Idle sessions"), and what each API key
//! holds (its session count and their estimated memory), kept in step on
//! every insert, removal, eviction and load so a quota check costs one
//! lookup. A resident session is charged its full estimate, an evicted one
//! what its stub holds.

use std::collections::HashMap;
use std::collections::btree_map::{self, BTreeMap};
use std::ops::Bound;
use std::sync::Arc;

use super::cost;
use super::limits::Usage;
use super::session::{Evicted, Owner, SessionRef};
use super::wire::SessionCost;

/// A session in the table.
#[derive(Debug, Clone)]
pub enum Entry {
    /// In memory.
    Resident(SessionRef),
    /// Evicted to the store: loaded back on its next request.
    Evicted(Arc<Evicted>),
}

impl Entry {
    /// Its owner.
    pub fn owner(&self) -> &Owner {
        match self {
            Self::Resident(s) => &s.owner,
            Self::Evicted(e) => &e.owner,
        }
    }

    /// Its estimated cost once resident.
    pub fn cost(&self) -> SessionCost {
        match self {
            Self::Resident(s) => cost::estimate(&s.model, &s.config),
            Self::Evicted(e) => e.cost,
        }
    }

    /// The bytes its owner is charged for it now: its full estimate while
    /// resident, what its stub holds while evicted.
    pub fn charge(&self) -> u64 {
        match self {
            Self::Resident(s) => cost::estimate(&s.model, &s.config).bytes,
            Self::Evicted(e) => e.held,
        }
    }

    /// The session, if it is in memory.
    pub fn resident(&self) -> Option<&SessionRef> {
        match self {
            Self::Resident(s) => Some(s),
            Self::Evicted(_) => None,
        }
    }
}

/// Sessions in id order with their owners' usage.
#[derive(Default)]
pub struct SessionTable {
    map: BTreeMap<String, Entry>,
    usage: HashMap<Owner, Usage>,
    evicted: usize,
    /// Bumped by every change of which entry an id maps to (an insert, a
    /// removal, a swap), so a lookup remembered with it stands for as long
    /// as it is unchanged ([`SessionTable::generation`]).
    generation: u64,
}

impl SessionTable {
    /// Number of sessions, evicted ones included.
    pub fn len(&self) -> usize {
        self.map.len()
    }

    /// True when there is none.
    pub fn is_empty(&self) -> bool {
        self.map.is_empty()
    }

    /// Number of evicted sessions.
    pub fn evicted(&self) -> usize {
        self.evicted
    }

    /// Which version of the id → entry mapping this is: never 0, and
    /// different after every insert, removal or swap. A caller that
    /// remembers what [`SessionTable::get`] returned for some ids (a
    /// group's members) may use it instead of looking them up again while
    /// the generation is the one it was read with.
    pub fn generation(&self) -> u64 {
        self.generation.wrapping_add(1).max(1)
    }

    /// The session with this id.
    pub fn get(&self, id: &str) -> Option<&Entry> {
        self.map.get(id)
    }

    /// Every session, in id order.
    pub fn values(&self) -> btree_map::Values<'_, String, Entry> {
        self.map.values()
    }

    /// Sessions with ids after `after` (all without), in id order.
    pub fn after(&self, after: Option<&str>) -> btree_map::Range<'_, String, Entry> {
        match after {
            Some(a) => self
                .map
                .range::<str, _>((Bound::Excluded(a), Bound::Unbounded)),
            None => self.map.range::<str, _>(..),
        }
    }

    /// Inserts (or replaces) a resident session, charging its owner.
    pub fn insert(&mut self, id: String, session: SessionRef) -> Option<Entry> {
        self.insert_entry(id, Entry::Resident(session))
    }

    /// Inserts (or replaces) a session, resident or evicted, charging its
    /// owner.
    pub fn insert_entry(&mut self, id: String, entry: Entry) -> Option<Entry> {
        let usage = self.usage.entry(*entry.owner()).or_default();
        usage.sessions += 1;
        usage.bytes = usage.bytes.saturating_add(entry.charge());
        self.evicted += usize::from(matches!(entry, Entry::Evicted(_)));
        self.generation += 1;
        let old = self.map.insert(id, entry);
        if let Some(old) = &old {
            self.refund(old);
        }
        old
    }

    /// Removes a session, refunding its owner.
    pub fn remove(&mut self, id: &str) -> Option<Entry> {
        let old = self.map.remove(id)?;
        self.generation += 1;
        self.refund(&old);
        Some(old)
    }

    /// Replaces the entry of `id` by `with` if it is still `expected` (the
    /// same resident session or the same eviction), moving its owner's
    /// charge from the one to the other (an eviction refunds all but the
    /// stub, a load charges the full estimate again). False if the entry
    /// changed meanwhile.
    pub fn swap(&mut self, id: &str, expected: &Entry, with: Entry) -> bool {
        let Some(entry) = self.map.get_mut(id) else {
            return false;
        };
        let same = match (&*entry, expected) {
            (Entry::Resident(a), Entry::Resident(b)) => Arc::ptr_eq(a, b),
            (Entry::Evicted(a), Entry::Evicted(b)) => Arc::ptr_eq(a, b),
            _ => false,
        };
        if !same {
            return false;
        }
        let was = usize::from(matches!(entry, Entry::Evicted(_)));
        let now = usize::from(matches!(with, Entry::Evicted(_)));
        let (refund, charge) = (entry.charge(), with.charge());
        if let Some(usage) = self.usage.get_mut(with.owner()) {
            usage.bytes = usage.bytes.saturating_sub(refund).saturating_add(charge);
        }
        *entry = with;
        self.evicted = self.evicted + now - was;
        self.generation += 1;
        true
    }

    fn refund(&mut self, entry: &Entry) {
        self.evicted -= usize::from(matches!(entry, Entry::Evicted(_)));
        let owner = entry.owner();
        if let Some(usage) = self.usage.get_mut(owner) {
            usage.sessions = usage.sessions.saturating_sub(1);
            usage.bytes = usage.bytes.saturating_sub(entry.charge());
            if usage.sessions == 0 {
                self.usage.remove(owner);
            }
        }
    }

    /// What `owner` holds now.
    pub fn usage(&self, owner: &Owner) -> Usage {
        self.usage.get(owner).copied().unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::agent_config::UpdateMode;
    use crate::service::session::Evicted;

    fn stub(tick: u64) -> Entry {
        Entry::Evicted(Arc::new(Evicted {
            owner: None,
            cost: SessionCost {
                bytes: 1000,
                tick_us: 1,
            },
            held: 100,
            tick,
            states: 50,
            mode: UpdateMode::Async,
            last_observed_ns: 0,
            lsn: 0,
        }))
    }

    /// The generation changes with every change of what an id maps to and
    /// with nothing else, so a lookup remembered with it stands exactly as
    /// long as the table still gives the same answer.
    #[test]
    fn the_generation_changes_with_every_insert_removal_and_swap_only() {
        let mut table = SessionTable::default();
        let mut seen = vec![table.generation()];
        let mut changed = |table: &SessionTable, expected: bool, what: &str| {
            let now = table.generation();
            assert_ne!(now, 0, "never 0");
            assert_eq!(!seen.contains(&now), expected, "{what}");
            seen.push(now);
        };
        let first = stub(1);
        table.insert_entry("a".into(), first.clone());
        changed(&table, true, "insert");
        table.insert_entry("a".into(), stub(2));
        changed(&table, true, "replace");
        let _ = (
            table.get("a"),
            table.len(),
            table.values().count(),
            table.after(None).count(),
        );
        changed(&table, false, "reads");
        assert!(!table.swap("a", &first, stub(3)), "no longer the entry");
        changed(&table, false, "a swap refused");
        assert!(!table.swap("b", &first, stub(3)), "no such id");
        changed(&table, false, "a swap of no entry");
        let now = table.get("a").cloned().expect("a");
        assert!(table.swap("a", &now, stub(4)));
        changed(&table, true, "swap");
        assert!(table.remove("b").is_none());
        changed(&table, false, "removal of no entry");
        assert!(table.remove("a").is_some());
        changed(&table, true, "removal");
    }
}
