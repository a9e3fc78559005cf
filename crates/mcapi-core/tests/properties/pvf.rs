//! Property 5: proto-value functions on grid maps (§5).

use super::*;

/// A random `rows × cols` map whose free cells form one 4-connected
/// component of at least two cells; one free cell may carry a mark.
pub(crate) fn random_connected_grid(
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

pub(crate) fn pvf_case(
    seed: u64,
    rows: usize,
    cols: usize,
    wall_p: f64,
    k_fraction: f64,
) -> TestResult {
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
