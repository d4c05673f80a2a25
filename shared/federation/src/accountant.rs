//! The privacy a DP-FedAvg run has spent: the Rényi-DP accountant of the Poisson-subsampled Gaussian mechanism
//! (Mironov, Talwar and Zhang 2019, "Rényi Differential Privacy of the Sampled Gaussian Mechanism"), computed as
//! Google's `dp_accounting` (and Opacus) compute it: RDP at a fixed set of orders, integer orders by the binomial
//! sum, fractional ones by the series of the paper's section 3.3, composed over rounds by addition, and turned into
//! (epsilon, delta) by Canonne, Kamath and Steinke 2020's conversion, at the best order.

use serde::{Deserialize, Serialize};

/// `dp_accounting`'s default orders: 1.1 to 10.9 by 0.1, 11 to 63, then 128, 256, 512 and 1024.
pub fn default_orders() -> Vec<f64> {
    let fractional = (1..100).map(|x| 1.0 + f64::from(x) / 10.0);
    let integer = (11..64).map(f64::from);
    fractional.chain(integer).chain([128.0, 256.0, 512.0, 1024.0]).collect()
}

/// Iterations after which the fractional-order series is taken not to converge, and the order left out.
const MAX_SERIES_TERMS: usize = 1000;

/// Privacy spent after some rounds: `epsilon` at `delta`, reached at RDP order `order`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PrivacySpent {
    pub epsilon: f64,
    pub delta: f64,
    pub order: f64,
    /// Rounds composed (each a sampled Gaussian release).
    pub rounds: u64,
}

/// The (epsilon, delta) of `steps` releases of the Gaussian mechanism with noise multiplier `noise_multiplier`
/// (noise standard deviation over L2 sensitivity), each on a Poisson sample of rate `sampling_rate`.
pub fn privacy_spent(sampling_rate: f64, noise_multiplier: f64, steps: u64, delta: f64) -> PrivacySpent {
    let orders = default_orders();
    let rdp: Vec<f64> =
        orders.iter().map(|&a| steps as f64 * rdp_sampled_gaussian(sampling_rate, noise_multiplier, a)).collect();
    let (epsilon, order) = epsilon_from_rdp(&orders, &rdp, delta);
    PrivacySpent { epsilon, delta, order, rounds: steps }
}

/// The RDP at order `alpha` of one release of the sampled Gaussian mechanism (infinite where the series does not
/// converge: that order is then never the best one).
pub fn rdp_sampled_gaussian(q: f64, sigma: f64, alpha: f64) -> f64 {
    if q == 0.0 {
        0.0
    } else if sigma == 0.0 || alpha.is_infinite() {
        f64::INFINITY
    } else if q == 1.0 {
        alpha / (2.0 * sigma * sigma)
    } else if alpha.fract() == 0.0 {
        log_a_integer(q, sigma, alpha as u64) / (alpha - 1.0)
    } else {
        log_a_fractional(q, sigma, alpha) / (alpha - 1.0)
    }
}

/// The smallest epsilon over `orders` for RDP values `rdp`, and its order (Canonne et al. 2020, proposition 12).
pub fn epsilon_from_rdp(orders: &[f64], rdp: &[f64], delta: f64) -> (f64, f64) {
    let candidate = |(&a, &r): (&f64, &f64)| -> f64 {
        if r < 0.0 || delta * delta + (-r).exp_m1() > 0.0 {
            // Below the KL bound delta <= sqrt(1 - exp(-r)): nothing spent.
            0.0
        } else if a > 1.01 {
            r + (-1.0 / a).ln_1p() - (delta * a).ln() / (a - 1.0)
        } else {
            f64::INFINITY
        }
    };
    let (epsilon, order) = orders
        .iter()
        .zip(rdp)
        .map(|pair| (candidate(pair), *pair.0))
        .fold((f64::INFINITY, 0.0), |best, next| if next.0 < best.0 { next } else { best });
    (epsilon.max(0.0), order)
}

/// `log(exp(x) + exp(y))`.
fn log_add(x: f64, y: f64) -> f64 {
    let (low, high) = if x < y { (x, y) } else { (y, x) };
    if low == f64::NEG_INFINITY { high } else { (low - high).exp().ln_1p() + high }
}

/// `log(n choose k)` for real `n` and `k`, from log-gamma (of the absolute value, as scipy's `gammaln`).
fn log_binomial(n: f64, k: f64) -> f64 {
    libm::lgamma(n + 1.0) - libm::lgamma(k + 1.0) - libm::lgamma(n - k + 1.0)
}

/// `log(erfc(x))`, by its asymptotic series where `erfc` underflows.
fn log_erfc(x: f64) -> f64 {
    let r = libm::erfc(x);
    if r > 0.0 {
        return r.ln();
    }
    let x2 = x * x;
    -std::f64::consts::PI.ln() / 2.0 - x.ln() - x2 - 0.5 / x2 + 0.625 / (x2 * x2) - 37.0 / 24.0 / x2.powi(3)
        + 353.0 / 64.0 / x2.powi(4)
}

