//! What a session costs the server: its memory and the CPU time of one
//! observation, estimated from the validated model and configuration before
//! the session exists (or from a live session's summary, which holds the
//! same facts).
//!
//! The estimates are worst cases of the data structures the core allocates
//! and of the work one observation does (observe, Eq. 1-3, then one LSTDQ
//! update, Algorithm 1 lines 5-9), counted in elementary operations and
//! converted at [`NS_PER_OP`]. They are deliberately simple and
//! conservative: their job is to refuse a session that would exhaust the
//! server (PostgreSQL's `work_mem` and etcd's request quotas play the same
//! role), not to predict latency. `benches/tick.rs` measures real ticks.

use mcapi_core::curiosity::{MAX_LIBRARY, expanded_dim};

use super::agent_config::{CuriosityConfig, EffectiveConfig};
use super::wire::{ModelSummary, SessionCost};

/// Nanoseconds per counted operation: scalar loops on this kind of machine
/// run at about one operation per nanosecond (a hallway tick counts about
/// 1,000 operations and takes about 0.9 µs in `cargo bench --bench tick`).
pub const NS_PER_OP: f64 = 1.0;

/// Bytes of fixed bookkeeping per session (ids, locks, counters, the agent's
/// small vectors).
const FIXED_BYTES: u64 = 4096;

/// Bytes of one history-ring tick besides its vectors: the entry (112,
/// its reply's policy version and the observation's digest included, which
/// replays of `seq` need, and room for the first four numbers of D and ξ,
/// which the vectors counted beside it then do not take) and an
/// allocation's overhead.
const RING_TICK_BYTES: u64 = 112 + 16;

/// Gauss–Seidel sweeps the planner allows before its dense fallback (see
/// `algo::lstdq`).
const MAX_SWEEPS: f64 = 20_000.0;

/// States up to which a stochastic model falls back to a dense solve.
const DENSE_FALLBACK_MAX_STATES: f64 = 2048.0;

fn mul(a: u64, b: u64) -> u64 {
    a.saturating_mul(b)
}

fn us(ops: f64) -> u64 {
    let us = ops * NS_PER_OP / 1000.0;
    if us.is_finite() && us < u64::MAX as f64 {
        us.ceil().max(1.0) as u64
    } else {
        u64::MAX
    }
}

/// Bytes of a model's action and stimulus names.
fn names_bytes(model: &ModelSummary) -> u64 {
    model
        .actions
        .iter()
        .chain(&model.stimuli)
        .map(|s| s.len() as u64 + 24)
        .sum()
}

/// Estimates the cost of a session on `model` with `config`.
pub fn estimate(model: &ModelSummary, config: &EffectiveConfig) -> SessionCost {
    estimate_with(
        model,
        config,
        model.learned.as_ref().map(|l| l.max_transitions),
    )
}

/// The most transitions a learned session on `model` with `config` may
/// store within the per-session budgets (`--max-session-bytes`,
/// `--max-tick-us`): its cost is estimated at its cap, so the cap is the
/// largest one that fits, up to `full` (every successor of every pair, at
/// most `--max-transitions`). When not even one successor per pair fits,
/// `full`: the session is then refused for its cost, with that message.
pub fn learned_cap_within(
    model: &ModelSummary,
    config: &EffectiveConfig,
    full: usize,
    max_bytes: u64,
    max_tick_us: u64,
) -> usize {
    let fits = |cap: usize| {
        let cost = estimate_with(model, config, Some(cap));
        cost.bytes <= max_bytes && cost.tick_us <= max_tick_us
    };
    // A fresh P̂ stores one successor per pair (unknown pairs lead to the
    // absorbing state, or stay put).
    let floor = model.pairs.min(full);
    if fits(full) || !fits(floor) {
        return full;
    }
    // The estimate grows with the cap: the largest cap that fits, in
    // [floor, full).
    let (mut lo, mut hi) = (floor, full);
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        if fits(mid) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    lo
}

