//! Property tests of the MCA-PI core (`mcapi_core`) against docs/algorithm.md.
//!
//! Each property draws its structure (sizes, rates, a seed) from proptest and
//! fills the bulk content (matrices, models, stimulus streams) from a ChaCha8
//! RNG seeded with the drawn seed, so a reported failure reproduces exactly.
//! Reference values are computed here independently, by dense linear algebra
//! on this file's own model representation (not the core's CSR).
//!
//! 1. MCA (Eqs. 1-2) converges to the minor eigenvector of C = E[Λξ ξᵀΛ].
//! 2. |D| = 1 after every update, for any finite stimulus and priorities;
//!    the running λ₁ estimate of condition (1) is the second moment's top
//!    eigenvalue.
//! 3. Indicator-basis LSTDQ equals Q^π = (I − γ P^π)⁻¹ R, and the improvement
//!    is greedy with the tie rule of §2.6.
//! 4. The feature engine with spanning (one-hot) features equals Q^π over
//!    successive updates (Sherman–Morrison path); with arbitrary features it
//!    equals the dense LSTDQ solution Φ (Φᵀ(Φ − γ P^πΦ))⁻¹ ΦᵀR.
//! 5. PVFs are orthonormal eigenvectors of the normalised Laplacian, smallest
//!    eigenvalues first, on random connected grid maps.
//! 6. Malformed models are rejected with a message naming the defect.
//! 7. Agents are deterministic given the seed, and never produce NaN.
//!
//! Three regression tests at the end pin down problems of the core found
//! while writing these (huge stimuli, γ near 1 on stochastic models, the λ₁
//! estimate); they failed before the core was fixed.

use std::cell::Cell;
use std::sync::Arc;

use mcapi_core::basis::{Basis, proto_value_functions};
use mcapi_core::drive::{Drive, norm};
use mcapi_core::lstdq::{Planner, PlannerStats, PlanningModel, TIE_TOLERANCE};
use mcapi_core::model::{EnvModel, GridMap};
use mcapi_core::spec::{ActionRef, BasisSpec, ModelSpec, TransitionSpec};
use mcapi_core::{Agent, AgentParams, AlgoError, Observation, StimulusRate};
use nalgebra::{DMatrix, DVector, SymmetricEigen};
use proptest::prelude::{
    Just, ProptestConfig, Strategy, TestCaseError, any, prop, prop_assert, prop_assert_eq,
    prop_assume, prop_oneof, proptest,
};
use proptest::test_runner::TestRunner;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

type TestResult<T = ()> = Result<T, TestCaseError>;

