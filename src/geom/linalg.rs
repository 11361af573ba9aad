//! Sylva's dense linear algebra, on nalgebra: the small systems of the registration solvers
//! (ICP point-to-plane, the surface refinement: at most 7 unknowns), the circle fits' 3×3
//! systems and the symmetric eigenproblem of Horn's quaternion method.
//!
//! Three pieces stay hand-written, each for a measured or structural reason:
//! - [`super::symmetric_eigen3`], the closed-form 3×3 eigen-decomposition used once per point
//!   for normals and eigen-features (see its module for the timing against nalgebra);
//! - [`gemm`], f32 matrix products through `matrixmultiply`'s `sgemm` (what nalgebra itself
//!   calls) behind a checked slice-and-stride interface, for the NeRF's layers and LPIPS;
//! - `splat::cpu::linalg`, the CPU twin of the splatting kernels' matrix and quaternion maths,
//!   which follows the WGSL operation for operation so the two agree to float rounding.

use nalgebra::{DMatrix, DVector, Matrix4};

/// Solves the leading `dim`×`dim` system `a x = b` (`dim` ≤ 7) by LU decomposition with
/// partial pivoting; `None` when a pivot is at most `rel_pivot` times the largest diagonal
/// entry (a degenerate system) or the solution is not finite.
pub(crate) fn solve(a: [[f64; 7]; 7], b: [f64; 7], dim: usize, rel_pivot: f64) -> Option<[f64; 7]> {
    let scale = (0..dim).map(|i| a[i][i].abs()).fold(0.0, f64::max);
    if scale.is_nan() || scale <= 0.0 {
        return None;
    }
    let lu = DMatrix::from_fn(dim, dim, |r, c| a[r][c]).lu();
    if lu
        .u()
        .diagonal()
        .iter()
        .any(|p| p.is_nan() || p.abs() <= rel_pivot * scale)
    {
        return None;
    }
    let x = lu.solve(&DVector::from_column_slice(&b[..dim]))?;
    let mut out = [0.0; 7];
    out[..dim].copy_from_slice(x.as_slice());
    out.iter().all(|v| v.is_finite()).then_some(out)
}

/// Solves the 3×3 system `a x = b` (row-major `a[i][j]`); `None` when it is singular or the
/// solution is not finite. The caller judges near-singularity on its own scale first.
pub(crate) fn solve3(a: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let m = nalgebra::Matrix3::from_fn(|r, c| a[r][c]);
    let x = m.lu().solve(&nalgebra::Vector3::from(b))?;
    let out = [x[0], x[1], x[2]];
    out.iter().all(|v| v.is_finite()).then_some(out)
}

/// The unit eigenvector of the largest eigenvalue of the symmetric 4×4 matrix `a` (row-major);
/// its sign is arbitrary.
pub(crate) fn top_eigenvector4(a: [[f64; 4]; 4]) -> [f64; 4] {
    let eig = Matrix4::from_fn(|r, c| a[r][c]).symmetric_eigen();
    let top = (0..4)
        .max_by(|&i, &j| eig.eigenvalues[i].total_cmp(&eig.eigenvalues[j]))
        .unwrap_or(0);
    let v = eig.eigenvectors.column(top);
    [v[0], v[1], v[2], v[3]]
}

/// `c += A B` in f32 with `A` m × k and `B` k × n given as (slice, row stride, column stride)
/// and `c` row-major m × n, through `matrixmultiply`'s `sgemm` (the crate the project has
/// through nalgebra): the NeRF's layers and LPIPS's convolutions. Panics when a slice is too
/// short for its shape and strides.
pub fn gemm(
    m: usize,
    k: usize,
    n: usize,
    a: (&[f32], isize, isize),
    b: (&[f32], isize, isize),
    c: &mut [f32],
) {
    if m == 0 || k == 0 || n == 0 {
        return;
    }
    let reach = |rows: usize, cols: usize, rs: isize, cs: isize| {
        (rows - 1) * rs as usize + (cols - 1) * cs as usize + 1
    };
    assert!(a.0.len() >= reach(m, k, a.1, a.2), "gemm: A too short");
    assert!(b.0.len() >= reach(k, n, b.1, b.2), "gemm: B too short");
    assert!(c.len() >= m * n, "gemm: C too short");
    // SAFETY: the asserts above keep every element read or written inside the slices, and
    // `c` does not overlap `a` or `b` (it is borrowed mutably).
    unsafe {
        matrixmultiply::sgemm(
            m,
            k,
            n,
            1.0,
            a.0.as_ptr(),
            a.1,
            a.2,
            b.0.as_ptr(),
            b.1,
            b.2,
            1.0,
            c.as_mut_ptr(),
            n as isize,
            1,
        );
    }
}
