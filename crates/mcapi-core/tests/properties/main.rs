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

mod agents;
mod drive;
mod features;
mod indicator;
mod malformed;
mod mca;
mod models;
mod pvf;
mod regressions;

use models::*;

type TestResult<T = ()> = Result<T, TestCaseError>;

/// Proptest configuration: `cases` cases, no regression files (this suite
/// keeps no files beside its code; a failure prints its minimal input instead).
pub(crate) fn config(cases: u32) -> ProptestConfig {
    ProptestConfig {
        cases,
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

pub(crate) fn fail(msg: impl Into<String>) -> TestCaseError {
    TestCaseError::fail(msg.into())
}

pub(crate) fn gaussian(rng: &mut ChaCha8Rng) -> f64 {
    StandardNormal.sample(rng)
}

pub(crate) fn names(prefix: &str, n: usize) -> Vec<String> {
    (0..n).map(|i| format!("{prefix}{i}")).collect()
}

/// `got` equals `want` within `rel · (1 + ‖want‖∞)` componentwise.
pub(crate) fn assert_close(got: &[f64], want: &[f64], rel: f64, what: &str) -> TestResult {
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
