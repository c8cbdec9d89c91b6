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
}
