//! The cost model's memory estimate (`cost.bytes`, docs/limits.md, "What a
//! session costs") against what sessions of each model kind really hold,
//! so that the quotas it enforces stay honest: this test fails when the two
//! drift more than 1.5× apart either way.
//!
//! Every heap allocation of this test binary is counted (a global
//! allocator that wraps the system's), each rounded up to the 16-byte
//! granule that malloc-style allocators hand out. A session is driven until
//! it holds the most its estimate prices: its history ring full, a learned
//! model's every (pair, successor) entry seen, a continuous world's sample
//! store full. What it holds is then what deleting it frees: the bytes
//! live once it has been driven minus the bytes live after its delete
//! (per-thread work space and caches that outlive it are not its own).
//! Each kind has a model of its own, so its planning model (counted in full
//! by the estimate, shared by sessions of one model) is freed with it.
//!
//! The resident set of a process holds a little more than its live
//! allocations (allocator size classes and free pages): BENCHMARKS.md
//! compares the estimate with the server's RSS for hallway sessions.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicI64, Ordering};

use mcapi_server::service::{
    Caller, CreateSession, Limits, ObservationIn, SessionConfig, SessionManager,
};
use serde_json::{Value, json};

/// SplitMix64: the driven worlds' randomness (any fixed sequence does).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }

    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Live heap bytes of this process.
static LIVE: AtomicI64 = AtomicI64::new(0);

struct Counting;

fn granule(size: usize) -> i64 {
    (size.div_ceil(16) * 16) as i64
}

// SAFETY: every call is forwarded to the system allocator with the same
// arguments; the counter is only arithmetic beside it.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        LIVE.fetch_add(granule(layout.size()), Ordering::Relaxed);
        // SAFETY: the caller's contract, forwarded.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        LIVE.fetch_add(granule(layout.size()), Ordering::Relaxed);
        // SAFETY: the caller's contract, forwarded.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        LIVE.fetch_sub(granule(layout.size()), Ordering::Relaxed);
        // SAFETY: the caller's contract, forwarded.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        LIVE.fetch_add(
            granule(new_size) - granule(layout.size()),
            Ordering::Relaxed,
        );
        // SAFETY: the caller's contract, forwarded.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// How a kind's world is driven: what the next observation says.
enum World {
    /// Numbered states in 0..n, each tick a random one with a random
    /// stimulus of `n_stimuli` components.
    States { n: usize, stimuli: usize },
    /// The same, with a curiosity signal of two components.
    Curious { n: usize, stimuli: usize },
    /// A point of the unit square.
    Square { stimuli: usize },
}

struct Kind {
    name: &'static str,
    model: Value,
    agent: Value,
    world: World,
    ticks: usize,
}