/// [`estimate`], a learned model priced at `learned_cap` transitions.
fn estimate_with(
    model: &ModelSummary,
    config: &EffectiveConfig,
    learned_cap: Option<usize>,
) -> SessionCost {
    if let Some(spec) = &model.continuous {
        return continuous(model, spec, config);
    }
    let states = model.states as u64;
    let actions = model.actions.len() as u64;
    let pairs = model.pairs as u64;
    // A learned model (docs/algorithm.md §8) is priced at the most
    // transitions it may come to store, stochastic.
    let (transitions, deterministic) = match learned_cap {
        Some(cap) => (cap as u64, false),
        None => (model.transitions as u64, model.deterministic),
    };
    let n = model.stimuli.len() as u64;
    let features = model.features as u64;
    let k = model.basis.k as u64;
    let feature_basis = model.basis.kind != "indicator";

    // The planning model: CSR successors, pair tables and the dense lookup.
    let names = names_bytes(model);
    let mut bytes =
        mul(model.transitions as u64, 12) + mul(pairs, 16) + mul(mul(states, actions), 4) + names;
    if feature_basis {
        // State features, ΦᵀΦ, M.
        bytes += mul(mul(states, k), 8) + mul(mul(features, features), 8);
        bytes += mul(mul(features, states), 8);
    }
    // The learner: Ξ and its visit counts, R, Q twice, the policy, D.
    bytes += mul(mul(pairs, n), 8) + mul(pairs, 4) + mul(pairs, 24) + mul(states, 4);
    bytes += mul(n, 64);
    if learned_cap.is_some() {
        // The agent's own planning model P̂ (with the absorbing state),
        // copied from the shared structure, and the counts: N(s, a) per
        // pair, one (s′, N(s, a, s′)) entry and its list's share per
        // stored transition.
        bytes += mul(transitions, 12) + mul(pairs + 1, 16) + mul(mul(states + 1, actions), 4);
        bytes += mul(pairs, 8 + 24) + mul(transitions, 16);
    }
    // The planner's engine (for the functional graph of a deterministic
    // model: V, 8 bytes a state, and the successors and order of its last
    // walk, at most 12 bytes a state held and 16 with the vector's spare
    // room).
    bytes += if feature_basis {
        mul(mul(features, features), 16) + mul(features, 40) + mul(states, 8)
    } else {
        mul(states, 28)
    };
    // The history ring: D and the stimulus per tick.
    let history = config.history as u64;
    bytes += mul(history, RING_TICK_BYTES + mul(2 * n + 1, 8));

    // One observation: Ξ row and D (O(n)), R for every pair (O(pairs·n)).
    let mut ops = (pairs * n) as f64 + 16.0 * n as f64;
    // One policy update.
    ops += if feature_basis {
        let f = features as f64;
        // A rebuild and inversion (every REFRESH_AFTER rank-one updates,
        // and whenever a Sherman–Morrison step is unsafe) plus Q = Φw.
        f * f * f + (pairs * k) as f64 + (states * features) as f64
    } else if deterministic {
        // The functional-graph solve: a few passes over states and pairs.
        5.0 * (pairs + states) as f64
    } else {
        // Gauss–Seidel until γ^sweeps·‖ΔV‖ is below 1e-12, or the dense
        // fallback when that takes more than MAX_SWEEPS.
        let sweeps = sweeps_for(config.gamma);
        let per_sweep = (transitions + states) as f64;
        if sweeps > MAX_SWEEPS {
            let s = states as f64;
            let dense = if s <= DENSE_FALLBACK_MAX_STATES {
                s * s * s / 3.0
            } else {
                0.0
            };
            MAX_SWEEPS * per_sweep + dense
        } else {
            sweeps * per_sweep
        }
    } + 5.0 * pairs as f64;

    if let Some(c) = &config.curiosity {
        let (channel_bytes, channel_ops) = curiosity(c);
        bytes = bytes.saturating_add(channel_bytes);
        ops += channel_ops;
    }
    SessionCost {
        bytes: bytes.saturating_add(FIXED_BYTES),
        tick_us: us(ops),
    }
}

