//! Small dense 3×3 / 2×3 helpers in f64 and the quaternion → rotation map with its
//! vector-Jacobian product (quaternion order (w, x, y, z), docs/splatting.md "Model").
//!
//! Hand-written rather than glam or nalgebra on purpose: this is the CPU twin of the
//! projection kernels (`shaders/project*.wgsl`), and each helper performs the kernel's
//! operations in the kernel's order and layout (row-major 2×3 Jacobians, which neither crate
//! has), so the twin tests compare the two to float rounding. The rest of Sylva's dense
//! linear algebra is nalgebra's (`geom::linalg`).

/// A 3×3 matrix, row-major.
pub type Mat3 = [[f64; 3]; 3];
/// A 2×3 matrix, row-major (the projection Jacobian and its products).
pub type Mat23 = [[f64; 3]; 2];

/// `a · b` for 3×3 matrices.
pub fn mul33(a: &Mat3, b: &Mat3) -> Mat3 {
    let mut m = [[0.0; 3]; 3];
    for (i, row) in m.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    m
}

/// `a · b` for a 2×3 by 3×3 product.
pub fn mul23_33(a: &Mat23, b: &Mat3) -> Mat23 {
    let mut m = [[0.0; 3]; 2];
    for (i, row) in m.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    m
}

/// Transpose of a 3×3 matrix.
pub fn transpose(a: &Mat3) -> Mat3 {
    let mut m = [[0.0; 3]; 3];
    for (i, row) in m.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = a[j][i];
        }
    }
    m
}

/// `a · v`.
pub fn mul_vec(a: &Mat3, v: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| a[i][0] * v[0] + a[i][1] * v[1] + a[i][2] * v[2])
}

/// `aᵀ · v`.
pub fn mul_t_vec(a: &Mat3, v: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|j| a[0][j] * v[0] + a[1][j] * v[1] + a[2][j] * v[2])
}

/// Dot product.
pub fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Rotation matrix of a unit quaternion (w, x, y, z).
pub fn quat_to_mat(q: [f64; 4]) -> Mat3 {
    quat_rows(q)
}

/// Rotation matrix (row-major) of the unit quaternion (w, x, y, z) in the quaternion's own
/// float type: the one formula behind [`quat_to_mat`], COLMAP's `qvec` rotation
/// (`cameras::rotation_from_qvec`) and the f32 densification's `strategy::quat_to_matrix`.
pub fn quat_rows<T>([w, x, y, z]: [T; 4]) -> [[T; 3]; 3]
where
    T: Copy
        + From<f32>
        + std::ops::Add<Output = T>
        + std::ops::Sub<Output = T>
        + std::ops::Mul<Output = T>,
{
    let (one, two) = (T::from(1.0), T::from(2.0));
    [
        [
            one - two * (y * y + z * z),
            two * (x * y - w * z),
            two * (x * z + w * y),
        ],
        [
            two * (x * y + w * z),
            one - two * (x * x + z * z),
            two * (y * z - w * x),
        ],
        [
            two * (x * z - w * y),
            two * (y * z + w * x),
            one - two * (x * x + y * y),
        ],
    ]
}

/// Given `g = dL/dR` for `R = quat_to_mat(q)`, returns `dL/dq` (q treated as free, i.e. before
/// any normalisation).
pub fn quat_to_mat_vjp(q: [f64; 4], g: &Mat3) -> [f64; 4] {
    let [w, x, y, z] = q;
    let dw =
        2.0 * (-z * g[0][1] + y * g[0][2] + z * g[1][0] - x * g[1][2] - y * g[2][0] + x * g[2][1]);
    let dx = 2.0
        * (y * g[0][1] + z * g[0][2] + y * g[1][0] - 2.0 * x * g[1][1] - w * g[1][2]
            + z * g[2][0]
            + w * g[2][1]
            - 2.0 * x * g[2][2]);
    let dy = 2.0
        * (-2.0 * y * g[0][0] + x * g[0][1] + w * g[0][2] + x * g[1][0] + z * g[1][2]
            - w * g[2][0]
            + z * g[2][1]
            - 2.0 * y * g[2][2]);
    let dz = 2.0
        * (-2.0 * z * g[0][0] - w * g[0][1] + x * g[0][2] + w * g[1][0] - 2.0 * z * g[1][1]
            + y * g[1][2]
            + x * g[2][0]
            + y * g[2][1]);
    [dw, dx, dy, dz]
}

/// Normalises `v` (any length) and returns (unit vector, length). A zero vector yields
/// `([1, 0, ...], 0)`-free behaviour is the caller's business: length 0 is returned as is.
pub fn normalise4(v: [f64; 4]) -> ([f64; 4], f64) {
    let n = (v.iter().map(|a| a * a).sum::<f64>()).sqrt();
    if n > 0.0 {
        (v.map(|a| a / n), n)
    } else {
        ([1.0, 0.0, 0.0, 0.0], 0.0)
    }
}

/// Backward of `u = v / |v|`: given `dL/du`, returns `dL/dv = (g − u (u·g)) / |v|`.
pub fn normalise_vjp<const N: usize>(u: [f64; N], len: f64, g: [f64; N]) -> [f64; N] {
    if len <= 0.0 {
        return [0.0; N];
    }
    let ug: f64 = u.iter().zip(g.iter()).map(|(a, b)| a * b).sum();
    let mut out = [0.0; N];
    for k in 0..N {
        out[k] = (g[k] - u[k] * ug) / len;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quat_matrix_is_orthonormal_and_vjp_matches_fd() {
        let (q, _) = normalise4([0.7, -0.3, 0.5, 0.2]);
        let r = quat_to_mat(q);
        let rrt = mul33(&r, &transpose(&r));
        for (i, row) in rrt.iter().enumerate() {
            for (j, v) in row.iter().enumerate() {
                let e = if i == j { 1.0 } else { 0.0 };
                assert!((v - e).abs() < 1e-12);
            }
        }
        let g = [[0.3, -1.0, 0.2], [0.5, 0.7, -0.4], [-0.9, 0.1, 0.6]];
        let f = |q: [f64; 4]| {
            let r = quat_to_mat(q);
            (0..3)
                .flat_map(|i| (0..3).map(move |j| (i, j)))
                .map(|(i, j)| g[i][j] * r[i][j])
                .sum::<f64>()
        };
        let an = quat_to_mat_vjp(q, &g);
        for k in 0..4 {
            let (mut qp, mut qm) = (q, q);
            qp[k] += 1e-6;
            qm[k] -= 1e-6;
            let fd = (f(qp) - f(qm)) / 2e-6;
            assert!((fd - an[k]).abs() < 1e-7, "k={k} fd={fd} an={}", an[k]);
        }
    }
}