fn kinds() -> Vec<Kind> {
    let open_grid = |side: usize| {
        let mut rows = vec!["#".repeat(side + 2)];
        for r in 0..side {
            let mut row: String = ".".repeat(side);
            if r == 0 {
                row.replace_range(0..1, "a");
            }
            if r == side - 1 {
                row.replace_range(side - 1..side, "b");
            }
            rows.push(format!("#{row}#"));
        }
        rows.push("#".repeat(side + 2));
        rows
    };
    let table = |n: usize| {
        let next: Vec<Vec<Value>> = (0..n)
            .map(|s| vec![json!((s + 1) % n), json!((s + n - 1) % n), json!(s)])
            .collect();
        json!({"states": n, "actions": ["left", "right", "stay"],
               "stimuli": ["food", "water", "rest"], "next": next})
    };
    vec![
        Kind {
            name: "preset (hallway, history 256)",
            model: json!({"preset": "hallway"}),
            agent: json!({"seed": 1}),
            world: World::States { n: 50, stimuli: 2 },
            ticks: 300,
        },
        Kind {
            name: "grid (30 x 30, 4 actions)",
            model: json!({"grid": open_grid(30), "sources": {"a": 0, "b": 1}}),
            agent: json!({"seed": 2, "history": 64}),
            world: World::States { n: 900, stimuli: 2 },
            ticks: 80,
        },
        Kind {
            name: "table (400 states, 3 actions)",
            model: table(400),
            agent: json!({"seed": 3, "history": 64}),
            world: World::States { n: 400, stimuli: 3 },
            ticks: 80,
        },
        Kind {
            name: "learned (12 states, 3 actions)",
            model: json!({"states": 12, "actions": ["left", "right", "stay"],
                          "stimuli": ["food", "rest"], "transitions": "learn"}),
            agent: json!({"seed": 4, "history": 64}),
            world: World::States { n: 12, stimuli: 2 },
            ticks: 1500,
        },
        Kind {
            name: "proto-value functions (20 x 20 grid, k = 20)",
            model: json!({"grid": open_grid(20), "sources": {"a": 0, "b": 1},
                          "basis": {"kind": "proto_value", "k": 20}}),
            agent: json!({"seed": 5, "history": 64}),
            world: World::States { n: 400, stimuli: 2 },
            ticks: 80,
        },
        Kind {
            // The library full: every learned sample freezes its module
            // (any error is below δ) and no module ever explains a source,
            // so 64 modules freeze, each judging all four sources.
            name: "curiosity (hallway, signal_dim 2, library full)",
            model: json!({"preset": "hallway"}),
            agent: json!({"seed": 6, "history": 64, "curiosity": {"signal_dim": 2, "params": {
                "delta": 1e9, "freeze_after": 1, "explain_min_samples": u64::MAX,
                "max_sources": 4}}}),
            world: World::Curious { n: 50, stimuli: 2 },
            ticks: 400,
        },
        Kind {
            name: "continuous (unit square, 8 x 8 RBFs, 256 samples)",
            model: json!({"observation_space": {"low": [0, 0], "high": [1, 1]},
                          "actions": ["n", "s", "e", "w"], "stimuli": ["food", "rest"],
                          "basis": {"kind": "rbf", "centres_per_dim": 8},
                          "samples": {"max": 256}}),
            agent: json!({"seed": 7, "history": 64}),
            world: World::Square { stimuli: 2 },
            ticks: 600,
        },
        Kind {
            name: "continuous (unit square, the default 64 x 64 grid)",
            model: json!({"observation_space": {"low": [0, 0], "high": [1, 1]},
                          "actions": ["n", "s", "e", "w"], "stimuli": ["food", "rest"]}),
            agent: json!({"seed": 7, "history": 64}),
            world: World::Square { stimuli: 2 },
            ticks: 600,
        },
    ]
}

fn observation(world: &World, first: bool, rng: &mut Rng) -> ObservationIn {
    let stimulus =
        |rng: &mut Rng, n: usize| (!first).then(|| (0..n).map(|_| rng.below(4) as f64).collect());
    let (state, observation, stimulus, signal, source) = match *world {
        World::States { n, stimuli } => {
            (Some(rng.below(n)), None, stimulus(rng, stimuli), None, None)
        }
        World::Curious { n, stimuli } => (
            Some(rng.below(n)),
            None,
            stimulus(rng, stimuli),
            (!first).then(|| vec![rng.unit(), rng.unit()]),
            (!first).then(|| rng.below(4)),
        ),
        World::Square { stimuli } => (
            None,
            Some(vec![rng.unit(), rng.unit()]),
            stimulus(rng, stimuli),
            None,
            None,
        ),
    };
    ObservationIn {
        state,
        observation,
        stimulus,
        action_taken: None,
        signal,
        signal_source: source,
        seq: None,
    }
}

fn live() -> i64 {
    LIVE.load(Ordering::Relaxed)
}

/// A current-thread runtime to await the manager's calls on.
fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime")
}

/// The tests of this binary measure one counter: one at a time.
static ONE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn measuring() -> std::sync::MutexGuard<'static, ()> {
    ONE_AT_A_TIME
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