/// Proptest configuration: `cases` cases, no regression files (this suite
/// must stay a single file; a failure prints its minimal input instead).
fn config(cases: u32) -> ProptestConfig {
    ProptestConfig {
        cases,
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

fn fail(msg: impl Into<String>) -> TestCaseError {
    TestCaseError::fail(msg.into())
}

fn gaussian(rng: &mut ChaCha8Rng) -> f64 {
    StandardNormal.sample(rng)
}

fn names(prefix: &str, n: usize) -> Vec<String> {
    (0..n).map(|i| format!("{prefix}{i}")).collect()
}

/// `got` equals `want` within `rel · (1 + ‖want‖∞)` componentwise.
fn assert_close(got: &[f64], want: &[f64], rel: f64, what: &str) -> TestResult {
    prop_assert_eq!(got.len(), want.len(), "{}: length", what);
    let scale = 1.0 + want.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        prop_assert!(
            (g - w).abs() <= rel * scale,
            "{}: entry {} is {} but the dense solve gives {} (scale {})",
            what,
            i,
            g,
            w,
            scale
        );
    }
    Ok(())
}

// ---------------------------------------------------------------------------
// Random environment models, in this file's own representation.
// ---------------------------------------------------------------------------

/// Successor states of a pair with their probabilities.
type Successors = Vec<(usize, f64)>;

/// `rows[s][a]` = successors of (s, a) with probabilities, `None` if unavailable.
#[derive(Debug, Clone)]
struct RawModel {
    states: usize,
    actions: usize,
    stochastic: bool,
    rows: Vec<Vec<Option<Successors>>>,
}

/// `m` distinct states of `0..states` (partial Fisher–Yates).
fn distinct_states(rng: &mut ChaCha8Rng, states: usize, m: usize) -> Vec<usize> {
    let mut all: Vec<usize> = (0..states).collect();
    for i in 0..m {
        let j = rng.random_range(i..states);
        all.swap(i, j);
    }
    all.truncate(m);
    all
}

/// A random sparse distribution over at least `min_support` states.
fn random_distribution(
    rng: &mut ChaCha8Rng,
    states: usize,
    min_support: usize,
) -> Vec<(usize, f64)> {
    let max_support = states.min(3).max(min_support);
    let m = rng.random_range(min_support..=max_support);
    let targets = distinct_states(rng, states, m);
    let weights: Vec<f64> = (0..m).map(|_| rng.random_range(0.05..1.0)).collect();
    let total: f64 = weights.iter().sum();
    targets
        .into_iter()
        .zip(weights.into_iter().map(|w| w / total))
        .collect()
}

impl RawModel {
    /// Each action is available with probability `p_available`; every state
    /// keeps at least one. Stochastic models have 1-3 successors per pair and
    /// (when there are two states or more) at least one pair with two.
    fn random(
        rng: &mut ChaCha8Rng,
        states: usize,
        actions: usize,
        stochastic: bool,
        p_available: f64,
    ) -> Self {
        let mut rows = Vec::with_capacity(states);
        let mut forced_branch = !stochastic || states < 2;
        for _ in 0..states {
            let mut available: Vec<bool> =
                (0..actions).map(|_| rng.random_bool(p_available)).collect();
            if !available.iter().any(|&x| x) {
                available[rng.random_range(0..actions)] = true;
            }
            let row = available
                .into_iter()
                .map(|avail| {
                    avail.then(|| {
                        if stochastic {
                            let min_support = if forced_branch { 1 } else { 2 };
                            forced_branch = true;
                            random_distribution(rng, states, min_support)
                        } else {
                            vec![(rng.random_range(0..states), 1.0)]
                        }
                    })
                })
                .collect();
            rows.push(row);
        }
        Self {
            states,
            actions,
            stochastic,
            rows,
        }
    }

    /// The posted form: `next` for deterministic models; for stochastic ones
    /// `transitions` in a shuffled order, actions by index or by name.
    fn spec(&self, rng: &mut ChaCha8Rng, n_stimuli: usize) -> ModelSpec {
        let action_names = names("act", self.actions);
        let (next, transitions) = if self.stochastic {
            let mut list = Vec::new();
            for (s, row) in self.rows.iter().enumerate() {
                for (a, succ) in row.iter().enumerate() {
                    if let Some(succ) = succ {
                        let action = if rng.random_bool(0.5) {
                            ActionRef::Index(a)
                        } else {
                            ActionRef::Name(action_names[a].clone())
                        };
                        list.push(TransitionSpec {
                            state: s,
                            action,
                            next: succ.clone(),
                        });
                    }
                }
            }
            for i in (1..list.len()).rev() {
                list.swap(i, rng.random_range(0..=i));
            }
            (None, Some(list))
        } else {
            let next = self
                .rows
                .iter()
                .map(|row| {
                    row.iter()
                        .map(|succ| succ.as_ref().map(|v| v[0].0))
                        .collect()
                })
                .collect();
            (Some(next), None)
        };
        ModelSpec {
            states: self.states,
            state_names: None,
            actions: action_names,
            next,
            transitions,
            stimuli: names("x", n_stimuli),
            basis: None,
        }
    }

    fn model(&self, rng: &mut ChaCha8Rng, n_stimuli: usize) -> TestResult<EnvModel> {
        EnvModel::from_spec(&self.spec(rng, n_stimuli))
            .map_err(|e| fail(format!("valid model refused: {e}")))
    }

    /// Pair numbering as documented: state-major, action-minor, valid pairs only.
    fn pair_index(&self) -> Vec<Vec<Option<usize>>> {
        let mut next = 0;
        self.rows
            .iter()
            .map(|row| {
                row.iter()
                    .map(|succ| {
                        succ.as_ref().map(|_| {
                            next += 1;
                            next - 1
                        })
                    })
                    .collect()
            })
            .collect()
    }

    fn n_pairs(&self) -> usize {
        self.rows.iter().flatten().filter(|x| x.is_some()).count()
    }

    fn available(&self, s: usize) -> Vec<usize> {
        (0..self.actions)
            .filter(|&a| self.rows[s][a].is_some())
            .collect()
    }

    /// A uniformly random available action per state.
    fn random_policy(&self, rng: &mut ChaCha8Rng) -> Vec<usize> {
        (0..self.states)
            .map(|s| {
                let avail = self.available(s);
                avail[rng.random_range(0..avail.len())]
            })
            .collect()
    }

    /// P^π over pairs: row (s,a), column (s', π(s')), entry P(s'|s,a).
    fn p_pi(&self, idx: &[Vec<Option<usize>>], pi: &[usize]) -> DMatrix<f64> {
        let n = self.n_pairs();
        let mut p = DMatrix::zeros(n, n);
        for s in 0..self.states {
            for a in 0..self.actions {
                let (Some(row), Some(succ)) = (idx[s][a], &self.rows[s][a]) else {
                    continue;
                };
                for &(t, prob) in succ {
                    let col =
                        idx[t][pi[t]].unwrap_or_else(|| unreachable!("π picks available actions"));
                    p[(row, col)] += prob;
                }
            }
        }
        p
    }

    /// Q^π = (I − γ P^π)⁻¹ R by a dense LU solve.
    fn dense_q(
        &self,
        idx: &[Vec<Option<usize>>],
        pi: &[usize],
        r: &[f64],
        gamma: f64,
    ) -> TestResult<Vec<f64>> {
        let n = self.n_pairs();
        let m = DMatrix::identity(n, n) - self.p_pi(idx, pi) * gamma;
        let q = m
            .lu()
            .solve(&DVector::from_column_slice(r))
            .ok_or_else(|| fail("I − γP^π is singular"))?;
        Ok(q.as_slice().to_vec())
    }
}

/// Actions of a planner policy given as pair indices.
fn policy_actions(model: &EnvModel, policy: &[u32]) -> Vec<usize> {
    policy
        .iter()
        .map(|&p| model.pair_action(p as usize))
        .collect()
}

fn policy_pairs(idx: &[Vec<Option<usize>>], pi: &[usize]) -> Vec<u32> {
    pi.iter()
        .enumerate()
        .map(|(s, &a)| {
            idx[s][a].unwrap_or_else(|| unreachable!("π picks available actions")) as u32
        })
        .collect()
}

/// Random rewards in [-5, 5], exactly zero on about a third of the pairs
/// (zeros create exact ties in Q, which exercise the tie rule).
fn random_rewards(rng: &mut ChaCha8Rng, n: usize) -> Vec<f64> {
    (0..n)
        .map(|_| {
            if rng.random_bool(0.35) {
                0.0
            } else {
                rng.random_range(-5.0..5.0)
            }
        })
        .collect()
}

/// π_{t+1} is greedy in Q with the tie rule of §2.6: a state keeps its
/// action when that action is within the tie tolerance of the max.
fn check_greedy(
    model: &EnvModel,
    before: &[u32],
    after: &[u32],
    q: &[f64],
    changes: usize,
) -> TestResult {
    let mut counted = 0;
    for s in 0..model.states() {
        let range = model.pairs_of(s);
        let max = q[range.clone()]
            .iter()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max);
        let floor = max - TIE_TOLERANCE * (1.0 + max.abs());
        let (old, new) = (before[s] as usize, after[s] as usize);
        prop_assert!(
            range.contains(&new),
            "state {}: pair {} is not one of its pairs",
            s,
            new
        );
        prop_assert!(
            q[new] >= floor,
            "state {}: Q(new) = {} is not maximal ({})",
            s,
            q[new],
            max
        );
        if q[old] >= floor {
            prop_assert_eq!(new, old, "state {}: a tied previous action must be kept", s);
        }
        counted += usize::from(new != old);
    }
    prop_assert_eq!(counted, changes, "reported policy changes");
    Ok(())
}

// ---------------------------------------------------------------------------
// 1. MCA convergence (Eqs. 1-2).
// ---------------------------------------------------------------------------

/// Random orthogonal n×n matrix: the Q of a QR of a Gaussian matrix.
fn random_orthogonal(rng: &mut ChaCha8Rng, n: usize) -> DMatrix<f64> {
    let g = DMatrix::from_fn(n, n, |_, _| gaussian(rng));
    g.qr().q()
}

fn mca_case(
    n: usize,
    seed: u64,
    scale: f64,
    gap: f64,
    spread: Vec<f64>,
    rho: Vec<f64>,
    eta_lambda_min: f64,
) -> TestResult {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut lambda = vec![scale, scale * gap];
    for i in 2..n {
        lambda.push(lambda[i - 1] * spread[i - 2]);
    }
    lambda.truncate(n);
    let lambda_max = lambda[n - 1];
    let eta = eta_lambda_min / scale;
    prop_assert!(eta * lambda_max < 0.5, "condition (1)");
    let q = random_orthogonal(&mut rng, n);
    let sqrt_c = &q
        * DMatrix::from_diagonal(&DVector::from_iterator(n, lambda.iter().map(|l| l.sqrt())))
        * q.transpose();
    let rho = &rho[..n];
    let mut drive = Drive::new(rho, eta, &mut rng);
    // Time constant of the slowest direction: 1/(η (λ_2 − λ_min)).
    let tau = 1.0 / (eta * (lambda[1] - lambda[0]));
    // 20 τ: a start almost orthogonal to v_min (D₀ is random) first has to
    // escape by noise; with 12 τ about 1 case in 10⁴ had not converged yet.
    let steps = (20.0 * tau).ceil() as usize;
    let tail = steps / 5;
    let minor = q.column(0).clone_owned();
    let mut z = DVector::zeros(n);
    let mut xi = vec![0.0; n];
    let mut mean_cos2 = 0.0;
    let mut mean_other = vec![0.0; n];
    for t in 0..steps {
        for zi in z.iter_mut() {
            *zi = gaussian(&mut rng);
        }
        let u = &sqrt_c * &z;
        for i in 0..n {
            xi[i] = rho[i] * u[i];
        }
        drive.update(&xi);
        if t >= steps - tail {
            let d = DVector::from_column_slice(drive.vector());
            mean_cos2 += minor.dot(&d).powi(2) / tail as f64;
            for (j, m) in mean_other.iter_mut().enumerate().skip(1) {
                *m += q.column(j).dot(&d).powi(2) / tail as f64;
            }
        }
    }
    let d = DVector::from_column_slice(drive.vector());
    let cos = minor.dot(&d).abs();
    prop_assert!(
        cos > 0.96,
        "final |cos(D, v_min)| = {} (λ = {:?}, η = {}, {} steps)",
        cos,
        lambda,
        eta,
        steps
    );
    prop_assert!(
        mean_cos2 > 0.96,
        "mean cos² over the last 4 τ = {} (λ = {:?})",
        mean_cos2,
        lambda
    );
    for (j, m) in mean_other.iter().enumerate().skip(1) {
        prop_assert!(
            *m < 0.04,
            "D leans to eigenvector {} (λ = {}): mean cos² = {}",
            j,
            lambda[j],
            m
        );
    }
    // The running λ₁ estimate sees the true largest eigenvalue.
    let est = drive.lambda1_estimate();
    prop_assert!(
        (est - lambda_max).abs() < 0.15 * lambda_max,
        "λ₁ estimate {} vs {}",
        est,
        lambda_max
    );
    prop_assert!(drive.condition_holds());
    Ok(())
}