/// `log(A_alpha)` for an integer order: the binomial sum of the paper's section 3.2.
fn log_a_integer(q: f64, sigma: f64, alpha: u64) -> f64 {
    let (log_q, log_1mq) = (q.ln(), (-q).ln_1p());
    (0..=alpha).fold(f64::NEG_INFINITY, |log_a, i| {
        let i = i as f64;
        let a = alpha as f64;
        let term = log_binomial(a, i) + i * log_q + (a - i) * log_1mq + (i * i - i) / (2.0 * sigma * sigma);
        log_add(log_a, term)
    })
}

/// `log(A_alpha)` for a fractional order: the two half-line integrals of section 3.3, summed until both terms
/// decrease and fall 30 nats below the total; infinite if that takes more than [`MAX_SERIES_TERMS`].
fn log_a_fractional(q: f64, sigma: f64, alpha: f64) -> f64 {
    let (log_q, log_1mq) = (q.ln(), (-q).ln_1p());
    let z0 = sigma * sigma * (1.0 / q - 1.0).ln() + 0.5;
    let scale = std::f64::consts::SQRT_2 * sigma;
    let (mut log_a0, mut log_a1) = (f64::NEG_INFINITY, f64::NEG_INFINITY);
    let (mut last_s0, mut last_s1) = (f64::NEG_INFINITY, f64::NEG_INFINITY);
    for i in 0..MAX_SERIES_TERMS {
        let i = i as f64;
        let j = alpha - i;
        let log_coef = log_binomial(alpha, i);
        let log_t0 = log_coef + i * log_q + j * log_1mq;
        let log_t1 = log_coef + j * log_q + i * log_1mq;
        let log_e0 = 0.5f64.ln() + log_erfc((i - z0) / scale);
        let log_e1 = 0.5f64.ln() + log_erfc((z0 - j) / scale);
        let log_s0 = log_t0 + (i * i - i) / (2.0 * sigma * sigma) + log_e0;
        let log_s1 = log_t1 + (j * j - j) / (2.0 * sigma * sigma) + log_e1;
        log_a0 = log_add(log_a0, log_s0);
        log_a1 = log_add(log_a1, log_s1);
        let total = log_add(log_a0, log_a1);
        if log_s0 < last_s0 && log_s1 < last_s1 && log_s0.max(log_s1) < total - 30.0 {
            return total;
        }
        (last_s0, last_s1) = (log_s0, log_s1);
    }
    f64::INFINITY
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Values of Google's `dp_accounting` 0.6.0 (`RdpAccountant`, default orders, `PoissonSampledDpEvent` of a
    /// `GaussianDpEvent` composed `steps` times, `get_epsilon_and_optimal_order`): (q, noise multiplier, steps,
    /// delta) -> (epsilon, order). The first is the DP-SGD MNIST setting of Abadi et al. (batch 256 of 60,000,
    /// noise 1.1, 60 epochs).
    const DP_ACCOUNTING: [((f64, f64, u64, f64), (f64, f64)); 6] = [
        ((256.0 / 60000.0, 1.1, 14063, 1e-5), (2.596655529521983, 8.1)),
        ((0.1, 1.0, 100, 1e-5), (7.903850223578231, 3.2)),
        ((1.0, 2.0, 40, 1e-5), (19.05359753163139, 2.5)),
        ((0.3, 0.8, 40, 1e-5), (21.814485403847563, 2.0)),
        ((0.5, 5.0, 1, 1e-5), (0.455531593304523, 30.0)),
        ((0.05, 0.6, 1000, 1e-5), (40.96884000798707, 1.7)),
    ];

    #[test]
    fn epsilon_matches_dp_accounting() {
        for ((q, sigma, steps, delta), (epsilon, order)) in DP_ACCOUNTING {
            let spent = privacy_spent(q, sigma, steps, delta);
            assert!(
                (spent.epsilon - epsilon).abs() <= 1e-9 * epsilon,
                "q={q} sigma={sigma} steps={steps}: epsilon {} against dp_accounting's {epsilon}",
                spent.epsilon
            );
            assert_eq!(spent.order, order, "q={q} sigma={sigma} steps={steps}");
        }
    }

    #[test]
    fn full_participation_is_the_gaussian_mechanism() {
        // Without sampling, RDP is alpha / (2 sigma^2) per release (Mironov 2017, proposition 7), by hand.
        assert_eq!(rdp_sampled_gaussian(1.0, 2.0, 3.0), 3.0 / 8.0);
        // The binomial sum at q = 1 would give the same: only its last term survives.
        let by_sum = log_a_integer(1.0 - 1e-12, 2.0, 3) / 2.0;
        assert!((by_sum - 3.0 / 8.0).abs() < 1e-9, "{by_sum}");
        // No rounds, no privacy spent; no noise, none kept.
        assert_eq!(privacy_spent(0.5, 1.0, 0, 1e-5).epsilon, 0.0);
        assert_eq!(privacy_spent(0.5, 0.0, 1, 1e-5).epsilon, f64::INFINITY);
    }
}
