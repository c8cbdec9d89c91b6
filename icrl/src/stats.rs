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