proptest! {
    #![proptest_config(config(48))]

    /// For Λξ = C^{1/2} z, z ~ N(0, I), with distinct eigenvalues
    /// λ_min < λ_2 (λ_2 ≥ 1.5 λ_min) < ... and η λ_max < 0.5, D converges to
    /// ± the minor eigenvector of C and stays away from every other one.
    /// ξ itself is ρ ⊙ C^{1/2} z, so Λ = diag(1/ρ) must be applied by the rule.
    ///
    /// Tuning: with η λ_min ≤ 0.0015 the stationary spread of D around v_min
    /// is E[sin²] ≈ Σ_j η λ_min λ_j / (2(λ_j − λ_min)) ≤ 0.005 (mean cos² ≈
    /// 0.995); the run lasts 20 τ, τ = 1/(η(λ_2 − λ_min)) ≤ 2000 samples, and
    /// the last 4 τ are averaged. A wrong rule (Hebbian sign, Λ ignored, no
    /// normalisation) lands far below the 0.96 thresholds.
    #[test]
    fn mca_drive_converges_to_the_minor_eigenvector(
        n in 2usize..=4,
        seed in any::<u64>(),
        scale in 0.25f64..4.0,
        gap in 1.5f64..2.5,
        spread in prop::collection::vec(1.2f64..3.0, 2),
        rho in prop::collection::vec(0.3f64..=1.0, 4),
        eta_lambda_min in 0.001f64..0.0015,
    ) {
        mca_case(n, seed, scale, gap, spread, rho, eta_lambda_min)?;
    }
}

// ---------------------------------------------------------------------------
// 2. |D| = 1 after every update (Eq. 2).
// ---------------------------------------------------------------------------

/// Any finite number, weighted towards ordinary values, zeros and extremes.
fn stimulus_component() -> impl Strategy<Value = f64> {
    use prop::num::f64 as f;
    prop_oneof![
        4 => -10.0f64..10.0,
        2 => Just(0.0),
        1 => Just(-0.0),
        2 => f::POSITIVE | f::NEGATIVE | f::NORMAL | f::SUBNORMAL | f::ZERO,
        1 => prop_oneof![
            Just(f64::MAX),
            Just(-f64::MAX),
            Just(f64::MIN_POSITIVE),
            1e150f64..1e300,
            -1e300f64..-1e150,
        ],
    ]
}

/// Priorities in (0, 1], including tiny ones (Λ = 1/ρ huge).
fn priority() -> impl Strategy<Value = f64> {
    prop_oneof![
        3 => 0.01f64..=1.0,
        2 => Just(1.0),
        1 => 1e-300f64..1e-3,
        1 => Just(f64::MIN_POSITIVE),
    ]
}

fn drive_case() -> impl Strategy<Value = (Vec<f64>, Vec<Vec<f64>>, f64, u64)> {
    (1usize..=4).prop_flat_map(|n| {
        (
            prop::collection::vec(priority(), n),
            prop::collection::vec(prop::collection::vec(stimulus_component(), n), 1..60),
            prop_oneof![1e-6f64..=0.5, Just(0.5), Just(0.01)],
            any::<u64>(),
        )
    })
}

fn unit_drive_case(rho: Vec<f64>, stimuli: Vec<Vec<f64>>, eta: f64, seed: u64) -> TestResult {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut drive = Drive::new(&rho, eta, &mut rng);
    prop_assert!((norm(drive.vector()) - 1.0).abs() <= 1e-12);
    for (t, xi) in stimuli.iter().enumerate() {
        let r = drive.update(xi);
        let d = drive.vector();
        prop_assert!(d.iter().all(|x| x.is_finite()), "tick {}: D = {:?}", t, d);
        prop_assert!(
            (norm(d) - 1.0).abs() <= 1e-12,
            "tick {}: ‖D‖ = {} for ξ = {:?}",
            t,
            norm(d),
            xi
        );
        let terms: Vec<f64> = d
            .iter()
            .zip(xi)
            .zip(&rho)
            .map(|((d, x), p)| d * (x / p))
            .collect();
        let expected: f64 = terms.iter().sum();
        let magnitude: f64 = terms.iter().map(|x| x.abs()).sum();
        if r.is_finite() && magnitude.is_finite() {
            prop_assert!(
                (r - expected).abs() <= 1e-12 * magnitude,
                "tick {}: r = {} but D·Λξ = {}",
                t,
                r,
                expected
            );
        }
    }
    prop_assert_eq!(drive.samples(), stimuli.len() as u64);
    Ok(())
}

proptest! {
    #![proptest_config(config(256))]

    /// After every update D is finite with ‖D‖ = 1, whatever finite stimulus
    /// arrives (zeros, subnormals, ±f64::MAX) and whatever ρ ∈ (0, 1].
    /// Where r is finite it is Eq. 3 with the updated D: r = D·Λξ.
    #[test]
    fn drive_stays_a_unit_vector((rho, stimuli, eta, seed) in drive_case()) {
        unit_drive_case(rho, stimuli, eta, seed)?;
    }
}

