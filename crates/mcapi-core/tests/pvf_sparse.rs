//! The sparse PVF solver (`basis::sparse_pvfs`, docs/algorithm.md §5)
//! against the dense one (`SymmetricEigen` of the whole Laplacian) where both
//! run. Grids have repeated eigenvalues, so individual eigenvectors are not
//! unique: the tests compare the eigenvalues directly and the spanned
//! subspaces by the sine of their largest principal angle, which is the
//! projector distance ‖U Uᵀ − V Vᵀ‖₂ (both bases orthonormal). Each case
//! checks that λ_k < λ_{k+1} by a clear gap, so the k-dimensional subspace is
//! unique and the comparison can fail.

use mcapi_core::basis::{DENSE_PVF_MAX_STATES, StateGraph, proto_value_functions, sparse_pvfs};
use mcapi_core::model::three_room;
use mcapi_core::{EnvModel, GridMap};
use nalgebra::{DMatrix, SymmetricEigen};

/// Eigenvalues ascending and the matching orthonormal eigenvectors (columns)
/// of the dense Laplacian.
fn dense(graph: &StateGraph) -> (Vec<f64>, DMatrix<f64>) {
    let eig = SymmetricEigen::new(graph.dense_laplacian());
    let n = eig.eigenvalues.len();
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let values = order.iter().map(|&i| eig.eigenvalues[i]).collect();
    let vectors = DMatrix::from_fn(n, n, |r, c| eig.eigenvectors[(r, order[c])]);
    (values, vectors)
}

/// sin of the largest principal angle between the column spaces of two
/// orthonormal n × k bases: ‖(I − U Uᵀ) V‖₂, accurate for small angles
/// (unlike √(1 − cos²)).
fn subspace_distance(u: &DMatrix<f64>, v: &DMatrix<f64>) -> f64 {
    let outside = v - u * u.tr_mul(v);
    outside.singular_values().max()
}

/// Row-major `states × k` features as an n × k matrix.
fn as_matrix(features: &[f64], n: usize, k: usize) -> DMatrix<f64> {
    DMatrix::from_fn(n, k, |s, j| features[s * k + j])
}

fn grid_model(text: &str) -> EnvModel {
    GridMap::from_text(text)
        .expect("grid")
        .model(vec!["x".into()])
        .expect("model")
}

fn open_grid(rows: usize, cols: usize) -> String {
    let mut text = String::new();
    for _ in 0..rows {
        text.push_str(&".".repeat(cols));
        text.push('\n');
    }
    text
}

/// Compares the sparse solver with the dense one on `model`'s graph.
fn agree(model: &EnvModel, k: usize, label: &str) {
    let graph = StateGraph::of(model);
    let n = graph.states();
    let (lambda, u) = dense(&graph);
    assert!(
        lambda[k] - lambda[k - 1] > 1e-4,
        "{label}: pick k where the spectrum has a gap (λ_k = {}, λ_k+1 = {})",
        lambda[k - 1],
        lambda[k]
    );
    let repeated = (1..k).filter(|&j| lambda[j] - lambda[j - 1] < 1e-9).count();
    let (theta, features) = sparse_pvfs(&graph, k).expect("sparse pvfs");
    for j in 0..k {
        assert!(
            (theta[j] - lambda[j]).abs() < 1e-9,
            "{label}: eigenvalue {j}: sparse {} dense {}",
            theta[j],
            lambda[j]
        );
    }
    let v = as_matrix(features.as_slice(), n, k);
    let gram = v.tr_mul(&v) - DMatrix::identity(k, k);
    assert!(
        gram.amax() < 1e-9,
        "{label}: not orthonormal: {}",
        gram.amax()
    );
    let distance = subspace_distance(&u.columns(0, k).into_owned(), &v);
    assert!(
        distance < 1e-8,
        "{label}: subspaces differ: sin θ_max = {distance:e}"
    );
    eprintln!(
        "{label}: n = {n}, k = {k}, {repeated} repeated eigenvalues, max |Δλ| = {:e}, sin θ_max = {distance:e}",
        (0..k)
            .map(|j| (theta[j] - lambda[j]).abs())
            .fold(0.0, f64::max)
    );
}

#[test]
fn sparse_pvfs_span_the_dense_subspace_on_an_open_grid_with_repeated_eigenvalues() {
    // 32 × 32: 1,024 states, above the dense threshold; the square's symmetry
    // repeats about half of the 30 smallest eigenvalues.
    agree(&grid_model(&open_grid(32, 32)), 30, "open 32x32");
}

#[test]
fn sparse_pvfs_agree_on_the_maze_a_chain_and_a_rectangle() {
    agree(&three_room().model, 30, "three-room");
    agree(&three_room().model, 10, "three-room k=10");
    let chain = EnvModel::chain(900, vec!["x".into()]).expect("chain");
    agree(&chain, 30, "chain 900");
    agree(&grid_model(&open_grid(20, 45)), 20, "open 20x45");
}

#[test]
fn sparse_pvfs_find_every_component_of_a_disconnected_graph() {
    // Two rooms with no door and an isolated cell: the eigenvalue 0 has one
    // copy per connected component with an edge.
    let mut text = String::new();
    for r in 0..20 {
        let row: String = (0..41)
            .map(|c| {
                if c == 20 || (r == 19 && c == 40) {
                    '#'
                } else {
                    '.'
                }
            })
            .collect();
        text.push_str(&row);
        text.push('\n');
    }
    text.push_str(&format!("{}.\n", "#".repeat(40)));
    let model = grid_model(&text);
    let graph = StateGraph::of(&model);
    let (lambda, _) = dense(&graph);
    assert!(
        lambda[1].abs() < 1e-12 && lambda[2] > 1e-6,
        "{:?}",
        &lambda[..3]
    );
    agree(&model, 12, "two rooms and an isolated cell");
}

