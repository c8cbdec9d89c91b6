//! Summary statistics for evaluation curves: mean and standard error.

use serde::{Deserialize, Serialize};

/// The mean of a sample and its standard error. An empty sample's mean and
/// s.e. are NaN, written to JSON as `null` and read back as NaN.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MeanSe {
    #[serde(deserialize_with = "null_as_nan")]
    pub mean: f64,
    /// `s / sqrt(n)` with the unbiased sample standard deviation `s` (divisor
    /// `n - 1`); 0 when `n < 2`.
    #[serde(deserialize_with = "null_as_nan")]
    pub se: f64,
    /// Sample size.
    pub n: usize,
}

impl MeanSe {
    /// The statistics of an empty sample.
    pub fn undefined() -> Self {
        MeanSe {
            mean: f64::NAN,
            se: f64::NAN,
            n: 0,
        }
    }
}

fn null_as_nan<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// Per-column mean and (population) standard deviation of `rows`, each
/// `dim` wide: the observation statistics both learners standardise with.
pub fn column_mean_std<'a>(
    rows: impl IntoIterator<Item = &'a [f32]>,
    dim: usize,
) -> (Vec<f32>, Vec<f32>) {
    let (mut sum, mut sq, mut n) = (vec![0.0f64; dim], vec![0.0f64; dim], 0.0f64);
    for row in rows {
        for (i, &x) in row.iter().enumerate() {
            sum[i] += f64::from(x);
            sq[i] += f64::from(x).powi(2);
        }
        n += 1.0;
    }
    let n = n.max(1.0);
    let mean: Vec<f32> = sum.iter().map(|s| (s / n) as f32).collect();
    let std = sq
        .iter()
        .zip(&mean)
        .map(|(s, &m)| (s / n - f64::from(m).powi(2)).max(0.0).sqrt() as f32)
        .collect();
    (mean, std)
}

/// Spearman's rank correlation of paired samples (average ranks for ties);
/// `None` with fewer than two pairs or a sample without spread.
pub fn spearman(xs: &[f64], ys: &[f64]) -> Option<f64> {
    fn ranks(v: &[f64]) -> Vec<f64> {
        let mut order: Vec<usize> = (0..v.len()).collect();
        order.sort_by(|&a, &b| v[a].total_cmp(&v[b]));
        let mut ranks = vec![0.0; v.len()];
        let mut i = 0;
        while i < order.len() {
            let mut j = i;
            while j + 1 < order.len() && v[order[j + 1]] == v[order[i]] {
                j += 1;
            }
            for &k in &order[i..=j] {
                ranks[k] = (i + j) as f64 / 2.0 + 1.0;
            }
            i = j + 1;
        }
        ranks
    }
    if xs.len() != ys.len() || xs.len() < 2 {
        return None;
    }
    let (rx, ry) = (ranks(xs), ranks(ys));
    let mean = (xs.len() as f64 + 1.0) / 2.0;
    let (mut cov, mut vx, mut vy) = (0.0, 0.0, 0.0);
    for (a, b) in rx.iter().zip(&ry) {
        cov += (a - mean) * (b - mean);
        vx += (a - mean).powi(2);
        vy += (b - mean).powi(2);
    }
    (vx > 0.0 && vy > 0.0).then(|| cov / (vx * vy).sqrt())
}

/// Mean and standard error of `xs`; `None` for an empty sample.
pub fn mean_se(xs: &[f64]) -> Option<MeanSe> {
    let n = xs.len();
    if n == 0 {
        return None;
    }
    let mean = xs.iter().sum::<f64>() / n as f64;
    let se = if n < 2 {
        0.0
    } else {
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        (var / n as f64).sqrt()
    };
    Some(MeanSe { mean, se, n })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spearman_ranks_with_ties_and_refuses_what_has_no_spread() {
        let xs = [1.0, 2.0, 3.0, 4.0];
        assert_eq!(spearman(&xs, &[10.0, 20.0, 30.0, 40.0]), Some(1.0));
        assert_eq!(spearman(&xs, &[4.0, 3.0, 2.0, 1.0]), Some(-1.0));
        // Monotone but not linear: still 1.
        assert_eq!(spearman(&xs, &[1.0, 8.0, 27.0, 1000.0]), Some(1.0));
        // Ties share their average rank: ranks (1, 2.5, 2.5, 4) against (1, 2, 3, 4).
        let rho = spearman(&xs, &[0.0, 5.0, 5.0, 9.0]).unwrap();
        assert!((rho - 0.9486832980505138).abs() < 1e-12, "{rho}");
        assert_eq!(spearman(&xs, &[1.0; 4]), None);
        assert_eq!(spearman(&[1.0], &[1.0]), None);
    }

    #[test]
    fn mean_and_standard_error_of_a_fixed_sample() {
        // mean 5, deviations -3 -1 1 3, variance 20/3, se sqrt(20/3/4) = sqrt(5/3).
        let m = mean_se(&[2.0, 4.0, 6.0, 8.0]).unwrap();
        assert_eq!(m.mean, 5.0);
        assert!((m.se - (5.0f64 / 3.0).sqrt()).abs() < 1e-12);
        assert_eq!(m.n, 4);
        let one = mean_se(&[3.5]).unwrap();
        assert_eq!((one.mean, one.se), (3.5, 0.0));
        assert!(mean_se(&[]).is_none());
    }

    #[test]
    fn column_statistics_of_fixed_rows() {
        let rows = [[1.0f32, 5.0], [3.0, 5.0]];
        let (mean, std) = column_mean_std(rows.iter().map(|r| &r[..]), 2);
        assert_eq!((mean, std), (vec![2.0, 5.0], vec![1.0, 0.0]));
    }
}
