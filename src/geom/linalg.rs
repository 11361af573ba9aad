//! Small dense linear systems of the registration solvers (ICP point-to-plane, the surface
//! refinement): at most 7 unknowns (rotation, translation, scale).

/// Solves the leading `dim`×`dim` system `a x = b` (`dim` ≤ 7) by Gaussian elimination with
/// partial pivoting; `None` when a pivot is at most `rel_pivot` times the largest diagonal
/// entry (a degenerate system) or the solution is not finite.
// Index loops mirror the matrix algebra.
#[allow(clippy::needless_range_loop)]
pub(crate) fn solve(
    mut a: [[f64; 7]; 7],
    mut b: [f64; 7],
    dim: usize,
    rel_pivot: f64,
) -> Option<[f64; 7]> {
    let scale = (0..dim).map(|i| a[i][i].abs()).fold(0.0, f64::max);
    if scale.is_nan() || scale <= 0.0 {
        return None;
    }
    for col in 0..dim {
        let piv = (col..dim).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[piv][col].abs() <= rel_pivot * scale {
            return None;
        }
        a.swap(col, piv);
        b.swap(col, piv);
        for r in col + 1..dim {
            let f = a[r][col] / a[col][col];
            for k in col..dim {
                a[r][k] -= f * a[col][k];
            }
            b[r] -= f * b[col];
        }
    }
    let mut x = [0.0; 7];
    for r in (0..dim).rev() {
        let s: f64 = (r + 1..dim).map(|k| a[r][k] * x[k]).sum();
        x[r] = (b[r] - s) / a[r][r];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn solves_a_pivoting_system_and_refuses_a_singular_one() {
        let mut a = [[0.0; 7]; 7];
        a[0] = [0.0, 2.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        a[1] = [3.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let x = solve(a, [4.0, 5.0, 0.0, 0.0, 0.0, 0.0, 0.0], 2, 1e-12).expect("regular");
        assert!(
            (x[0] - 1.0).abs() < 1e-12 && (x[1] - 2.0).abs() < 1e-12,
            "{x:?}"
        );
        a[1] = [0.0, 4.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        assert!(solve(a, [4.0, 8.0, 0.0, 0.0, 0.0, 0.0, 0.0], 2, 1e-12).is_none());
    }
}