#[test]
fn pvfs_above_the_dense_threshold_come_from_the_sparse_solver_and_are_reproducible() {
    let model = grid_model(&open_grid(30, 30));
    assert!(model.states() > DENSE_PVF_MAX_STATES);
    let a = proto_value_functions(&model, 30).expect("pvfs");
    let b = proto_value_functions(&model, 30).expect("pvfs");
    assert_eq!(a, b, "the same model gives the same bits");
    let (_, sparse) = sparse_pvfs(&StateGraph::of(&model), 30).expect("sparse");
    assert_eq!(a, sparse);
    // Each vector is signed so that its largest-magnitude entry is positive.
    for j in 0..30 {
        let pivot = (0..model.states())
            .map(|s| a.row(s)[j])
            .fold(0.0f64, |m, x| if x.abs() > m.abs() { x } else { m });
        assert!(pivot > 0.0, "vector {j}");
    }
}

/// `theta` and `features` are k orthonormal eigenpairs of the graph's
/// Laplacian with the k smallest eigenvalues (checked against the dense
/// solver's eigenvalues; the vectors need not match when λ_k repeats).
fn are_the_smallest_eigenpairs(graph: &StateGraph, k: usize, theta: &[f64], features: &[f64]) {
    let n = graph.states();
    let (lambda, _) = dense(graph);
    let v = as_matrix(features, n, k);
    let gram = v.tr_mul(&v);
    assert!(
        (gram - DMatrix::identity(k, k)).abs().max() < 1e-9,
        "orthonormal"
    );
    let lap = graph.dense_laplacian();
    for j in 0..k {
        assert!(
            (theta[j] - lambda[j]).abs() < 1e-9,
            "θ_{j} = {} vs {}",
            theta[j],
            lambda[j]
        );
        let col = v.column(j);
        let residual = (&lap * col - col * theta[j]).norm();
        assert!(residual < 1e-8, "residual of pair {j}: {residual}");
    }
}

fn doorless_rooms(rooms: usize, room: &str) -> String {
    let mut text = String::new();
    for _ in 0..rooms {
        text.push_str(room);
        text.push('\n');
        text.push_str(&"#".repeat(room.len()));
        text.push('\n');
    }
    text
}

#[test]
fn more_doorless_rooms_than_the_block_is_wide_are_solved_from_their_null_space() {
    // 267 rooms of three cells (801 states, the sparse path): eigenvalue 0
    // repeats 267 times, far beyond the block of 45 the plain iteration
    // carries, which stalls there (found by crates/mcapi-server/tests/fuzz/
    // through the API).
    let model = grid_model(&doorless_rooms(267, "a.b"));
    let graph = StateGraph::of(&model);
    assert_eq!(graph.states(), 801);
    let features = proto_value_functions(&model, 30).expect("pvfs");
    let (theta, direct) = sparse_pvfs(&graph, 30).expect("sparse");
    assert_eq!(features.as_slice(), direct.as_slice());
    are_the_smallest_eigenpairs(&graph, 30, &theta, direct.as_slice());
}

#[test]
fn identical_rooms_repeating_the_kth_eigenvalue_across_the_block_are_solved() {
    // 20 identical rooms: eigenvalues 0, 1 and 2, each 20 times. The 30
    // wanted are the 20 null vectors and 10 of the twenty at 1, which fill
    // the block of the second stage exactly.
    let model = grid_model(&doorless_rooms(20, "a.b"));
    let graph = StateGraph::of(&model);
    let (theta, features) = sparse_pvfs(&graph, 30).expect("sparse");
    are_the_smallest_eigenpairs(&graph, 30, &theta, features.as_slice());
}

/// A build budget decides only whether a build finishes: past its
/// deadline, or with its flag set, the build stops with `BuildStopped`
/// (and builds nothing); with room to spare it gives the same bits as a
/// build without a budget.
#[test]
fn a_build_budget_stops_the_sparse_solver_or_changes_nothing() {
    use std::sync::atomic::AtomicBool;
    use std::time::{Duration, Instant};

    use mcapi_core::basis::proto_value_functions_within;
    use mcapi_core::{AlgoError, BuildBudget};

    let model = grid_model(&open_grid(30, 30));
    assert!(model.states() > DENSE_PVF_MAX_STATES);
    let past = BuildBudget {
        deadline: Some(Instant::now()),
        cancelled: None,
    };
    assert!(matches!(
        proto_value_functions_within(&model, 10, past),
        Err(AlgoError::BuildStopped(_))
    ));
    let flag = AtomicBool::new(true);
    let abandoned = BuildBudget {
        deadline: None,
        cancelled: Some(&flag),
    };
    assert!(matches!(
        proto_value_functions_within(&model, 10, abandoned),
        Err(AlgoError::BuildStopped(_))
    ));
    let unset = AtomicBool::new(false);
    let roomy = BuildBudget {
        deadline: Instant::now().checked_add(Duration::from_secs(3600)),
        cancelled: Some(&unset),
    };
    let within = proto_value_functions_within(&model, 10, roomy).expect("built");
    let plain = proto_value_functions(&model, 10).expect("built");
    assert_eq!(within, plain);
}