/// The running λ₁ estimate (condition (1), §4) is the largest eigenvalue of
/// the empirical second moment of Λξ, computed here densely; the condition
/// is reported as holding exactly when η λ₁ < 0.5 for that estimate.
fn lambda1_case(rho: Vec<f64>, stimuli: Vec<Vec<f64>>, eta: f64) -> TestResult {
    let n = rho.len();
    let mut drive = Drive::from_parts(vec![1.0; n], &rho, eta);
    let mut c = DMatrix::<f64>::zeros(n, n);
    let mut max_sq: f64 = 0.0;
    for xi in &stimuli {
        drive.update(xi);
        let u = DVector::from_iterator(n, xi.iter().zip(&rho).map(|(x, p)| x / p));
        c += &u * u.transpose();
        max_sq = max_sq.max(u.norm_squared());
    }
    c /= stimuli.len() as f64;
    let mut eig: Vec<f64> = SymmetricEigen::new(c).eigenvalues.iter().copied().collect();
    eig.sort_by(|a, b| b.total_cmp(a));
    let (lambda1, lambda2) = (eig[0], eig.get(1).copied().unwrap_or(eig[0]));
    let est = drive.lambda1_estimate();
    let tiny = 1e-9 * lambda1 + 1e-12;
    // The core estimates λ₁ by a capped power iteration from (1, …, 1)/√n:
    // with λ₂ close to λ₁ and a top eigenvector nearly orthogonal to the
    // start it stops between λ₂ and λ₁ (see the ignored known-issue test at
    // the end of this file), so only a clear gap demands λ₁ itself.
    prop_assert!(
        est <= lambda1 + tiny && est >= lambda2 - tiny,
        "λ₁ estimate {} is outside [λ₂, λ₁] = [{}, {}]",
        est,
        lambda2,
        lambda1
    );
    if lambda2 <= 0.95 * lambda1 {
        prop_assert!(
            (est - lambda1).abs() <= 1e-6 * lambda1 + 1e-12,
            "λ₁ estimate {} but the second moment's largest eigenvalue is {} (λ₂ = {})",
            est,
            lambda1,
            lambda2
        );
    }
    prop_assert!((drive.max_sq_norm() - max_sq).abs() <= 1e-12 * max_sq);
    prop_assert_eq!(
        drive.condition_holds(),
        eta * est < 0.5,
        "η λ₁ = {}",
        eta * est
    );
    Ok(())
}

fn lambda1_stream() -> impl Strategy<Value = (Vec<f64>, Vec<Vec<f64>>, f64)> {
    (1usize..=4).prop_flat_map(|n| {
        let component = prop_oneof![3 => -10.0f64..10.0, 1 => Just(0.0)];
        (
            prop::collection::vec(0.05f64..=1.0, n),
            prop::collection::vec(prop::collection::vec(component, n), 1..80),
            0.001f64..=0.5,
        )
    })
}

proptest! {
    #![proptest_config(config(256))]

    /// Property 2b: the λ₁ estimate behind condition (1).
    #[test]
    fn lambda1_estimate_is_the_largest_second_moment_eigenvalue(
        (rho, stimuli, eta) in lambda1_stream(),
    ) {
        lambda1_case(rho, stimuli, eta)?;
    }
}

// ---------------------------------------------------------------------------
// 3. Indicator-basis LSTDQ is exact policy evaluation (§5).
// ---------------------------------------------------------------------------

fn indicator_case(
    seed: u64,
    states: usize,
    actions: usize,
    stochastic: bool,
    gamma: f64,
) -> TestResult {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let raw = RawModel::random(&mut rng, states, actions, stochastic, 0.7);
    let model = raw.model(&mut rng, 1)?;
    let idx = raw.pair_index();
    for (s, row) in idx.iter().enumerate() {
        for (a, &p) in row.iter().enumerate() {
            prop_assert_eq!(model.pair(s, a), p, "pair numbering of ({}, {})", s, a);
        }
    }
    prop_assert_eq!(model.n_pairs(), raw.n_pairs());
    prop_assert_eq!(model.is_deterministic(), !stochastic || states < 2);
    let pi = raw.random_policy(&mut rng);
    let r = random_rewards(&mut rng, raw.n_pairs());
    let ctx = PlanningModel::new(model, Basis::Indicator);
    let before = policy_pairs(&idx, &pi);
    let mut planner = Planner::new(&ctx, before.clone());
    let out = planner
        .update(&ctx, &r, gamma, 1e-6, &mut rng)
        .map_err(|e| fail(format!("update failed: {e}")))?;
    let want = raw.dense_q(&idx, &pi, &r, gamma)?;
    assert_close(planner.q(), &want, 1e-8, "Q")?;
    // Fig. 2d: the first error is ‖Q − 0‖₂.
    let q_norm = norm(planner.q());
    prop_assert!((out.lstdq_error - q_norm).abs() <= 1e-12 * (1.0 + q_norm));
    check_greedy(
        ctx.model(),
        &before,
        planner.policy(),
        planner.q(),
        out.policy_changes,
    )
}

proptest! {
    #![proptest_config(config(128))]

    /// Deterministic models (functional-graph engine): Q = (I − γP^π)⁻¹R.
    #[test]
    fn indicator_lstdq_is_exact_on_deterministic_models(
        seed in any::<u64>(), states in 1usize..=12, actions in 1usize..=4, gamma in 0.0f64..0.99,
    ) {
        indicator_case(seed, states, actions, false, gamma)?;
    }

    /// Stochastic models (Gauss–Seidel engine): Q = (I − γP^π)⁻¹R.
    #[test]
    fn indicator_lstdq_is_exact_on_stochastic_models(
        seed in any::<u64>(), states in 1usize..=12, actions in 1usize..=4, gamma in 0.0f64..0.99,
    ) {
        indicator_case(seed, states, actions, true, gamma)?;
    }
}

// ---------------------------------------------------------------------------
// 4. The feature (PVF / custom) engine.
// ---------------------------------------------------------------------------

/// Perturbs the rewards of one or two pairs, so that the greedy policy
/// usually changes in only a few states (the Sherman–Morrison path).
fn nudge_rewards(rng: &mut ChaCha8Rng, r: &mut [f64]) {
    for _ in 0..rng.random_range(1..=2) {
        let p = rng.random_range(0..r.len());
        r[p] = rng.random_range(-5.0..5.0);
    }
}

/// Successive updates with one-hot state features scaled by c_s ≠ 0: the
/// block basis spans every valid pair, so LSTDQ must equal Q^π each time.
fn spanning_feature_case(
    seed: u64,
    states: usize,
    actions: usize,
    stochastic: bool,
    gamma: f64,
    updates: usize,
) -> TestResult<PlannerStats> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let raw = RawModel::random(&mut rng, states, actions, stochastic, 0.75);
    let model = raw.model(&mut rng, 1)?;
    let idx = raw.pair_index();
    let state_features: Vec<Vec<f64>> = (0..states)
        .map(|s| {
            let c = rng.random_range(0.5..2.0) * if rng.random_bool(0.5) { 1.0 } else { -1.0 };
            (0..states).map(|j| if j == s { c } else { 0.0 }).collect()
        })
        .collect();
    let basis = Basis::build(&BasisSpec::Custom { state_features }, &model)
        .map_err(|e| fail(format!("basis refused: {e}")))?;
    let ctx = PlanningModel::new(model, basis);
    let mut planner = Planner::new(&ctx, policy_pairs(&idx, &raw.random_policy(&mut rng)));
    let mut r = random_rewards(&mut rng, raw.n_pairs());
    for t in 0..updates {
        let before = planner.policy().to_vec();
        let pi = policy_actions(ctx.model(), &before);
        let out = planner
            .update(&ctx, &r, gamma, 1e-6, &mut rng)
            .map_err(|e| fail(format!("update {t} failed: {e}")))?;
        let want = raw.dense_q(&idx, &pi, &r, gamma)?;
        assert_close(planner.q(), &want, 1e-8, &format!("Q at update {t}"))?;
        check_greedy(
            ctx.model(),
            &before,
            planner.policy(),
            planner.q(),
            out.policy_changes,
        )?;
        nudge_rewards(&mut rng, &mut r);
    }
    Ok(planner.stats())
}

