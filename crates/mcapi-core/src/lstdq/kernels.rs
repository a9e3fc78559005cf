//! The vectorised kernels of engine 3 ([`super::features`]): b = ΦᵀR,
//! w = A⁻¹b, Q = Φw, matrix-vector products and rank-one updates, each
//! compiled for AVX-512, AVX2 and NEON and picked at run time, each summing
//! in a fixed order so the bits do not depend on the vector width.

use super::*;

/// Read-only inputs of [`feature_kernel`].
pub(super) struct FeatureKernel<'a> {
    pub(super) pair_state: &'a [u32],
    pub(super) pair_action: &'a [u32],
    /// v(s) row-major, |S|×kp, zero-padded.
    pub(super) rows_padded: &'a [f64],
    /// Row stride of `rows_padded`, a multiple of [`LANES`] ≥ k.
    pub(super) kp: usize,
    /// v_j column-major, |S|×k.
    pub(super) v_cols: &'a [f64],
    pub(super) k: usize,
    /// A⁻¹ column-major, K×K.
    pub(super) a_inv: &'a [f64],
    pub(super) r: &'a [f64],
}

/// Outputs and scratch of [`feature_kernel`].
pub(super) struct FeatureScratch<'a> {
    /// b with each action block padded to kp entries (|A|·kp).
    pub(super) b_wide: &'a mut [f64],
    pub(super) b: &'a mut [f64],
    pub(super) w: &'a mut [f64],
    /// Q(s, a) for every state and action, column-major |S|×|A|.
    pub(super) q_states: &'a mut [f64],
}

/// Lanes of the widest vector register the kernels are compiled for (8
/// doubles with AVX-512): the rows b = ΦᵀR reads are padded to a multiple,
/// so their axpys have no scalar remainder.
pub(super) const LANES: usize = 8;

/// Rows per block of [`combine_columns_into`].
pub(super) const ROW_BLOCK: usize = 16;

/// b = ΦᵀR, w = A⁻¹b, Q = Φw with the block structure φ(s,a) = e_a ⊗ v(s)
/// (docs/algorithm.md §2.6; §5, engine 3).
///
/// b gains R(s,a) v(s) in block a, pair by pair, as axpys over padded rows
/// (consecutive pairs mostly belong to different actions, so the axpys do
/// not wait for each other); w is the sum of A⁻¹'s columns weighted by b and
/// Q(·, a) = Σ_j w_(a,j) v_j over states, both by [`combine_columns_into`],
/// which keeps a block of outputs in registers while it walks the columns.
/// Every output is summed in a fixed order, so the bits do not depend on the
/// vector width: the function is compiled for AVX-512, AVX2 and NEON as well
/// and picks the best version at run time, and every version gives the same
/// results (no FMA contraction).
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+avx",
    "aarch64+neon"
))]
pub(super) fn feature_kernel<'a>(x: FeatureKernel<'a>, out: FeatureScratch<'a>, q: &mut [f64]) {
    let (k, kp) = (x.k, x.kp);
    let n = x.v_cols.len() / k;
    out.b_wide.fill(0.0);
    for ((&rp, &s), &a) in x.r.iter().zip(x.pair_state).zip(x.pair_action) {
        let (s, a) = (s as usize, a as usize);
        let block = &mut out.b_wide[a * kp..(a + 1) * kp];
        for (bj, vj) in block.iter_mut().zip(&x.rows_padded[s * kp..(s + 1) * kp]) {
            *bj += rp * vj;
        }
    }
    for (bj, wide) in out.b.chunks_exact_mut(k).zip(out.b_wide.chunks_exact(kp)) {
        bj.copy_from_slice(&wide[..k]);
    }
    combine_columns_into(out.w, x.a_inv, out.b);
    for (col, wa) in out.q_states.chunks_exact_mut(n).zip(out.w.chunks_exact(k)) {
        combine_columns_into(col, x.v_cols, wa);
    }
    for ((qp, &s), &a) in q.iter_mut().zip(x.pair_state).zip(x.pair_action) {
        *qp = out.q_states[a as usize * n + s as usize];
    }
}

