//! Prefetch hints: a caller about to tick many agents in turn (a server's
//! group step) asks the CPU to start loading the next agent's tables while
//! it ticks this one. With 10,000 hallway agents of about 6 KiB each, no
//! agent's tables are in any cache when its turn comes, and a tick waits on
//! DRAM for each table it touches (BENCHMARKS.md §14).
//!
//! A hint changes no value and no result: the prefetched agent is only read
//! through its ordinary methods afterwards.
//!
//! The lines go to the second-level cache (`T1`), not the first. Criterion's
//! `tick/hallway_indicator_10000_agents_prefetched` (the next agent's
//! tables and the struct of the agent after it, as the group step hints
//! them): 1.19-1.22 µs a tick against 1.65-1.82 µs without. Into L1 (`T0`)
//! the hint made the tick slower than none (1.83 µs against 1.69): the
//! hinted lines evict the ticking agent's own from a 32 KiB L1. Two agents
//! ahead instead of one: 1.60 µs against 1.45.

/// Bytes per cache line on the machines this runs on (x86-64, most ARM).
const LINE: usize = 64;

/// Hints that every cache line of `value` will be read soon.
#[inline]
pub fn value<T>(value: &T) {
    slice(std::slice::from_ref(value));
}

/// Hints that every cache line of `data` will be read soon.
#[inline]
pub fn slice<T>(data: &[T]) {
    let start = data.as_ptr() as usize;
    let bytes = std::mem::size_of_val(data);
    let mut at = start & !(LINE - 1);
    while at < start + bytes {
        line(at as *const u8);
        at += LINE;
    }
}

/// Hints that the cache line at `p` will be read soon.
#[inline(always)]
fn line(p: *const u8) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch is a hint, not an access: it never faults, reads
    // no value into the program and writes nothing, whatever the address
    // (here always inside a live slice). SSE, which it needs, is part of
    // the x86-64 baseline.
    unsafe {
        use std::arch::x86_64::{_MM_HINT_T1, _mm_prefetch};
        _mm_prefetch::<_MM_HINT_T1>(p.cast());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}
