//! The intervals figures are stated with: a Student-t 95% interval of a mean over seeds (experiment reports), and a
//! Wilson 95% interval of a success rate over pooled episodes (reports, and the language check of a sim evaluation).

use serde::{Deserialize, Serialize};
use statrs::distribution::{ContinuousCDF, Normal, StudentsT};

/// A mean with its 95% confidence interval.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Interval {
    pub mean: f64,
    pub ci95_low: f64,
    pub ci95_high: f64,
}

impl Interval {
    /// The mean of `values` with a two-sided 95% Student-t interval (n - 1 degrees of freedom). One value gives a
    /// zero-width interval: there is nothing to estimate the spread from.
    pub fn t(values: &[f64]) -> Option<Self> {
        let n = values.len();
        if n == 0 {
            return None;
        }
        let mean = values.iter().sum::<f64>() / n as f64;
        if n == 1 {
            return Some(Self { mean, ci95_low: mean, ci95_high: mean });
        }
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        let t = StudentsT::new(0.0, 1.0, (n - 1) as f64).expect("n > 1 degrees of freedom").inverse_cdf(0.975);
        let half = t * (var / n as f64).sqrt();
        Some(Self { mean, ci95_low: mean - half, ci95_high: mean + half })
    }

    /// Wilson's 95% score interval of `successes` out of `trials`.
    pub fn wilson(successes: u64, trials: u64) -> Option<Self> {
        if trials == 0 {
            return None;
        }
        let z = Normal::standard().inverse_cdf(0.975);
        let n = trials as f64;
        let p = successes as f64 / n;
        let denom = 1.0 + z * z / n;
        let centre = (p + z * z / (2.0 * n)) / denom;
        let half = z * (p * (1.0 - p) / n + z * z / (4.0 * n * n)).sqrt() / denom;
        Some(Self { mean: p, ci95_low: (centre - half).max(0.0), ci95_high: (centre + half).min(1.0) })
    }

    /// The interval cut to the range `[low, high]` its quantity can take (a t interval of three success rates
    /// near 0 can reach below 0): the mean stays.
    pub fn within(self, low: f64, high: f64) -> Self {
        Self { ci95_low: self.ci95_low.clamp(low, high), ci95_high: self.ci95_high.clamp(low, high), ..self }
    }

    pub fn contains(&self, x: f64) -> bool {
        self.ci95_low <= x && x <= self.ci95_high
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn t_interval_matches_a_hand_computation() {
        // mean 2, sample sd 1, n 3: t(0.975, 2) = 4.302653, half width 4.302653 / sqrt(3) = 2.484138.
        let i = Interval::t(&[1.0, 2.0, 3.0]).unwrap();
        assert!((i.mean - 2.0).abs() < 1e-12);
        assert!((i.ci95_high - 2.0 - 2.484138).abs() < 1e-5, "{i:?}");
        assert!((i.ci95_low - 2.0 + 2.484138).abs() < 1e-5, "{i:?}");
        assert_eq!(Interval::t(&[5.0]).unwrap(), Interval { mean: 5.0, ci95_low: 5.0, ci95_high: 5.0 });
        assert!(Interval::t(&[]).is_none());
        // Three success rates near 0 reach below it; cut to what a rate can be, the mean untouched.
        let rates = Interval::t(&[0.32, 0.08, 0.3]).unwrap();
        assert!(rates.ci95_low < 0.0, "{rates:?}");
        let cut = rates.within(0.0, 1.0);
        assert_eq!((cut.mean, cut.ci95_low, cut.ci95_high), (rates.mean, 0.0, rates.ci95_high));
    }

    #[test]
    fn wilson_interval_matches_published_values() {
        // 8 of 10: Wilson 95% interval 0.4902 to 0.9433 (Newcombe 1998, and every calculator).
        let i = Interval::wilson(8, 10).unwrap();
        assert!((i.ci95_low - 0.4902).abs() < 1e-4 && (i.ci95_high - 0.9433).abs() < 1e-4, "{i:?}");
        // 0 of 50 still has an upper bound (0.0713).
        let i = Interval::wilson(0, 50).unwrap();
        assert_eq!(i.ci95_low, 0.0);
        assert!((i.ci95_high - 0.0713).abs() < 1e-4, "{i:?}");
    }
}