/// x = M u for a square column-major M, as a sum of M's columns (vectorised;
/// AVX-512, AVX2 and NEON versions picked at run time).
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+avx",
    "aarch64+neon"
))]
pub(super) fn mat_vec(m: &[f64], u: &[f64], x: &mut [f64]) {
    combine_columns_into(x, m, u);
}

/// out = Σ_j c_j · cols_j, where `cols` holds `c.len()` columns of
/// `out.len()` entries each.
///
/// Every entry is summed from 0 in the same order: the columns four at a
/// time, out_i += (c₀a₀ᵢ + c₁a₁ᵢ) + (c₂a₂ᵢ + c₃a₃ᵢ), then the columns left
/// over one at a time. So the bits do not depend on the vector width, nor on
/// the blocking: the rows are done [`ROW_BLOCK`] at a time (then 4, then 1),
/// each block summed in registers over all columns and stored once.
#[inline(always)]
pub(super) fn combine_columns_into(out: &mut [f64], cols: &[f64], c: &[f64]) {
    let n = out.len();
    let mut i0 = 0;
    while n - i0 >= ROW_BLOCK {
        combine_rows::<ROW_BLOCK>(out, cols, c, i0);
        i0 += ROW_BLOCK;
    }
    while n - i0 >= 4 {
        combine_rows::<4>(out, cols, c, i0);
        i0 += 4;
    }
    while i0 < n {
        combine_rows::<1>(out, cols, c, i0);
        i0 += 1;
    }
}

/// Rows i0..i0+W of [`combine_columns_into`].
#[inline(always)]
pub(super) fn combine_rows<const W: usize>(out: &mut [f64], cols: &[f64], c: &[f64], i0: usize) {
    let n = out.len();
    let mut acc = [0.0f64; W];
    let mut quads = c.chunks_exact(4);
    for (q, c4) in (&mut quads).enumerate() {
        let base = 4 * q * n + i0;
        let a0 = &cols[base..base + W];
        let a1 = &cols[base + n..base + n + W];
        let a2 = &cols[base + 2 * n..base + 2 * n + W];
        let a3 = &cols[base + 3 * n..base + 3 * n + W];
        let (c0, c1, c2, c3) = (c4[0], c4[1], c4[2], c4[3]);
        for ((((o, x0), x1), x2), x3) in acc.iter_mut().zip(a0).zip(a1).zip(a2).zip(a3) {
            *o += (c0 * x0 + c1 * x1) + (c2 * x2 + c3 * x3);
        }
    }
    let done = c.len() / 4 * 4;
    for (j, &cj) in c.iter().enumerate().skip(done) {
        let base = j * n + i0;
        for (o, x) in acc.iter_mut().zip(&cols[base..base + W]) {
            *o += cj * x;
        }
    }
    out[i0..i0 + W].copy_from_slice(&acc);
}

/// M += alpha x yᵀ for a column-major M with `x.len()` rows and `y.len()`
/// columns (vectorised like [`mat_vec`]).
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+avx", "aarch64+neon"))]
pub(super) fn rank_one_update(m: &mut [f64], alpha: f64, x: &[f64], y: &[f64]) {
    for (&yj, col) in y.iter().zip(m.chunks_exact_mut(x.len())) {
        let c = alpha * yj;
        if c != 0.0 {
            for (mi, xi) in col.iter_mut().zip(x) {
                *mi += c * xi;
            }
        }
    }
}

/// A⁻¹ by LU with partial pivoting, or `None` when A is numerically singular
/// (a pivot below 1e-12 of the largest).
pub(super) fn invert_if_regular(a: &DMatrix<f64>) -> Option<DMatrix<f64>> {
    let lu = a.clone().lu();
    let u = lu.u();
    let diag = u.diagonal();
    let max = diag.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let min = diag.iter().fold(f64::INFINITY, |m, x| m.min(x.abs()));
    if !(max.is_finite() && max > 0.0 && min > 1e-12 * max) {
        return None;
    }
    lu.try_inverse()
        .filter(|inv| inv.iter().all(|x| x.is_finite()))
}
