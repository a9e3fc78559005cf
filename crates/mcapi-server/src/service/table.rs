//! The session table: sessions by id, and what each API key holds (its
//! session count and their estimated memory), kept in step on every insert
//! and removal so a quota check costs one lookup.

use std::collections::HashMap;
use std::collections::btree_map::{self, BTreeMap};
use std::ops::Bound;

use super::cost;
use super::limits::Usage;
use super::session::{Session, SessionRef};

/// Who holds a session: the SHA-256 of its API key, or `None` without keys.
pub type Owner = Option<[u8; 32]>;

/// Sessions in id order with their owners' usage.
#[derive(Default)]
pub struct SessionTable {
    map: BTreeMap<String, SessionRef>,
    usage: HashMap<Owner, Usage>,
}

fn bytes_of(session: &Session) -> u64 {
    cost::estimate(&session.model, &session.config).bytes
}

impl SessionTable {
    /// Number of sessions.
    pub fn len(&self) -> usize {
        self.map.len()
    }

    /// True when there is none.
    pub fn is_empty(&self) -> bool {
        self.map.is_empty()
    }

    /// The session with this id.
    pub fn get(&self, id: &str) -> Option<&SessionRef> {
        self.map.get(id)
    }

    /// Every session, in id order.
    pub fn values(&self) -> btree_map::Values<'_, String, SessionRef> {
        self.map.values()
    }

    /// Sessions with ids after `after` (all without), in id order.
    pub fn after(&self, after: Option<&str>) -> btree_map::Range<'_, String, SessionRef> {
        match after {
            Some(a) => self
                .map
                .range::<str, _>((Bound::Excluded(a), Bound::Unbounded)),
            None => self.map.range::<str, _>(..),
        }
    }

    /// Inserts (or replaces) a session, charging its owner.
    pub fn insert(&mut self, id: String, session: SessionRef) -> Option<SessionRef> {
        let usage = self.usage.entry(session.owner).or_default();
        usage.sessions += 1;
        usage.bytes = usage.bytes.saturating_add(bytes_of(&session));
        let old = self.map.insert(id, session);
        if let Some(old) = &old {
            self.refund(old);
        }
        old
    }

    /// Removes a session, refunding its owner.
    pub fn remove(&mut self, id: &str) -> Option<SessionRef> {
        let old = self.map.remove(id)?;
        self.refund(&old);
        Some(old)
    }

    fn refund(&mut self, session: &Session) {
        if let Some(usage) = self.usage.get_mut(&session.owner) {
            usage.sessions = usage.sessions.saturating_sub(1);
            usage.bytes = usage.bytes.saturating_sub(bytes_of(session));
            if usage.sessions == 0 {
                self.usage.remove(&session.owner);
            }
        }
    }

    /// What `owner` holds now.
    pub fn usage(&self, owner: &Owner) -> Usage {
        self.usage.get(owner).copied().unwrap_or_default()
    }
}
