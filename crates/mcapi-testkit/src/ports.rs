//! Free loopback ports for a server about to be started.
//!
//! A port found free is released before the server binds it, and in that
//! moment anything else may take it: a port the kernel hands out for
//! `bind(…:0)` (a cluster's replicas, an in-process test server) or as the
//! local port of an outgoing connection (every client of every test) comes
//! from its ephemeral range, so ports taken from that range can be handed
//! out again before the server binds them. The ports here come from below
//! that range instead, one after the other from a counter this process
//! starts at an offset of its own, so nothing the kernel picks and no other
//! test of the process can get them.

use std::net::TcpListener;
use std::sync::OnceLock;
use std::sync::atomic::{AtomicU32, Ordering};

/// The lowest port handed out.
const FIRST: u16 = 10_000;

/// Two distinct ports nothing listens on right now (HTTP, gRPC). Both
/// listeners are held until both ports are known.
pub fn free_ports() -> (u16, u16) {
    let a = listener();
    let b = listener();
    let port = |l: &TcpListener| l.local_addr().expect("addr").port();
    (port(&a), port(&b))
}

/// A listener on the next free port below the ephemeral range, or on one
/// the kernel picks if that range leaves no room below it.
fn listener() -> TcpListener {
    let Some(span) = span() else {
        return TcpListener::bind("127.0.0.1:0").expect("bind");
    };
    static NEXT: AtomicU32 = AtomicU32::new(0);
    let start = std::process::id().wrapping_mul(7919) % u32::from(span);
    for _ in 0..span {
        let k = NEXT.fetch_add(1, Ordering::Relaxed);
        let port = FIRST + ((start + k) % u32::from(span)) as u16;
        if let Ok(l) = TcpListener::bind(("127.0.0.1", port)) {
            return l;
        }
    }
    panic!("no free loopback port from {FIRST} up to the ephemeral range");
}

/// How many ports lie from [`FIRST`] up to the kernel's ephemeral range
/// (`/proc/sys/net/ipv4/ip_local_port_range`), if at least 1,000.
fn span() -> Option<u16> {
    static SPAN: OnceLock<Option<u16>> = OnceLock::new();
    *SPAN.get_or_init(|| {
        let range = std::fs::read_to_string("/proc/sys/net/ipv4/ip_local_port_range").ok()?;
        let low: u16 = range.split_whitespace().next()?.parse().ok()?;
        low.checked_sub(FIRST).filter(|&n| n >= 1_000)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ports_are_free_distinct_and_below_the_ephemeral_range() {
        let mut seen = std::collections::BTreeSet::new();
        for _ in 0..50 {
            let (a, b) = free_ports();
            assert_ne!(a, b);
            for p in [a, b] {
                // Free once released, and never handed out twice.
                drop(TcpListener::bind(("127.0.0.1", p)).expect("free"));
                assert!(seen.insert(p), "{p} handed out twice");
                if let Some(span) = span() {
                    assert!((FIRST..FIRST + span).contains(&p), "{p}");
                }
            }
        }
    }

    #[test]
    fn a_port_in_use_is_skipped() {
        let Some(_) = span() else { return };
        // Occupy the next port the counter would give, then ask.
        let taken = listener();
        let port = taken.local_addr().expect("addr").port();
        let after = (port - FIRST + 1) % span().expect("span") + FIRST;
        let blocker = TcpListener::bind(("127.0.0.1", after));
        let (a, b) = free_ports();
        if blocker.is_ok() {
            assert!(a != after && b != after, "{after} is in use");
        }
        assert!(a != port && b != port);
    }
}
