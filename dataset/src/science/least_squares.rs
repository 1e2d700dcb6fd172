//! Least squares of a few unknowns, from their normal equations: how every fit of a BRDF model's coefficients to
//! reference renderings is solved (the model-form oracle's tables, the trainer's uniform calibration and its
//! non-negative start).

/// Solve the small system `a x = b` (Gaussian elimination with partial pivoting); singular directions (a term
/// that is zero everywhere) get 0. The normal equations of every least-squares fit of a model's coefficients.
pub fn solve_small_system(mut a: Vec<Vec<f64>>, mut b: Vec<f64>) -> Vec<f64> {
    let n = b.len();
    for col in 0..n {
        let pivot = (col..n)
            .max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))
            .expect("non-empty");
        a.swap(col, pivot);
        b.swap(col, pivot);
        if a[col][col].abs() < 1e-300 {
            continue;
        }
        for row in col + 1..n {
            let f = a[row][col] / a[col][col];
            let (upper, lower) = a.split_at_mut(row);
            for (x, p) in lower[0][col..].iter_mut().zip(&upper[col][col..]) {
                *x -= f * p;
            }
            b[row] -= f * b[col];
        }
    }
    let mut x = vec![0.0; n];
    for row in (0..n).rev() {
        if a[row][row].abs() < 1e-300 {
            continue;
        }
        let rest: f64 = (row + 1..n).map(|k| a[row][k] * x[k]).sum();
        x[row] = (b[row] - rest) / a[row][row];
    }
    x
}