/// The cost of a continuous world's session (docs/algorithm.md §9), its
/// sample store counted full: Ξ's recursive least squares (a k × k inverse
/// per action), the planner's (k|A|)² inverse, the samples with their
/// features, the probe points and the history ring. A tick evaluates R at
/// every sample's pair and successor, solves w = A⁻¹b and re-chooses every
/// successor action; each changed successor is a rank-one update of A⁻¹,
/// priced at half the samples changing (what the three-room bench measures
/// early on, when the policy moves most), and a rebuild every
/// `REBUILD_EVERY` ticks is spread over them.
fn continuous(
    model: &ModelSummary,
    spec: &mcapi_core::continuous::ContinuousSpec,
    config: &EffectiveConfig,
) -> SessionCost {
    use mcapi_core::continuous::planner::{MAX_PENDING, REBUILD_EVERY};
    use mcapi_core::continuous::stimulus::PROBES;
    if let Some(grid) = grid_shape(spec) {
        return continuous_grid(model, spec, config, grid);
    }
    let k = model.basis.k as u64;
    let na = model.actions.len() as u64;
    let n = model.stimuli.len() as u64;
    let d = spec.observation_space.dim() as u64;
    let samples = u64::from(
        spec.samples
            .max
            .unwrap_or(mcapi_core::continuous::model::MAX_SAMPLES),
    );
    let f = k * na;
    let names = names_bytes(model);
    let mut bytes = names + mul(mul(na, mul(k, k) + mul(k, n)), 8);
    // A⁻¹, its vectors, and its pending rank-one terms (x, y and x
    // transposed while they are applied).
    bytes += mul(mul(f, f), 8) + mul(f, 24) + mul(f, 24 * MAX_PENDING as u64);
    bytes += mul(samples, mul(2 * d + 2 * k + 8, 8));
    bytes += mul(mul(PROBES as u64, k), 8) + mul(mul(k, d), 16);
    let history = config.history as u64;
    bytes += mul(history, RING_TICK_BYTES + mul(2 * n + 1 + d, 8));
    let (kf, naf, sf, ff) = (k as f64, na as f64, samples as f64, f as f64);
    let mut ops = 4.0 * sf * naf * kf + sf * kf + ff * ff;
    ops += (sf / 2.0) * 2.0 * ff * ff;
    ops += (ff * ff * ff + sf * ff * ff) / REBUILD_EVERY as f64;
    if let Some(mcapi_core::continuous::ContinuousBasisSpec::Pvf {
        nodes, neighbours, ..
    }) = &spec.basis
    {
        // The graph and its eigenvectors; a rebuild (at most every 50
        // ticks) re-features every sample and refits Ξ, spread over them.
        use mcapi_core::continuous::basis::{DEFAULT_PVF_NEIGHBOURS, DEFAULT_PVF_NODES};
        let m = u64::from(nodes.unwrap_or(DEFAULT_PVF_NODES));
        let g = u64::from(neighbours.unwrap_or(DEFAULT_PVF_NEIGHBOURS));
        bytes += mul(m, mul(d + k + 2 * g, 8));
        let (mf, gf) = (m as f64, g as f64);
        ops += sf * gf * kf * naf + (mf * mf * kf + sf * kf * kf * naf) / 50.0;
    }
    SessionCost {
        bytes: bytes.saturating_add(FIXED_BYTES),
        tick_us: us(ops),
    }
}

/// The grid of a continuous session (docs/algorithm.md §9.8): its cells
/// per dimension, moves kept per pair and reach in cells, if its basis is
/// a grid.
fn grid_shape(spec: &mcapi_core::continuous::ContinuousSpec) -> Option<(u64, u64, f64)> {
    use mcapi_core::continuous::grid::{DEFAULT_GRID_NEIGHBOURS, DEFAULT_GRID_REACH};
    match spec.basis {
        Some(mcapi_core::continuous::ContinuousBasisSpec::Grid {
            cells_per_dim,
            neighbours,
            reach,
        }) => Some((
            u64::from(cells_per_dim),
            u64::from(neighbours.unwrap_or(DEFAULT_GRID_NEIGHBOURS)),
            reach.unwrap_or(DEFAULT_GRID_REACH),
        )),
        _ => None,
    }
}

