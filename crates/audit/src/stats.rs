//! Small numerical helpers for the audit: Student-t tail probabilities, robust
//! location/scale, quantiles and a symmetric positive-definite solver.

/// ln Γ(x) for x > 0 (Lanczos approximation, g = 7, n = 9; |error| < 1e-13 here).
pub fn ln_gamma(x: f64) -> f64 {
    const G: f64 = 7.0;
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        // Reflection keeps the series in its accurate range.
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + G + 0.5;
    for (i, c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// Regularised incomplete beta I_x(a, b) by its continued fraction (modified Lentz).
pub fn inc_beta(x: f64, a: f64, b: f64) -> f64 {
    if x <= 0.0 {
        return 0.0;
    }
    if x >= 1.0 {
        return 1.0;
    }
    let ln_front = ln_gamma(a + b) - ln_gamma(a) - ln_gamma(b) + a * x.ln() + b * (1.0 - x).ln();
    // The fraction converges fast for x < (a+1)/(a+b+2); use the symmetry otherwise.
    if x > (a + 1.0) / (a + b + 2.0) {
        return 1.0 - inc_beta(1.0 - x, b, a);
    }
    let tiny = 1e-300;
    let mut c = 1.0;
    let mut d = 1.0 - (a + b) * x / (a + 1.0);
    if d.abs() < tiny {
        d = tiny;
    }
    d = 1.0 / d;
    let mut f = d;
    // One modified-Lentz step with coefficient `num`: the factor it multiplies f by.
    let mut step = |num: f64| {
        d = 1.0 + num * d;
        if d.abs() < tiny {
            d = tiny;
        }
        c = 1.0 + num / c;
        if c.abs() < tiny {
            c = tiny;
        }
        d = 1.0 / d;
        d * c
    };
    for m in 1..500 {
        let m = m as f64;
        // Even step.
        f *= step(m * (b - m) * x / ((a + 2.0 * m - 1.0) * (a + 2.0 * m)));
        // Odd step.
        let delta = step(-(a + m) * (a + b + m) * x / ((a + 2.0 * m) * (a + 2.0 * m + 1.0)));
        f *= delta;
        if (delta - 1.0).abs() < 1e-15 {
            break;
        }
    }
    ln_front.exp() * f / a
}

/// P(T > t) for Student's t with `df` degrees of freedom.
pub fn t_upper_tail(t: f64, df: f64) -> f64 {
    if t.is_nan() {
        return 1.0;
    }
    if t == f64::INFINITY {
        return 0.0;
    }
    if t == f64::NEG_INFINITY {
        return 1.0;
    }
    let tail = 0.5 * inc_beta(df / (df + t * t), 0.5 * df, 0.5);
    if t > 0.0 {
        tail
    } else {
        1.0 - tail
    }
}

/// Regularised upper incomplete gamma Q(a, x) (series below a+1, continued fraction above).
pub fn gamma_q(a: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 1.0;
    }
    let ln_front = -x + a * x.ln() - ln_gamma(a);
    if x < a + 1.0 {
        let (mut sum, mut term, mut ap) = (1.0 / a, 1.0 / a, a);
        for _ in 0..1000 {
            ap += 1.0;
            term *= x / ap;
            sum += term;
            if term.abs() < sum.abs() * 1e-16 {
                break;
            }
        }
        return (1.0 - sum * ln_front.exp()).clamp(0.0, 1.0);
    }
    let tiny = 1e-300;
    let mut b = x + 1.0 - a;
    let mut c = 1.0 / tiny;
    let mut d = 1.0 / b;
    let mut h = d;
    for i in 1..1000 {
        let an = -(i as f64) * (i as f64 - a);
        b += 2.0;
        d = an * d + b;
        if d.abs() < tiny {
            d = tiny;
        }
        c = b + an / c;
        if c.abs() < tiny {
            c = tiny;
        }
        d = 1.0 / d;
        let del = d * c;
        h *= del;
        if (del - 1.0).abs() < 1e-16 {
            break;
        }
    }
    (ln_front.exp() * h).clamp(0.0, 1.0)
}

/// P(χ²_df > x).
pub fn chi2_upper_tail(x: f64, df: f64) -> f64 {
    if !(x > 0.0) {
        return 1.0;
    }
    gamma_q(0.5 * df, 0.5 * x)
}

/// One-sided one-sample t-test of H0: mean ≤ 0 against mean > 0. Returns (t, p).
/// Fewer than 2 values, or zero spread, give p = 0 for a positive mean and 1 otherwise.
pub fn one_sided_t(xs: &[f64]) -> (f64, f64) {
    let n = xs.len() as f64;
    let mean = mean(xs);
    if xs.len() < 2 {
        return (f64::NAN, if mean > 0.0 && xs.len() == 1 { 0.5 } else { 1.0 });
    }
    let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
    if var <= 0.0 || !var.is_finite() {
        return (if mean > 0.0 { f64::INFINITY } else { f64::NEG_INFINITY }, if mean > 0.0 { 0.0 } else { 1.0 });
    }
    let t = mean / (var / n).sqrt();
    (t, t_upper_tail(t, n - 1.0))
}

pub fn mean(xs: &[f64]) -> f64 {
    if xs.is_empty() {
        return f64::NAN;
    }
    xs.iter().sum::<f64>() / xs.len() as f64
}

/// Linear-interpolated quantile of already sorted values (q in [0, 1]).
pub fn quantile_sorted(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let pos = q.clamp(0.0, 1.0) * (sorted.len() - 1) as f64;
    let i = pos.floor() as usize;
    let j = (i + 1).min(sorted.len() - 1);
    sorted[i] + (pos - i as f64) * (sorted[j] - sorted[i])
}

pub fn median(xs: &[f64]) -> f64 {
    let mut v: Vec<f64> = xs.iter().copied().filter(|x| x.is_finite()).collect();
    v.sort_by(|a, b| a.total_cmp(b));
    quantile_sorted(&v, 0.5)
}

/// 1.4826 · median absolute deviation: the standard deviation for Gaussian data,
/// insensitive to a minority of gross outliers.
pub fn robust_sd(xs: &[f64]) -> f64 {
    let m = median(xs);
    let dev: Vec<f64> = xs.iter().map(|x| (x - m).abs()).collect();
    1.4826 * median(&dev)
}

/// Solves `A x = b` for symmetric positive (semi)definite `A` (row-major k×k) by a
/// Jacobi-scaled Cholesky factorisation; a tiny ridge is added when `A` is singular
/// (collinear features), so directions without information stay at zero.
pub fn solve_spd(a: &[f64], b: &[f64]) -> Option<Vec<f64>> {
    let k = b.len();
    if k == 0 {
        return Some(vec![]);
    }
    let d: Vec<f64> = (0..k).map(|i| if a[i * k + i] > 0.0 { 1.0 / a[i * k + i].sqrt() } else { 0.0 }).collect();
    for ridge in [0.0, 1e-10, 1e-7, 1e-4] {
        let mut l = vec![0.0; k * k];
        let mut ok = true;
        'outer: for i in 0..k {
            for j in 0..=i {
                let mut s = a[i * k + j] * d[i] * d[j];
                if i == j {
                    s += ridge + if d[i] == 0.0 { 1.0 } else { 0.0 };
                }
                for m in 0..j {
                    s -= l[i * k + m] * l[j * k + m];
                }
                if i == j {
                    if !(s > 0.0) || !s.is_finite() {
                        ok = false;
                        break 'outer;
                    }
                    l[i * k + i] = s.sqrt();
                } else {
                    l[i * k + j] = s / l[j * k + j];
                }
            }
        }
        if !ok {
            continue;
        }
        let mut y: Vec<f64> = (0..k).map(|i| b[i] * d[i]).collect();
        for i in 0..k {
            for m in 0..i {
                y[i] -= l[i * k + m] * y[m];
            }
            y[i] /= l[i * k + i];
        }
        for i in (0..k).rev() {
            for m in i + 1..k {
                y[i] -= l[m * k + i] * y[m];
            }
            y[i] /= l[i * k + i];
        }
        return Some((0..k).map(|i| y[i] * d[i]).collect());
    }
    None
}