/// Runs a property by hand so that statistics can be checked over all cases.
fn run_property<S: Strategy>(cases: u32, strategy: S, test: impl Fn(S::Value) -> TestResult) {
    let mut runner = TestRunner::new(config(cases));
    if let Err(e) = runner.run(&strategy, test) {
        panic!("{e}");
    }
}

/// Property 4a. Also checks that the cases did exercise both the rank-one
/// (Sherman–Morrison) updates and the reuse of an unchanged factorisation.
#[test]
fn feature_engine_with_spanning_features_is_exact() {
    let totals = Cell::new(PlannerStats::default());
    let strategy = (
        any::<u64>(),
        2usize..=14,
        2usize..=4,
        any::<bool>(),
        0.0f64..0.99,
        4usize..=12,
    );
    run_property(
        64,
        strategy,
        |(seed, states, actions, stochastic, gamma, updates)| {
            let stats = spanning_feature_case(seed, states, actions, stochastic, gamma, updates)?;
            let mut sum = totals.get();
            sum.updates += stats.updates;
            sum.reuses += stats.reuses;
            sum.factorisations += stats.factorisations;
            sum.rank_one_updates += stats.rank_one_updates;
            totals.set(sum);
            Ok(())
        },
    );
    let totals = totals.get();
    assert!(
        totals.rank_one_updates > 0,
        "no Sherman–Morrison update was exercised: {totals:?}"
    );
    assert!(totals.reuses > 0, "no factorisation was reused: {totals:?}");
}

/// The LSTDQ fixed point for arbitrary state-block features, densely:
/// A = Φᵀ(Φ − γ P^πΦ), b = ΦᵀR, Q = Φ A⁻¹ b, with features that are zero on
/// every valid pair dropped. Returns `None` when A is ill-conditioned.
fn dense_lstdq(
    raw: &RawModel,
    idx: &[Vec<Option<usize>>],
    v: &DMatrix<f64>,
    pi: &[usize],
    r: &[f64],
    gamma: f64,
) -> Option<Vec<f64>> {
    let (n, k) = (raw.n_pairs(), v.ncols());
    let mut phi = DMatrix::zeros(n, k * raw.actions);
    for s in 0..raw.states {
        for a in 0..raw.actions {
            if let Some(p) = idx[s][a] {
                for j in 0..k {
                    phi[(p, a * k + j)] = v[(s, j)];
                }
            }
        }
    }
    let used: Vec<usize> = (0..phi.ncols())
        .filter(|&j| phi.column(j).iter().any(|&x| x != 0.0))
        .collect();
    let phi = phi.select_columns(&used);
    let a = phi.transpose() * (&phi - raw.p_pi(idx, pi) * &phi * gamma);
    let svd = a.clone().svd(false, false);
    let (max, min) = (svd.singular_values.max(), svd.singular_values.min());
    let regular = min > 1e-7 * max;
    if !regular {
        return None;
    }
    let b = phi.transpose() * DVector::from_column_slice(r);
    let w = a.lu().solve(&b)?;
    Some((phi * w).as_slice().to_vec())
}

fn arbitrary_feature_case(
    seed: u64,
    states: usize,
    actions: usize,
    stochastic: bool,
    gamma: f64,
    updates: usize,
) -> TestResult {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    // Every action available everywhere, so that each block has full rank.
    let raw = RawModel::random(&mut rng, states, actions, stochastic, 1.0);
    let model = raw.model(&mut rng, 1)?;
    let idx = raw.pair_index();
    let k = rng.random_range(1..=states);
    let v = DMatrix::from_fn(states, k, |_, _| gaussian(&mut rng));
    let rows: Vec<Vec<f64>> = (0..states)
        .map(|s| v.row(s).iter().copied().collect())
        .collect();
    let basis = Basis::build(
        &BasisSpec::Custom {
            state_features: rows,
        },
        &model,
    )
    .map_err(|e| fail(format!("basis refused: {e}")))?;
    let ctx = PlanningModel::new(model, basis);
    let mut planner = Planner::new(&ctx, policy_pairs(&idx, &raw.random_policy(&mut rng)));
    let mut r = random_rewards(&mut rng, raw.n_pairs());
    for t in 0..updates {
        let before = planner.policy().to_vec();
        let pi = policy_actions(ctx.model(), &before);
        let want = dense_lstdq(&raw, &idx, &v, &pi, &r, gamma);
        let Some(want) = want else {
            // A is (nearly) singular for this policy: the core adds a ridge,
            // which has no exact dense counterpart. Stop comparing here.
            prop_assume!(t > 0);
            break;
        };
        let out = planner
            .update(&ctx, &r, gamma, 1e-6, &mut rng)
            .map_err(|e| fail(format!("update {t} failed: {e}")))?;
        prop_assert!(
            planner.stats().ridge_used == 0,
            "ridge used although A is regular"
        );
        assert_close(planner.q(), &want, 1e-7, &format!("Q at update {t}"))?;
        check_greedy(
            ctx.model(),
            &before,
            planner.policy(),
            planner.q(),
            out.policy_changes,
        )?;
        nudge_rewards(&mut rng, &mut r);
    }
    Ok(())
}

proptest! {
    #![proptest_config(config(64))]

    /// Property 4b: with random Gaussian state features (k ≤ |S|, so the
    /// basis does not span the pairs) every update's Q is the LSTDQ solution
    /// for the policy held before it, through rebuilds and rank-one updates.
    #[test]
    fn feature_engine_solves_lstdq_for_arbitrary_features(
        seed in any::<u64>(),
        states in 2usize..=10,
        actions in 1usize..=3,
        stochastic in any::<bool>(),
        gamma in 0.0f64..0.9,
        updates in 3usize..=8,
    ) {
        arbitrary_feature_case(seed, states, actions, stochastic, gamma, updates)?;
    }
}

// ---------------------------------------------------------------------------
// 5. Proto-value functions on grid maps (§5).
// ---------------------------------------------------------------------------

/// A random `rows × cols` map whose free cells form one 4-connected
/// component of at least two cells; one free cell may carry a mark.
fn random_connected_grid(
    rng: &mut ChaCha8Rng,
    rows: usize,
    cols: usize,
    wall_p: f64,
) -> Vec<String> {
    let mut free: Vec<bool> = (0..rows * cols).map(|_| !rng.random_bool(wall_p)).collect();
    let start = rng.random_range(0..rows * cols);
    let neighbour = if start % cols + 1 < cols {
        start + 1
    } else {
        start - 1
    };
    free[start] = true;
    free[neighbour] = true;
    // Flood fill from `start`; everything unreached becomes a wall.
    let mut reached = vec![false; rows * cols];
    let mut stack = vec![start];
    reached[start] = true;
    while let Some(i) = stack.pop() {
        let (r, c) = (i / cols, i % cols);
        let mut push = |j: usize| {
            if free[j] && !reached[j] {
                reached[j] = true;
                stack.push(j);
            }
        };
        if c > 0 {
            push(i - 1);
        }
        if c + 1 < cols {
            push(i + 1);
        }
        if r > 0 {
            push(i - cols);
        }
        if r + 1 < rows {
            push(i + cols);
        }
    }
    let mut cells: Vec<char> = reached.iter().map(|&x| if x { '.' } else { '#' }).collect();
    if rng.random_bool(0.5) {
        let free_cells: Vec<usize> = (0..rows * cols).filter(|&i| reached[i]).collect();
        cells[free_cells[rng.random_range(0..free_cells.len())]] = 'a';
    }
    cells.chunks(cols).map(|row| row.iter().collect()).collect()
}