/// The cost of a continuous session on a grid: per (cell, action) its kept
/// moves (a distance and a displacement each) and its successor; per cell
/// Ξ's sums, nearest stimulus and prior, the arrivals, π, V, R and the
/// evaluation's marks and walk; and the history ring. A tick computes R
/// in every cell, walks π's graph once and re-chooses every cell's action.
fn continuous_grid(
    model: &ModelSummary,
    spec: &mcapi_core::continuous::ContinuousSpec,
    config: &EffectiveConfig,
    (res, neighbours, _): (u64, u64, f64),
) -> SessionCost {
    let na = model.actions.len() as u64;
    let n = model.stimuli.len() as u64;
    let d = spec.observation_space.dim() as u64;
    let cells = (0..d).fold(1u64, |acc, _| mul(acc, res));
    let pairs = mul(cells, na);
    let mut bytes = names_bytes(model);
    bytes += mul(pairs, mul(mul(neighbours, 1 + d), 8) + 4);
    bytes += mul(cells, mul(n, 24) + 34);
    let history = config.history as u64;
    bytes += mul(history, RING_TICK_BYTES + mul(2 * n + 1 + d, 8));
    let ops = cells as f64 * (2.0 * n as f64 + 10.0) + 4.0 * pairs as f64;
    SessionCost {
        bytes: bytes.saturating_add(FIXED_BYTES),
        tick_us: us(ops),
    }
}

/// A low estimate of the time, in milliseconds, that building `basis` for
/// `model` takes: what a session's creation is refused for before the
/// build starts when it is over `--max-build-ms` (the build is also
/// stopped by that deadline while it runs, so the estimate only has to
/// spare the server builds that could not finish; it errs low, so that no
/// build that could finish is refused). Only proto-value functions cost
/// more than the model itself:
/// - up to `DENSE_PVF_MAX_STATES` states, a dense symmetric
///   eigendecomposition, |S|³/4 operations (551 ms for 1,024 states,
///   BENCHMARKS.md §9, is about |S|³/2);
/// - above, the sparse solver's iteration, two of them at a filter of
///   degree 32: each applies the Laplacian to a block of b vectors per
///   degree, b (|S| + 2 · transitions), and orthonormalises and rotates
///   the block, 4 |S| b² (measured: 30 ms for 30 PVFs of a 32 × 32 grid,
///   estimated 31; 0.74 s for a 100 × 100 grid, estimated 0.31; about
///   155 s for 550 PVFs of a 10,000-state ring, estimated 56).
pub fn basis_build_ms(basis: &mcapi_core::BasisSpec, model: &mcapi_core::EnvModel) -> u64 {
    use mcapi_core::basis::{DENSE_PVF_MAX_STATES, sparse_pvf_block};
    let mcapi_core::BasisSpec::ProtoValue { k } = basis else {
        return 0;
    };
    let n = model.states() as f64;
    let ops = if model.states() <= DENSE_PVF_MAX_STATES {
        n * n * n / 4.0
    } else {
        let b = sparse_pvf_block(*k, model.states()) as f64;
        let nnz = 2.0 * model.n_transitions() as f64;
        2.0 * (32.0 * b * (n + nnz) + 4.0 * n * b * b)
    };
    us(ops) / 1000
}

/// Bytes an evicted session holds in memory (docs/sessions.md, "Idle
/// sessions"): its stub of `stub` bytes (`session::Evicted`, see
/// `Evicted::held_bytes`) behind its `Arc`, its id as the table's key, and
/// its slot of the table's B-tree with the nodes' slack. What its owner is
/// charged while it is evicted, instead of its full [`estimate`] (charged
/// again when it is loaded back); `tests/cost_calibration.rs` checks it
/// against what the stubs hold.
pub fn evicted_bytes(stub: usize, id: &str) -> u64 {
    /// An `Arc`'s two counts, and a B-tree slot (a `String` key and an
    /// `Entry`) with the slack of nodes about two-thirds full.
    const OVERHEAD: u64 = 16 + 64;
    (stub as u64).div_ceil(16) * 16 + (id.len() as u64).div_ceil(16) * 16 + OVERHEAD
}