/// Inverse of a symmetric positive-definite matrix (column by column through [`solve_spd`]).
#[cfg(test)]
pub fn inverse_spd(a: &[f64], k: usize) -> Option<Vec<f64>> {
    let mut inv = vec![0.0; k * k];
    for j in 0..k {
        let mut e = vec![0.0; k];
        e[j] = 1.0;
        let x = solve_spd(a, &e)?;
        for i in 0..k {
            inv[i * k + j] = x[i];
        }
    }
    Some(inv)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn t_tail_matches_tables() {
        // Reference values: scipy.stats.t.sf.
        let cases = [
            (2.0, 5.0, 0.050_969_739_414_929_174),
            (1.0, 1.0, 0.25),
            (3.5, 10.0, 0.002_863_252_714_942_605),
            (-1.0, 4.0, 0.813_049_516_849_970_6),
            (8.0, 7.0, 4.557_460_585_437_679e-5),
        ];
        for (t, df, want) in cases {
            let got = t_upper_tail(t, df);
            assert!((got - want).abs() < 1e-10 * want.max(1e-3), "t={t} df={df}: {got} vs {want}");
        }
        // Large df approaches the normal tail: P(Z > 1.96) = 0.0249979.
        assert!((t_upper_tail(1.959_963_984_540_054, 1e7) - 0.025).abs() < 1e-6);
        assert!((ln_gamma(5.0) - 24f64.ln()).abs() < 1e-12);
        assert!((ln_gamma(0.5) - std::f64::consts::PI.sqrt().ln()).abs() < 1e-12);
        // scipy.stats.chi2.sf
        for (x, df, want) in
            [(3.841_458_820_694_124, 1.0, 0.05), (10.0, 3.0, 0.018_566_135_463_043_25), (0.5, 4.0, 0.973_500_978_839_256_1)]
        {
            let got = chi2_upper_tail(x, df);
            assert!((got - want).abs() < 1e-9, "chi2 {x} {df}: {got} vs {want}");
        }
    }

    #[test]
    fn one_sided_t_directions() {
        let (t, p) = one_sided_t(&[1.0, 2.0, 3.0, 4.0]);
        assert!((t - 2.5 / (1.666_666_666_666_666_7f64 / 4.0).sqrt()).abs() < 1e-12);
        // scipy.stats.t.sf(3.872983346207417, 3)
        assert!((p - 0.015_233_145_831_085_489).abs() < 1e-9, "{p}");
        let (_, p) = one_sided_t(&[-1.0, -2.0, -3.0]);
        assert!(p > 0.95);
        assert_eq!(one_sided_t(&[2.0, 2.0, 2.0]).1, 0.0);
    }

    #[test]
    fn spd_solve_and_inverse() {
        let a = [4.0, 2.0, 0.6, 2.0, 5.0, 1.0, 0.6, 1.0, 3.0];
        let x = solve_spd(&a, &[1.0, 2.0, 3.0]).unwrap();
        for i in 0..3 {
            let r: f64 = (0..3).map(|j| a[i * 3 + j] * x[j]).sum();
            assert!((r - [1.0, 2.0, 3.0][i]).abs() < 1e-12);
        }
        let inv = inverse_spd(&a, 3).unwrap();
        for i in 0..3 {
            for j in 0..3 {
                let r: f64 = (0..3).map(|m| a[i * 3 + m] * inv[m * 3 + j]).sum();
                assert!((r - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
        // Collinear columns: still a finite answer.
        let s = [1.0, 1.0, 1.0, 1.0];
        let x = solve_spd(&s, &[2.0, 2.0]).unwrap();
        assert!(x.iter().all(|v| v.is_finite()) && ((x[0] + x[1]) - 2.0).abs() < 1e-3);
        assert!((robust_sd(&[1.0, 2.0, 3.0, 4.0, 100.0]) - 1.4826).abs() < 1e-12);
    }
}