fn pvf_case(seed: u64, rows: usize, cols: usize, wall_p: f64, k_fraction: f64) -> TestResult {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let lines = random_connected_grid(&mut rng, rows, cols, wall_p);
    let grid = GridMap::parse(&lines)
        .map_err(|e| fail(format!("map refused: {e}\n{}", lines.join("\n"))))?;
    let model = grid
        .model(vec!["x".into()])
        .map_err(|e| fail(format!("grid model refused: {e}")))?;
    let n = grid.states();
    prop_assert!(n >= 2);
    let k = 1 + ((n - 1) as f64 * k_fraction).round() as usize;
    let f = proto_value_functions(&model, k).map_err(|e| fail(format!("pvf failed: {e}")))?;
    prop_assert_eq!((f.k(), f.states()), (k, n));

    // The normalised Laplacian from the map's 4-neighbourhood.
    let mut w = DMatrix::<f64>::zeros(n, n);
    for s in 0..n {
        let (r, c) = grid.cell_of(s);
        for (dr, dc) in [(0i64, 1i64), (1, 0)] {
            let (r2, c2) = (r as i64 + dr, c as i64 + dc);
            if let Some(t) = grid.state_at(r2 as usize, c2 as usize) {
                w[(s, t)] = 1.0;
                w[(t, s)] = 1.0;
            }
        }
    }
    let deg: Vec<f64> = (0..n).map(|s| w.row(s).sum()).collect();
    prop_assert!(
        deg.iter().all(|&d| d > 0.0),
        "connected map has an isolated cell"
    );
    let lap = DMatrix::from_fn(n, n, |i, j| {
        f64::from(u8::from(i == j)) - w[(i, j)] / (deg[i] * deg[j]).sqrt()
    });
    let mut spectrum: Vec<f64> = SymmetricEigen::new(lap.clone())
        .eigenvalues
        .iter()
        .copied()
        .collect();
    spectrum.sort_by(f64::total_cmp);

    let v = DMatrix::from_fn(n, k, |s, j| f.row(s)[j]);
    let gram = v.transpose() * &v;
    for i in 0..k {
        for j in 0..k {
            let expected = f64::from(u8::from(i == j));
            prop_assert!(
                (gram[(i, j)] - expected).abs() < 1e-9,
                "<v{}, v{}> = {}",
                i,
                j,
                gram[(i, j)]
            );
        }
    }
    for (j, (col, &lambda)) in v.column_iter().zip(&spectrum).enumerate() {
        let mu = col.dot(&(&lap * col));
        let residual = (&lap * col - col * mu).amax();
        prop_assert!(
            residual < 1e-8,
            "v{} is not an eigenvector: residual {}",
            j,
            residual
        );
        prop_assert!(
            (mu - lambda).abs() < 1e-8,
            "v{} has eigenvalue {}, expected the {}-th smallest {}",
            j,
            mu,
            j,
            lambda
        );
        let (hi, lo) = (col.max(), col.min());
        prop_assert!(
            hi >= -lo - 1e-12,
            "v{}: largest-magnitude entry is negative ({} vs {})",
            j,
            hi,
            lo
        );
    }
    // Connected: eigenvalue 0 is simple and its vector is D^{1/2}1 / ‖·‖, positive.
    let total: f64 = deg.iter().sum();
    for (s, d) in deg.iter().enumerate() {
        let expected = (d / total).sqrt();
        let got = f.row(s)[0];
        prop_assert!(
            (got - expected).abs() < 1e-9,
            "v0({}) = {}, expected {}",
            s,
            got,
            expected
        );
    }
    prop_assert!(
        spectrum[1] > 1e-9,
        "a connected graph has a simple zero eigenvalue"
    );
    Ok(())
}

proptest! {
    #![proptest_config(config(64))]

    /// On a connected grid the k PVFs are orthonormal eigenvectors of the
    /// normalised Laplacian (built here from the map itself), with the k
    /// smallest eigenvalues in ascending order; the first is ∝ √degree with
    /// eigenvalue 0; each is signed so its largest-magnitude entry is positive.
    #[test]
    fn pvfs_are_orthonormal_laplacian_eigenvectors(
        seed in any::<u64>(),
        rows in 2usize..=8,
        cols in 2usize..=8,
        wall_p in 0.0f64..0.5,
        k_fraction in 0.0f64..=1.0,
    ) {
        pvf_case(seed, rows, cols, wall_p, k_fraction)?;
    }
}

// ---------------------------------------------------------------------------
// 6. Malformed models are rejected (EnvModel::from_spec).
// ---------------------------------------------------------------------------

/// Injects one defect into a valid spec; returns the fragments the error
/// message must contain.
fn inject_defect(
    rng: &mut ChaCha8Rng,
    raw: &RawModel,
    spec: &mut ModelSpec,
    defect: usize,
) -> Vec<String> {
    let states = raw.states;
    let beyond = states + rng.random_range(0..5);
    if let Some(next) = spec.next.as_mut() {
        match defect % 4 {
            0 => {
                // A successor out of range.
                let s = rng.random_range(0..states);
                let a = raw.available(s)[rng.random_range(0..raw.available(s).len())];
                next[s][a] = Some(beyond);
                vec![format!(
                    "`next[{s}][{a}]` = {beyond} is out of range (states are 0..{states})"
                )]
            }
            1 => {
                // A state with no available action.
                let s = rng.random_range(0..states);
                next[s].iter_mut().for_each(|x| *x = None);
                vec![format!("state {s} has no available action")]
            }
            2 => {
                // A row of the wrong length.
                let s = rng.random_range(0..states);
                if rng.random_bool(0.5) {
                    next[s].push(Some(0));
                } else {
                    next[s].pop();
                }
                let len = next[s].len();
                vec![format!(
                    "`next[{s}]` has {len} entries, expected one per action ({})",
                    raw.actions
                )]
            }
            _ => {
                // The wrong number of rows.
                if rng.random_bool(0.5) {
                    next.push(vec![None; raw.actions]);
                } else {
                    next.pop();
                }
                vec![format!(
                    "`next` has {} rows, expected one per state ({states})",
                    next.len()
                )]
            }
        }
    } else {
        let list = spec
            .transitions
            .as_mut()
            .unwrap_or_else(|| unreachable!("one encoding is set"));
        let i = rng.random_range(0..list.len());
        let j = rng.random_range(0..list[i].next.len());
        match defect % 5 {
            0 => {
                list[i].state = beyond;
                vec![format!(
                    "`transitions[{i}].state` = {beyond} is out of range (states are 0..{states})"
                )]
            }
            1 => {
                list[i].next[j].0 = beyond;
                vec![format!(
                    "`transitions[{i}].next[{j}]` state {beyond} is out of range"
                )]
            }
            2 => {
                // Probabilities that do not sum to 1: too little, or an extra successor.
                let tr = &mut list[i];
                let unlisted = (0..states).find(|t| tr.next.iter().all(|&(u, _)| u != *t));
                match unlisted {
                    Some(t) if rng.random_bool(0.5) => {
                        tr.next.push((t, rng.random_range(0.001..=1.0)))
                    }
                    _ => {
                        let f = rng.random_range(0.0..0.999);
                        tr.next
                            .iter_mut()
                            .for_each(|(_, p)| *p = (*p * f).max(1e-3 * *p));
                    }
                }
                let sum: f64 = tr.next.iter().map(|&(_, p)| p).sum();
                vec![format!(
                    "`transitions[{i}]` probabilities sum to {sum}, not 1"
                )]
            }
            3 => {
                // A probability outside (0, 1]: negative, zero, above 1 or NaN.
                let p = match rng.random_range(0..4) {
                    0 => -rng.random_range(1e-9..=1.0),
                    1 => 0.0,
                    2 => 1.0 + rng.random_range(1e-6..=1.0),
                    _ => f64::NAN,
                };
                list[i].next[j].1 = p;
                vec![format!(
                    "`transitions[{i}].next[{j}]` probability {p} is not in (0, 1]"
                )]
            }
            _ => {
                // A state with no available action: drop all its transitions.
                let s = list[i].state;
                list.retain(|tr| tr.state != s);
                vec![format!("state {s} has no available action")]
            }
        }
    }
}