/// Estimated CPU time of one observation without its policy update (what
/// an async-mode observation costs the request), in microseconds.
pub fn observe_us(model: &ModelSummary, config: &EffectiveConfig) -> u64 {
    if let Some(spec) = &model.continuous
        && let Some((_, neighbours, reach)) = grid_shape(spec)
    {
        // The cells a move teaches, each a sorted insert of a kept move
        // and a mean over them; the stimulus's cells.
        let d = spec.observation_space.dim() as i32;
        let taught = (2.0 * reach + 1.0).powi(d);
        let kept = neighbours as f64 * (1.0 + f64::from(d));
        return us(taught * (2.0 * kept + 16.0) + 3f64.powi(d) * 8.0);
    }
    if let Some(spec) = &model.continuous {
        // Ξ's update, the new sample's rank-one term, the known marks.
        let (k, na) = (model.basis.k as f64, model.actions.len() as f64);
        let d = spec.observation_space.dim() as f64;
        let samples = f64::from(
            spec.samples
                .max
                .unwrap_or(mcapi_core::continuous::model::MAX_SAMPLES),
        );
        return us(3.0 * k * k + 2.0 * (k * na) * (k * na) + samples * d);
    }
    let n = model.stimuli.len() as f64;
    let mut ops = model.pairs as f64 * n + 16.0 * n;
    if let Some(c) = &config.curiosity {
        ops += curiosity(c).1;
    }
    us(ops)
}

/// Sweeps of Gauss–Seidel for a 1e-12 contraction at discount γ.
fn sweeps_for(gamma: f64) -> f64 {
    if gamma <= 0.0 {
        1.0
    } else if gamma >= 1.0 {
        f64::INFINITY
    } else {
        ((1e-12f64).ln() / gamma.ln()).ceil() + 1.0
    }
}