/// Minimise ‖A x − t‖² subject to x ≥ 0, given the normal equations (`ata` = AᵀA, `atb` = Aᵗt) of a few
/// unknowns. The optimum solves the unconstrained normal equations restricted to its non-zero coefficients, so
/// trying every support (2ⁿ of them; n ≤ 4 here) and keeping the best feasible solution is exact.
pub fn nonnegative_least_squares(ata: &[Vec<f64>], atb: &[f64]) -> Vec<f64> {
    let n = atb.len();
    assert!(n <= 8, "{n} unknowns: enumerating supports is for a few");
    // ‖A x − t‖² − ‖t‖² = xᵀ AᵀA x − 2 xᵀ Aᵀt.
    let objective = |x: &[f64]| {
        (0..n)
            .map(|i| x[i] * ((0..n).map(|j| ata[i][j] * x[j]).sum::<f64>() - 2.0 * atb[i]))
            .sum::<f64>()
    };
    let mut best = (vec![0.0; n], 0.0);
    for support in 1u32..1 << n {
        let idx: Vec<usize> = (0..n).filter(|&i| support & (1 << i) != 0).collect();
        let sub_a = idx
            .iter()
            .map(|&i| idx.iter().map(|&j| ata[i][j]).collect())
            .collect();
        let sub_b = idx.iter().map(|&i| atb[i]).collect();
        let sub_x = solve_small_system(sub_a, sub_b);
        // A singular support (collinear terms) solves to some finite x that need not be its optimum; it is still
        // scored by the true objective, and the optimum's own support (independent terms) is among those tried.
        if !sub_x.iter().all(|&v| v >= 0.0) {
            continue;
        }
        let mut x = vec![0.0; n];
        for (&i, v) in idx.iter().zip(sub_x) {
            x[i] = v;
        }
        let value = objective(&x);
        if value < best.1 {
            best = (x, value);
        }
    }
    best.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Normal equations of a random tall system (rows × n), with the target drawn too.
    fn normal_equations(rows: &[(Vec<f64>, f64)]) -> (Vec<Vec<f64>>, Vec<f64>) {
        let n = rows[0].0.len();
        let (mut ata, mut atb) = (vec![vec![0.0; n]; n], vec![0.0; n]);
        for (a, t) in rows {
            for i in 0..n {
                atb[i] += a[i] * t;
                for j in 0..n {
                    ata[i][j] += a[i] * a[j];
                }
            }
        }
        (ata, atb)
    }

    proptest! {
        /// The Karush–Kuhn–Tucker conditions of the constrained optimum: x ≥ 0, the gradient AᵀA x − Aᵀt is ≥ 0
        /// everywhere and 0 where x > 0; and where the unconstrained solution is already ≥ 0 it is that solution.
        #[test]
        fn nonnegative_least_squares_meets_the_optimality_conditions(
            rows in prop::collection::vec((prop::collection::vec(0.0f64..1.0, 3), -1.0f64..1.0), 8..40)
        ) {
            let (ata, atb) = normal_equations(&rows);
            let x = nonnegative_least_squares(&ata, &atb);
            let scale = atb.iter().map(|v| v.abs()).fold(1e-12, f64::max)
                + ata.iter().flatten().map(|v| v.abs()).fold(0.0, f64::max);
            for i in 0..3 {
                let gradient: f64 = (0..3).map(|j| ata[i][j] * x[j]).sum::<f64>() - atb[i];
                prop_assert!(x[i] >= 0.0);
                prop_assert!(gradient >= -1e-9 * scale, "x {x:?}, gradient[{i}] {gradient}");
                if x[i] > 0.0 {
                    prop_assert!(gradient.abs() <= 1e-9 * scale, "x {x:?}, gradient[{i}] {gradient}");
                }
            }
            let free = solve_small_system(ata.clone(), atb.clone());
            if free.iter().all(|&v| v >= 0.0) {
                for (a, b) in x.iter().zip(&free) {
                    prop_assert!((a - b).abs() <= 1e-9 * (1.0 + b.abs()), "{x:?} vs {free:?}");
                }
            }
        }
    }

    /// Two identical terms (H3's are nearly so): the optimum is not unique, but what is returned meets the
    /// optimality conditions and fits the target as well as the one term alone.
    #[test]
    fn duplicated_terms_still_give_an_optimum() {
        let rows: Vec<(Vec<f64>, f64)> = (0..12)
            .map(|k| {
                let a = 0.5 + 0.1 * k as f64;
                (vec![a, a, 1.0], 3.0 * a - 0.2)
            })
            .collect();
        let (ata, atb) = normal_equations(&rows);
        let x = nonnegative_least_squares(&ata, &atb);
        assert!(x.iter().all(|&v| v >= 0.0), "{x:?}");
        for i in 0..3 {
            let gradient: f64 = (0..3).map(|j| ata[i][j] * x[j]).sum::<f64>() - atb[i];
            assert!(
                gradient >= -1e-9 && (x[i] == 0.0 || gradient.abs() <= 1e-9),
                "x {x:?}, gradient[{i}] {gradient}"
            );
        }
        // The constant would have to be negative (−0.2): it is dropped, and a + b is the slope-only fit.
        assert_eq!(x[2], 0.0);
        let (sa, st): (f64, f64) = rows
            .iter()
            .fold((0.0, 0.0), |(s, t), (r, y)| (s + r[0] * r[0], t + r[0] * y));
        assert!((x[0] + x[1] - st / sa).abs() < 1e-9, "{x:?}");
    }

    /// A target that one term explains with a negative coefficient: that term is dropped, the rest refitted.
    #[test]
    fn a_term_that_would_go_negative_is_dropped_and_the_rest_refitted() {
        // t = 2 a − b on rows where a and b vary independently: the unconstrained fit is (2, −1).
        let rows: Vec<(Vec<f64>, f64)> = (0..20)
            .map(|k| {
                let (a, b) = (1.0 + (k % 5) as f64, 1.0 + (k / 5) as f64);
                (vec![a, b], 2.0 * a - b)
            })
            .collect();
        let (ata, atb) = normal_equations(&rows);
        let free = solve_small_system(ata.clone(), atb.clone());
        assert!((free[0] - 2.0).abs() < 1e-9 && (free[1] + 1.0).abs() < 1e-9);
        let x = nonnegative_least_squares(&ata, &atb);
        assert_eq!(x[1], 0.0);
        // With b dropped, the best a alone: Σ a t / Σ a².
        assert!((x[0] - atb[0] / ata[0][0]).abs() < 1e-12, "{x:?}");
    }
}
