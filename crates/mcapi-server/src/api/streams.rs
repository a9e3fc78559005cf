//! Concurrent watch streams per caller: REST event streams
//! (`GET /v1/sessions/{id}/events`) and gRPC `Watch` streams share one
//! budget, `--max-streams-per-key`. With API keys the budget is per key;
//! without keys it is per client IP address (behind a proxy, all its clients
//! share one), and per server when the address is unknown. Beyond it a new
//! stream is refused with 429 `too_many_streams` / RESOURCE_EXHAUSTED; a
//! [`StreamSlot`] gives its place back when the stream ends, whether the
//! session was deleted, the client went away or the server is stopping.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::Arc;

use parking_lot::Mutex;

use crate::service::{Caller, ServiceError};

/// Whose budget a stream counts against.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
enum Owner {
    /// An API key, by digest.
    Key([u8; 32]),
    /// A client address (no keys configured).
    Peer(IpAddr),
    /// No keys and no known address.
    Server,
}

/// Open streams per owner, at most `max` each.
#[derive(Debug)]
pub struct StreamLimiter {
    max: usize,
    open: Mutex<HashMap<Owner, usize>>,
}

impl std::fmt::Debug for Owner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            // Never print the digest: it identifies the key.
            Self::Key(_) => f.write_str("Key(..)"),
            Self::Peer(ip) => write!(f, "Peer({ip})"),
            Self::Server => f.write_str("Server"),
        }
    }
}

impl StreamLimiter {
    /// At most `max` concurrent streams per owner.
    pub fn new(max: usize) -> Arc<Self> {
        Arc::new(Self {
            max,
            open: Mutex::new(HashMap::new()),
        })
    }

    /// The limit per owner.
    pub fn max(&self) -> usize {
        self.max
    }

    fn owner(caller: Caller, peer: Option<IpAddr>) -> Owner {
        match (caller.owner(), peer) {
            (Some(digest), _) => Owner::Key(digest),
            (None, Some(ip)) => Owner::Peer(ip),
            (None, None) => Owner::Server,
        }
    }

    /// A slot for a new stream of `caller` (from `peer`), or
    /// [`ServiceError::TooManyStreams`] when it holds `max` already.
    pub fn acquire(
        self: &Arc<Self>,
        caller: Caller,
        peer: Option<IpAddr>,
    ) -> Result<StreamSlot, ServiceError> {
        let owner = Self::owner(caller, peer);
        let mut open = self.open.lock();
        let count = open.entry(owner).or_insert(0);
        if *count >= self.max {
            let who = match owner {
                Owner::Key(_) => "this API key",
                Owner::Peer(_) => "this client address",
                Owner::Server => "the server",
            };
            return Err(ServiceError::TooManyStreams(format!(
                "{who} already has {} open event/Watch streams, the limit \
                 (--max-streams-per-key); close one first",
                self.max
            )));
        }
        *count += 1;
        Ok(StreamSlot {
            limiter: Arc::clone(self),
            owner,
        })
    }

    /// Streams `caller` (from `peer`) holds open now.
    pub fn open(&self, caller: Caller, peer: Option<IpAddr>) -> usize {
        let owner = Self::owner(caller, peer);
        self.open.lock().get(&owner).copied().unwrap_or(0)
    }
}

/// One open stream's place in its owner's budget, given back when dropped.
#[derive(Debug)]
pub struct StreamSlot {
    limiter: Arc<StreamLimiter>,
    owner: Owner,
}

impl Drop for StreamSlot {
    fn drop(&mut self) {
        let mut open = self.limiter.open.lock();
        if let Some(count) = open.get_mut(&self.owner) {
            *count = count.saturating_sub(1);
            if *count == 0 {
                open.remove(&self.owner);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::ApiKeys;

    #[test]
    fn slots_are_counted_per_owner_and_given_back() {
        let keys = ApiKeys::new(["key-a-0123456789ab", "key-b-0123456789ab"]);
        let a = keys
            .authenticate(Some("Bearer key-a-0123456789ab"))
            .expect("a");
        let b = keys
            .authenticate(Some("Bearer key-b-0123456789ab"))
            .expect("b");
        let limiter = StreamLimiter::new(2);
        let a1 = limiter.acquire(a, None).expect("first");
        let _a2 = limiter.acquire(a, None).expect("second");
        let err = limiter.acquire(a, None).expect_err("third refused");
        assert!(matches!(err, ServiceError::TooManyStreams(_)), "{err:?}");
        // Another key has its own budget, whatever the address.
        let _b1 = limiter.acquire(b, None).expect("other key");
        assert_eq!(limiter.open(a, None), 2);
        drop(a1);
        assert_eq!(limiter.open(a, None), 1);
        let _a3 = limiter.acquire(a, None).expect("a slot was freed");

        // Without keys: per address.
        let one: IpAddr = [10, 0, 0, 1].into();
        let two: IpAddr = [10, 0, 0, 2].into();
        let _p1 = limiter.acquire(Caller::Anyone, Some(one)).expect("1");
        let p2 = limiter.acquire(Caller::Anyone, Some(one)).expect("2");
        assert!(limiter.acquire(Caller::Anyone, Some(one)).is_err());
        let _q1 = limiter
            .acquire(Caller::Anyone, Some(two))
            .expect("other address");
        drop(p2);
        assert_eq!(limiter.open(Caller::Anyone, Some(one)), 1);
        assert!(format!("{:?}", limiter).contains("Key(..)"));
    }
}