/// Memory and per-sample operations of a curiosity channel (docs/algorithm.md
/// §7): one active module learning, up to [`MAX_LIBRARY`] frozen ones
/// judging every sample, each with a tracker per source.
fn curiosity(c: &CuriosityConfig) -> (u64, f64) {
    let p = &c.params;
    let d = expanded_dim(c.signal_dim) as u64;
    let window = (p.tau as u64 + p.lag as u64) * 8;
    let roc = p.max_centres as u64 * 16;
    // Mean, covariance, whitening, w, the previous sample.
    let module = mul(mul(d, d), 16) + mul(d, 32);
    let tracker = roc + p.tau as u64 * 8 + 32;
    let library = MAX_LIBRARY as u64;
    let bytes = module
        + window
        + roc
        + mul(library, module + mul(p.max_sources as u64, tracker))
        + p.max_sources as u64;
    let df = d as f64;
    // Covariance update, eigendecomposition (about 10 d³), the whitening
    // matrix (d³/2), mat-vecs, ROC; each frozen module judges the sample.
    let learn = 2.0 * df * df + 10.0 * df * df * df + 0.5 * df * df * df + 4.0 * df * df;
    let judge = library as f64 * (2.0 * df * df + p.max_centres as f64 * 4.0);
    (
        bytes,
        learn + judge + (p.max_centres * p.max_centres) as f64,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::agent_config::SessionConfig;
    use crate::service::wire::BasisSummary;
    use mcapi_core::CuriosityParams;

    fn summary(states: usize, actions: usize, n: usize, deterministic: bool) -> ModelSummary {
        ModelSummary {
            states,
            actions: (0..actions).map(|a| format!("a{a}")).collect(),
            stimuli: (0..n).map(|i| format!("s{i}")).collect(),
            pairs: states * actions,
            transitions: states * actions * if deterministic { 1 } else { 2 },
            deterministic,
            basis: BasisSummary {
                kind: "indicator".into(),
                k: 0,
            },
            features: states * actions,
            continuous: None,
            layout: None,
            learned: None,
        }
    }

    fn config(history: usize, curiosity: Option<CuriosityConfig>) -> EffectiveConfig {
        let request = SessionConfig {
            seed: Some(1),
            history: Some(history),
            curiosity,
            ..SessionConfig::default()
        };
        let params = request.params().check(2, 1).expect("valid");
        request.effective(&params)
    }

    #[test]
    fn a_hallway_costs_tens_of_kilobytes_and_about_a_microsecond() {
        let cost = estimate(&summary(50, 3, 2, true), &config(256, None));
        assert!(cost.bytes > 20_000 && cost.bytes < 200_000, "{cost:?}");
        assert!(cost.tick_us >= 1 && cost.tick_us <= 5, "{cost:?}");
    }

    #[test]
    fn cost_grows_with_what_a_client_controls() {
        let base = estimate(&summary(1000, 4, 3, true), &config(256, None));
        let long_history = estimate(&summary(1000, 4, 3, true), &config(100_000, None));
        assert!(long_history.bytes > base.bytes + 100_000 * 64);
        let stochastic = estimate(&summary(1000, 4, 3, false), &config(256, None));
        assert!(
            stochastic.tick_us > 50 * base.tick_us,
            "{stochastic:?} vs {base:?}"
        );
        let mut slow = config(256, None);
        slow.gamma = 0.999_999;
        let near_one = estimate(&summary(1000, 4, 3, false), &slow);
        assert!(near_one.tick_us > stochastic.tick_us);
    }

    #[test]
    fn a_learned_model_is_priced_at_its_cap_on_stored_transitions() {
        let known = estimate(&summary(100, 4, 2, true), &config(256, None));
        let mut learned = summary(100, 4, 2, true);
        learned.learned = Some(crate::service::wire::LearnedSummary {
            known_after: 3,
            optimism: mcapi_core::Optimism::Absorbing,
            max_transitions: 400 * 100,
        });
        let cost = estimate(&learned, &config(256, None));
        // 40,000 entries of the counts and of P̂, at least 28 bytes each.
        assert!(
            cost.bytes > known.bytes + 40_000 * 28,
            "{cost:?} vs {known:?}"
        );
        // Planned as a stochastic model of 40,000 transitions.
        assert!(cost.tick_us > 100 * known.tick_us, "{cost:?} vs {known:?}");
    }

    #[test]
    fn a_learned_cap_is_the_largest_that_fits_the_budgets() {
        // A 100 × 100 grid: 10,000 states, 5 actions, 2 stimuli.
        let mut learned = summary(10_000, 5, 2, true);
        let full = 2_000_000;
        learned.learned = Some(crate::service::wire::LearnedSummary {
            known_after: 3,
            optimism: mcapi_core::Optimism::Absorbing,
            max_transitions: full,
        });
        let cfg = config(256, None);
        let limits = crate::service::Limits::default();
        let (bytes, us) = (limits.max_session_bytes, limits.max_tick_us);
        assert!(
            estimate(&learned, &cfg).tick_us > us,
            "priced at `full`, it does not fit"
        );
        let cap = learned_cap_within(&learned, &cfg, full, bytes, us);
        assert!(cap >= learned.pairs && cap < full, "{cap}");
        let at = |cap| estimate_with(&learned, &cfg, Some(cap));
        assert!(
            at(cap).tick_us <= us && at(cap).bytes <= bytes,
            "{:?}",
            at(cap)
        );
        assert!(
            at(cap + 1).tick_us > us || at(cap + 1).bytes > bytes,
            "{:?}",
            at(cap + 1)
        );
        // A cap that fits is kept; a model that cannot fit keeps `full` (and
        // is refused for its cost).
        assert_eq!(learned_cap_within(&learned, &cfg, 1_000, bytes, us), 1_000);
        assert_eq!(learned_cap_within(&learned, &cfg, full, bytes, 1), full);
    }

    #[test]
    fn a_large_signal_is_priced_by_its_eigendecomposition() {
        let channel = |m| CuriosityConfig {
            signal_dim: m,
            params: CuriosityParams::default(),
        };
        let small = estimate(&summary(50, 3, 3, true), &config(256, Some(channel(2))));
        let large = estimate(&summary(50, 3, 3, true), &config(256, Some(channel(64))));
        assert!(small.tick_us < 100, "{small:?}");
        // d = 2144: about 10^11 operations per sample.
        assert!(large.tick_us > 10_000_000, "{large:?}");
        assert!(large.bytes > 64 * 2144 * 2144 * 16, "{large:?}");
    }
}