#[test]
fn the_memory_estimate_is_within_one_and_a_half_times_what_sessions_hold() {
    let _measuring = measuring();
    let rt = runtime();
    let manager = SessionManager::new(Limits::default(), 1).expect("manager");
    let mut rows = Vec::new();
    for kind in kinds() {
        let agent: SessionConfig = serde_json::from_value(kind.agent).expect("agent");
        let info = manager
            .create(
                Caller::Anyone,
                CreateSession {
                    model: kind.model,
                    agent,
                },
            )
            .unwrap_or_else(|e| panic!("{}: {e}", kind.name));
        let mut rng = Rng(9);
        rt.block_on(async {
            for t in 0..=kind.ticks {
                let obs = observation(&kind.world, t == 0, &mut rng);
                manager
                    .observe(Caller::Anyone, &info.id, vec![obs])
                    .await
                    .unwrap_or_else(|e| panic!("{}, tick {t}: {e}", kind.name));
            }
        });
        let driven = live();
        rt.block_on(manager.delete(Caller::Anyone, &info.id))
            .expect("delete");
        // A tick job may hold the session a moment after the delete.
        let mut after = live();
        for _ in 0..100 {
            std::thread::sleep(std::time::Duration::from_millis(10));
            let now = live();
            if now == after && driven - now > 64 {
                break;
            }
            after = now;
        }
        let held = (driven - after) as f64;
        let estimate = info.cost.bytes as f64;
        rows.push((kind.name, estimate, held, estimate / held));
    }
    let mut report = String::from("kind | estimate | held | estimate / held\n");
    for (name, estimate, held, ratio) in &rows {
        report += &format!("{name} | {estimate:.0} | {held:.0} | {ratio:.2}\n");
    }
    println!("{report}");
    for (name, _, _, ratio) in &rows {
        assert!(
            (1.0 / 1.5..=1.5).contains(ratio),
            "{name}: the estimate is {ratio:.2} times what the session holds\n{report}"
        );
    }
}

/// Creates `n` pristine hallway sessions on `manager`.
fn hallways(manager: &SessionManager, n: usize) -> Vec<String> {
    (0..n)
        .map(|i| {
            let agent: SessionConfig = serde_json::from_value(json!({"seed": i})).expect("agent");
            manager
                .create(
                    Caller::Anyone,
                    CreateSession {
                        model: json!({"preset": "hallway"}),
                        agent,
                    },
                )
                .expect("create")
                .id
        })
        .collect()
}

/// An evicted session is charged what its stub holds
/// (`cost::evicted_bytes`), within 1.5× of what it holds: what a resident
/// session holds (what deleting it frees, on the memory store) minus what
/// evicting it frees (sessions as created, so that eviction writes
/// nothing).
#[test]
fn an_evicted_session_is_charged_what_its_stub_holds() {
    const N: usize = 400;
    let _measuring = measuring();
    let rt = runtime();
    let memory = SessionManager::new(Limits::default(), 1).expect("manager");
    let ids = hallways(&memory, N);
    let before = live();
    rt.block_on(async {
        for id in &ids {
            memory.delete(Caller::Anyone, id).await.expect("delete");
        }
    });
    let resident = (before - live()) as f64 / N as f64;

    let data = tempfile::tempdir().expect("data dir");
    let store = std::sync::Arc::new(mcapi_store::Store::open(data.path()).expect("store"));
    let durable = SessionManager::with_options(mcapi_server::service::ManagerOptions {
        store: Some(store),
        evict_after: Some(std::time::Duration::from_secs(3600)),
        ..mcapi_server::service::ManagerOptions::new(Limits::default(), 1)
    })
    .expect("manager");
    durable.recover().expect("recovery");
    hallways(&durable, N);
    let charged_resident = durable.usage(Caller::Anyone).bytes;
    let before = live();
    assert_eq!(durable.evict_idle(std::time::Duration::ZERO), N);
    let freed = (before - live()) as f64 / N as f64;
    let charged = durable.usage(Caller::Anyone).bytes;
    assert!(
        charged * 20 < charged_resident,
        "evicted, {N} sessions are charged {charged} bytes, resident {charged_resident}"
    );
    let per = charged as f64 / N as f64;
    let held = resident - freed;
    println!(
        "a hallway session as created holds {resident:.0} bytes; evicted, it is charged {per:.0} and holds {held:.0}"
    );
    assert!(
        (1.0 / 1.5..=1.5).contains(&(per / held)),
        "an evicted session is charged {per:.0} bytes and holds {held:.0}"
    );
}
