//! The inner products of the continuous agent's hot loops: [`dot`], with
//! four independent accumulators so that the compiler can keep them in
//! vector registers (a plain `sum()` is one serial chain of additions), and
//! [`rows_times`], a matrix product over the sample store's rows. The
//! order of the additions is fixed, so the result is the same bits on
//! every run.

/// Σ aᵢ bᵢ over the shorter of the two slices.
#[inline(always)]
pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0.0f64; 4];
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        acc[0] += x[0] * y[0];
        acc[1] += x[1] * y[1];
        acc[2] += x[2] * y[2];
        acc[3] += x[3] * y[3];
    }
    let tail: f64 = ra.iter().zip(rb).map(|(x, y)| x * y).sum();
    (acc[0] + acc[2]) + (acc[1] + acc[3]) + tail
}

/// Rows of X summed together by [`rows_times`] (independent sums in flight).
const ROWS: usize = 4;

/// out = X M for X of `k` columns (row-major, `x.len() / k` rows) and M of
/// `k` rows and `m` columns (row-major): out[i·m + c] = Σ_j X[i][j] M[j][c].
///
/// Every entry is summed over j in order from 0, one product at a time, in
/// every path (blocks of [`ROWS`] rows × 4 columns in registers, and the
/// rows and columns left over), so the bits depend neither on the
/// blocking nor on the vector width.
#[inline(always)]
pub fn rows_times(x: &[f64], k: usize, mat: &[f64], m: usize, out: &mut [f64]) {
    if k == 0 || m == 0 {
        out.iter_mut().for_each(|o| *o = 0.0);
        return;
    }
    let rows = x.len() / k;
    let mat = &mat[..k * m];
    let out = &mut out[..rows * m];
    let entry = |xi: &[f64], c: usize| {
        xi.iter()
            .zip(mat.chunks_exact(m))
            .fold(0.0, |acc, (xj, row)| acc + xj * row[c])
    };
    let full = rows / ROWS * ROWS;
    for (xb, ob) in x[..full * k]
        .chunks_exact(ROWS * k)
        .zip(out.chunks_exact_mut(ROWS * m))
    {
        let xr: [&[f64]; ROWS] = std::array::from_fn(|r| &xb[r * k..(r + 1) * k]);
        let mut c0 = 0;
        while c0 + 4 <= m {
            let mut acc = [[0.0f64; 4]; ROWS];
            for (j, row) in mat.chunks_exact(m).enumerate() {
                let mc: &[f64; 4] = row[c0..c0 + 4].try_into().unwrap_or(&[0.0; 4]);
                for (acc, xr) in acc.iter_mut().zip(&xr) {
                    let xv = xr[j];
                    for (a, mv) in acc.iter_mut().zip(mc) {
                        *a += xv * mv;
                    }
                }
            }
            for (r, acc) in acc.iter().enumerate() {
                ob[r * m + c0..r * m + c0 + 4].copy_from_slice(acc);
            }
            c0 += 4;
        }
        for c in c0..m {
            for (r, xi) in xr.iter().enumerate() {
                ob[r * m + c] = entry(xi, c);
            }
        }
    }
    for (xi, oi) in x[full * k..rows * k]
        .chunks_exact(k)
        .zip(out[full * m..].chunks_exact_mut(m))
    {
        for (c, o) in oi.iter_mut().enumerate() {
            *o = entry(xi, c);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{dot, rows_times};

    /// Every entry of [`rows_times`] is the serial sum over j, whatever the
    /// number of rows and columns (blocks and leftovers alike).
    #[test]
    fn rows_times_is_the_serial_sum_in_every_block() {
        let k = 7;
        for rows in [0usize, 1, 3, 4, 5, 9] {
            for m in [1usize, 3, 4, 6, 8] {
                let x: Vec<f64> = (0..rows * k)
                    .map(|i| ((i * 13 % 17) as f64).sin())
                    .collect();
                let mat: Vec<f64> = (0..k * m).map(|i| ((i * 7 % 11) as f64).cos()).collect();
                let mut out = vec![f64::NAN; rows * m];
                rows_times(&x, k, &mat, m, &mut out);
                for i in 0..rows {
                    for c in 0..m {
                        let serial = (0..k).fold(0.0, |acc, j| acc + x[i * k + j] * mat[j * m + c]);
                        assert_eq!(
                            out[i * m + c].to_bits(),
                            serial.to_bits(),
                            "rows {rows}, m {m}, ({i}, {c})"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn dot_matches_the_serial_sum_on_exact_values() {
        for n in 0..20usize {
            let a: Vec<f64> = (0..n).map(|i| i as f64).collect();
            let b: Vec<f64> = (0..n).map(|i| (i % 3) as f64 - 1.0).collect();
            let serial: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
            assert_eq!(dot(&a, &b), serial, "n = {n}");
        }
        assert_eq!(dot(&[1.0, 2.0], &[3.0]), 3.0, "the shorter length");
    }
}