fn malformed_case(
    seed: u64,
    states: usize,
    actions: usize,
    stochastic: bool,
    defect: usize,
) -> TestResult {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let raw = RawModel::random(&mut rng, states, actions, stochastic, 0.6);
    let mut spec = raw.spec(&mut rng, 2);
    prop_assert!(
        EnvModel::from_spec(&spec).is_ok(),
        "the undamaged spec must be valid"
    );
    let fragments = inject_defect(&mut rng, &raw, &mut spec, defect);
    match EnvModel::from_spec(&spec) {
        Ok(_) => {
            return Err(fail(format!(
                "accepted a spec with a defect ({fragments:?}): {spec:?}"
            )));
        }
        Err(e) => {
            prop_assert!(
                matches!(e, AlgoError::InvalidModel(_)),
                "wrong error kind: {:?}",
                e
            );
            let msg = e.to_string();
            for fragment in &fragments {
                prop_assert!(
                    msg.contains(fragment.as_str()),
                    "{:?} should contain {:?}",
                    msg,
                    fragment
                );
            }
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(config(256))]

    /// A valid random spec is accepted; with one injected defect it is
    /// refused as an invalid model whose message names field, index and value.
    #[test]
    fn malformed_models_are_rejected(
        seed in any::<u64>(),
        states in 1usize..=6,
        actions in 1usize..=3,
        stochastic in any::<bool>(),
        defect in 0usize..20,
    ) {
        malformed_case(seed, states, actions, stochastic, defect)?;
    }
}

// ---------------------------------------------------------------------------
// 7. Agents: determinism, and no NaN.
// ---------------------------------------------------------------------------

#[derive(Debug, Clone)]
struct AgentCase {
    seed: u64,
    states: usize,
    actions: usize,
    n_stimuli: usize,
    stochastic: bool,
    basis: usize,
    eta: f64,
    gamma: f64,
    epsilon: f64,
    constant_rate: Option<f64>,
    ticks: usize,
}

fn agent_case() -> impl Strategy<Value = AgentCase> {
    (
        (
            any::<u64>(),
            2usize..=12,
            1usize..=4,
            1usize..=3,
            any::<bool>(),
            0usize..3,
        ),
        (
            prop_oneof![1e-3f64..=0.5, Just(0.5)],
            0.0f64..0.99,
            prop_oneof![Just(0.0), 0.0f64..=1.0],
            prop::option::of(0.01f64..=1.0),
            1usize..=60,
        ),
    )
        .prop_map(
            |(
                (seed, states, actions, n_stimuli, stochastic, basis),
                (eta, gamma, epsilon, constant_rate, ticks),
            )| {
                AgentCase {
                    seed,
                    states,
                    actions,
                    n_stimuli,
                    stochastic,
                    basis,
                    eta,
                    gamma,
                    epsilon,
                    constant_rate,
                    ticks,
                }
            },
        )
}

fn build_agent(
    case: &AgentCase,
    spec: &ModelSpec,
    basis: &BasisSpec,
    rho: &[f64],
) -> TestResult<Agent> {
    let model = EnvModel::from_spec(spec).map_err(|e| fail(format!("model refused: {e}")))?;
    let basis = Basis::build(basis, &model).map_err(|e| fail(format!("basis refused: {e}")))?;
    let params = AgentParams {
        eta: Some(case.eta),
        gamma: Some(case.gamma),
        priorities: Some(rho.to_vec()),
        stimulus_rate: case.constant_rate.map(StimulusRate::Constant),
        epsilon: Some(case.epsilon),
        seed: Some(case.seed),
        ..AgentParams::default()
    }
    .check(case.n_stimuli, 0)
    .map_err(|e| fail(format!("params refused: {e}")))?;
    Ok(Agent::new(
        Arc::new(PlanningModel::new(model, basis)),
        params,
    ))
}

/// Everything observable about an agent's numeric state, bit for bit.
fn fingerprint(agent: &Agent) -> (Vec<u64>, Vec<u64>, Vec<u32>, Vec<u64>) {
    let bits = |x: &[f64]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    (
        bits(agent.drive().vector()),
        bits(agent.planner().q()),
        agent.planner().policy().to_vec(),
        bits(agent.rewards()),
    )
}

fn check_finite(agent: &Agent, t: usize) -> TestResult {
    let d = agent.drive().vector();
    prop_assert!(d.iter().all(|x| x.is_finite()), "tick {}: D = {:?}", t, d);
    prop_assert!(
        (norm(d) - 1.0).abs() < 1e-12,
        "tick {}: ‖D‖ = {}",
        t,
        norm(d)
    );
    let q = agent.planner().q();
    prop_assert!(
        q.iter().all(|x| x.is_finite()),
        "tick {}: Q has a non-finite entry",
        t
    );
    prop_assert!(
        agent.rewards().iter().all(|x| x.is_finite() && *x >= 0.0),
        "tick {}: R",
        t
    );
    prop_assert!(
        agent.stimulus().table().iter().all(|x| x.is_finite()),
        "tick {}: Ξ",
        t
    );
    Ok(())
}

fn agent_determinism_case(case: AgentCase) -> TestResult {
    let mut rng = ChaCha8Rng::seed_from_u64(case.seed ^ 0x9e37_79b9_7f4a_7c15);
    let raw = RawModel::random(&mut rng, case.states, case.actions, case.stochastic, 0.7);
    let spec = raw.spec(&mut rng, case.n_stimuli);
    let basis = match case.basis {
        0 => BasisSpec::Indicator,
        1 => BasisSpec::ProtoValue {
            k: rng.random_range(1..=case.states),
        },
        _ => {
            let k = rng.random_range(1..=3);
            BasisSpec::Custom {
                state_features: (0..case.states)
                    .map(|_| (0..k).map(|_| gaussian(&mut rng)).collect())
                    .collect(),
            }
        }
    };
    let rho: Vec<f64> = (0..case.n_stimuli)
        .map(|_| rng.random_range(0.1..=1.0))
        .collect();
    let mut a = build_agent(&case, &spec, &basis, &rho)?;
    let mut b = build_agent(&case, &spec, &basis, &rho)?;
    prop_assert_eq!(fingerprint(&a), fingerprint(&b));
    let clone_at = rng.random_range(0..=case.ticks);
    let mut c: Option<Agent> = None;

    let mut prev = rng.random_range(0..case.states);
    let first_a = a
        .step(&Observation::first(prev))
        .map_err(|e| fail(format!("first step: {e}")))?;
    let first_b = b
        .step(&Observation::first(prev))
        .map_err(|e| fail(format!("first step: {e}")))?;
    prop_assert_eq!(first_a, first_b);
    for t in 0..case.ticks {
        if t == clone_at {
            c = Some(a.clone());
        }
        let state = rng.random_range(0..case.states);
        let xi: Vec<f64> = (0..case.n_stimuli)
            .map(|_| {
                if rng.random_bool(0.5) {
                    0.0
                } else {
                    2.0 * gaussian(&mut rng)
                }
            })
            .collect();
        let action_taken = rng.random_bool(0.2).then(|| {
            let avail = raw.available(prev);
            avail[rng.random_range(0..avail.len())]
        });
        let obs = Observation {
            state,
            stimulus: Some(&xi),
            action_taken,
        };
        let sa = a.step(&obs).map_err(|e| fail(format!("tick {t}: {e}")))?;
        let sb = b.step(&obs).map_err(|e| fail(format!("tick {t}: {e}")))?;
        prop_assert_eq!(sa, sb, "tick {}", t);
        prop_assert_eq!(sa.reward.to_bits(), sb.reward.to_bits());
        prop_assert!(
            sa.reward.is_finite() && sa.reward >= 0.0,
            "tick {}: |r| = {}",
            t,
            sa.reward
        );
        prop_assert!(
            sa.action < case.actions && raw.rows[state][sa.action].is_some(),
            "tick {}: action {} unavailable in {}",
            t,
            sa.action,
            state
        );
        prop_assert_eq!(fingerprint(&a), fingerprint(&b), "tick {}", t);
        if let Some(c) = c.as_mut() {
            let sc = c
                .step(&obs)
                .map_err(|e| fail(format!("clone, tick {t}: {e}")))?;
            prop_assert_eq!(sa, sc, "clone, tick {}", t);
            prop_assert_eq!(fingerprint(&a), fingerprint(c), "clone, tick {}", t);
        }
        check_finite(&a, t)?;
        prev = state;
    }
    prop_assert_eq!(a.tick(), case.ticks as u64);
    Ok(())
}

proptest! {
    #![proptest_config(config(64))]

    /// Two agents with the same seed, fed the same observations (random
    /// states, stimuli with exact zeros, sometimes a reported action_taken),
    /// give identical steps and bit-identical D, Q, π and R; so does a clone
    /// taken midway. D, Q, R and Ξ stay finite, with ‖D‖ = 1.
    #[test]
    fn agents_are_deterministic_and_finite(case in agent_case()) {
        agent_determinism_case(case)?;
    }
}

// ---------------------------------------------------------------------------
// Known issues of the core, found while writing these properties. Ignored so
// that the suite stays green; run with `--ignored` to see them fail. Each is
// phrased so that any reasonable fix (refuse the input, report an error, or
// compute the right value) makes it pass.
// ---------------------------------------------------------------------------

/// One finite but huge stimulus (‖Λξ‖² overflows f64) must not break the
/// session: it is either refused up front, or later ordinary ticks still
/// plan, with a finite λ₁ estimate. Before the fix: `Drive::update` left D
/// unchanged (its norm overflowed), the running second moment became inf
/// then NaN for good (condition (1) then read as violated forever), and
/// every later plan failed with "LSTDQ produced a non-finite Q" because
/// ‖Q_t − Q_{t+1}‖² overflowed although Q itself was finite. Now stimuli
/// beyond ±1e12 are refused.
#[test]
fn huge_finite_stimulus_does_not_break_the_session() {
    let model = EnvModel::chain(5, vec!["food".into(), "rest".into()]).expect("chain");
    let params = AgentParams {
        seed: Some(1),
        ..AgentParams::default()
    }
    .check(2, 0)
    .expect("params");
    let mut agent = Agent::new(
        Arc::new(PlanningModel::new(model, Basis::Indicator)),
        params,
    );
    agent
        .step(&Observation::first(2))
        .expect("first observation");
    let huge = agent.step(&Observation::new(2, &[1e200, 0.0]));
    if huge.is_err() && agent.tick() == 0 {
        return; // refused up front, nothing learned: fine
    }
    for t in 0..3 {
        let step = agent.step(&Observation::new(2, &[1.0, 0.0]));
        assert!(
            step.is_ok(),
            "ordinary tick {t} after a huge stimulus: {step:?}"
        );
    }
    assert!(
        agent.drive().lambda1_estimate().is_finite(),
        "λ₁ estimate is not finite"
    );
}

/// Stochastic models with γ close to 1 (γ ∈ [0, 1) is accepted): the
/// Gauss–Seidel engine used to stop at its sweep cap and silently return an
/// unconverged Q (relative error about 5e-5 at γ = 0.9999 on 3 states).
/// Either the result is exact or the update reports an error.
#[test]
fn stochastic_evaluation_near_gamma_one_is_exact_or_an_error() {
    for seed in 0..20 {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let raw = RawModel::random(&mut rng, 3, 1, true, 1.0);
        let model = raw.model(&mut rng, 1).expect("model");
        let idx = raw.pair_index();
        let pi = raw.random_policy(&mut rng);
        let r = random_rewards(&mut rng, raw.n_pairs());
        let gamma = 0.9999;
        let ctx = PlanningModel::new(model, Basis::Indicator);
        let mut planner = Planner::new(&ctx, policy_pairs(&idx, &pi));
        if planner.update(&ctx, &r, gamma, 1e-6, &mut rng).is_ok() {
            let want = raw.dense_q(&idx, &pi, &r, gamma).expect("dense solve");
            let scale = 1.0 + want.iter().fold(0.0f64, |m, x| m.max(x.abs()));
            for (g, w) in planner.q().iter().zip(&want) {
                assert!(
                    (g - w).abs() <= 1e-8 * scale,
                    "seed {seed}: Q = {g}, dense {w}"
                );
            }
        }
    }
}

/// The λ₁ estimate behind condition (1) was a power iteration started from
/// (1, …, 1)/√n and capped at 200 steps; when the second moment's top
/// eigenvector was orthogonal to that start it missed λ₁. Stimuli that always
/// have the form (a, −a) give C = a²[[1, −1], [−1, 1]], λ₁ = 2a², but the
/// estimate was 0, so `condition_holds()` said true although η λ₁ = 0.8 ≥ 0.5.
/// (When the top eigenvector is merely nearly orthogonal to the start and λ₂
/// is close to λ₁, the capped iteration stops short: about 0.7% low on a
/// random 9-sample stream with λ₂/λ₁ = 0.989.) It is now a symmetric
/// eigendecomposition, exact and cheap for small n.
#[test]
fn lambda1_estimate_sees_an_antisymmetric_stimulus() {
    let mut drive = Drive::from_parts(vec![0.6, 0.8], &[1.0, 1.0], 0.4);
    for _ in 0..10 {
        drive.update(&[1.0, -1.0]);
    }
    let est = drive.lambda1_estimate();
    assert!((est - 2.0).abs() < 1e-9, "λ₁ estimate {est}, expected 2");
    assert!(
        !drive.condition_holds(),
        "η λ₁ = 0.8 violates condition (1)"
    );
}
