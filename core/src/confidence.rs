//! 95 % confidence intervals for `actor eval` (over the episodes of one evaluation). The
//! intervals over seeds of one method and scene are `python -m junction.analysis`'s
//! (python/junction/analysis/stats.py), with the same exact t quantiles.
//!
//! Each kind of statistic gets the interval that behaves well where ours live:
//! - shares of episodes (success, crash, …): Wilson's score interval, which stays inside
//!   [0, 1] and does not collapse to a point at 0 or 1 as the normal interval does;
//! - counts per unit of exposure (collisions per simulated second, arrivals per 300 steps):
//!   the score interval of a Poisson rate, the same construction for a count;
//! - means (reward, length, acceleration): Student's t, exact quantiles;
//! - sample maxima: a seeded percentile bootstrap (a maximum has no t interval; resampling
//!   shows how much it depends on the few extreme episodes; the upper end is the observed
//!   maximum itself whenever resamples hit it often enough, i.e. almost always).

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// The standard normal's 97.5 % quantile.
pub const Z_95: f64 = 1.959_963_984_540_054;
/// Resamples of [`bootstrap_max`].
pub const BOOTSTRAP_RESAMPLES: usize = 2000;
/// Above this many degrees of freedom the t quantile comes from its Cornish–Fisher
/// expansion (error < 1e-9) instead of the exact series (whose cost grows with the degrees).
const EXACT_T_MAX_DF: u64 = 2000;

/// How an interval was computed (written into eval JSON and CSV).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CiMethod {
    Wilson,
    PoissonScore,
    StudentT,
    Bootstrap,
}

impl CiMethod {
    pub fn label(self) -> &'static str {
        match self {
            CiMethod::Wilson => "wilson",
            CiMethod::PoissonScore => "poisson_score",
            CiMethod::StudentT => "student_t",
            CiMethod::Bootstrap => "bootstrap",
        }
    }
}

/// A point estimate with its 95 % interval; `low`/`high` are None when the sample is too
/// small for one (a mean or maximum of fewer than 2 values).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    pub value: f64,
    pub low: Option<f64>,
    pub high: Option<f64>,
    pub ci: CiMethod,
    /// Size of the sample behind it: episodes, or the count for a rate.
    pub n: u64,
}

impl Estimate {
    /// Half the interval's width, when it has one.
    pub fn half_width(&self) -> Option<f64> {
        Some((self.high? - self.low?) / 2.0)
    }
}

/// Wilson score interval of `successes` out of `trials` (trials ≥ 1).
pub fn wilson(successes: u64, trials: u64) -> Estimate {
    let n = trials.max(1) as f64;
    let p = successes as f64 / n;
    let z2 = Z_95 * Z_95;
    let denominator = 1.0 + z2 / n;
    let centre = (p + z2 / (2.0 * n)) / denominator;
    let half = Z_95 / denominator * (p * (1.0 - p) / n + z2 / (4.0 * n * n)).sqrt();
    Estimate {
        value: p,
        low: Some((centre - half).max(0.0)),
        high: Some((centre + half).min(1.0)),
        ci: CiMethod::Wilson,
        n: trials,
    }
}

/// Score interval of a Poisson rate: `count` events in `exposure` units (seconds, blocks of
/// steps). Solves (k − μ)² = z²·μ for the expected count μ; at k = 0 it gives [0, z²].
pub fn poisson_rate(count: u64, exposure: f64) -> Estimate {
    let k = count as f64;
    let exposure = if exposure > 0.0 { exposure } else { f64::NAN };
    let z2 = Z_95 * Z_95;
    let spread = Z_95 * (k + z2 / 4.0).sqrt();
    Estimate {
        value: k / exposure,
        low: Some(((k + z2 / 2.0 - spread) / exposure).max(0.0)),
        high: Some((k + z2 / 2.0 + spread) / exposure),
        ci: CiMethod::PoissonScore,
        n: count,
    }
}

/// Mean with Student's t interval (no interval below 2 values).
pub fn mean_t(values: &[f64]) -> Estimate {
    let n = values.len();
    let mean = values.iter().sum::<f64>() / n.max(1) as f64;
    let (low, high) = if n >= 2 {
        let variance = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        let half = t_quantile_975((n - 1) as u64) * (variance / n as f64).sqrt();
        (Some(mean - half), Some(mean + half))
    } else {
        (None, None)
    };
    Estimate {
        value: mean,
        low,
        high,
        ci: CiMethod::StudentT,
        n: n as u64,
    }
}

/// Sample maximum with a percentile bootstrap interval: the 2.5 % and 97.5 % points of the
/// maxima of [`BOOTSTRAP_RESAMPLES`] resamples drawn with replacement, seeded by `seed` so a
/// report is reproducible. No interval below 2 values.
pub fn bootstrap_max(values: &[f64], seed: u64) -> Estimate {
    let n = values.len();
    let max = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let (low, high) = if n >= 2 {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut maxima: Vec<f64> = (0..BOOTSTRAP_RESAMPLES)
            .map(|_| {
                (0..n)
                    .map(|_| values[rng.gen_range(0..n)])
                    .fold(f64::NEG_INFINITY, f64::max)
            })
            .collect();
        maxima.sort_by(f64::total_cmp);
        let at = |q: f64| maxima[((q * BOOTSTRAP_RESAMPLES as f64) as usize).min(maxima.len() - 1)];
        (Some(at(0.025)), Some(at(0.975)))
    } else {
        (None, None)
    };
    Estimate {
        value: if n == 0 { 0.0 } else { max },
        low,
        high,
        ci: CiMethod::Bootstrap,
        n: n as u64,
    }
}

/// The 97.5 % quantile of Student's t with `df` ≥ 1 degrees of freedom (the half-width
/// multiplier of a 95 % interval), found by bisection on the exact distribution function.
pub fn t_quantile_975(df: u64) -> f64 {
    let df = df.max(1);
    if df > EXACT_T_MAX_DF {
        return cornish_fisher_975(df as f64);
    }
    // P(|T| ≤ t) rises from 0 to 1; the quantile is where it reaches 0.95.
    let (mut low, mut high) = (0.0f64, 1.0f64);
    while central_probability(high, df) < 0.95 {
        high *= 2.0;
    }
    for _ in 0..200 {
        let mid = 0.5 * (low + high);
        if central_probability(mid, df) < 0.95 {
            low = mid;
        } else {
            high = mid;
        }
        if high - low < 1e-13 * high {
            break;
        }
    }
    0.5 * (low + high)
}

/// P(|T| ≤ t) for Student's t with integer `df`, from its closed form in θ = atan(t/√df)
/// (Abramowitz & Stegun 26.7.3–4): a finite series in cos²θ, odd and even df differing.
fn central_probability(t: f64, df: u64) -> f64 {
    let theta = (t / (df as f64).sqrt()).atan();
    let (sin, cos) = theta.sin_cos();
    let cos2 = cos * cos;
    if df % 2 == 1 {
        // (2/π)·(θ + sinθ·[cosθ + (2/3)cos³θ + (2·4)/(3·5)cos⁵θ + … up to cos^(df−2)θ])
        let mut term = cos;
        let mut sum = 0.0;
        for k in 1..=(df - 1) / 2 {
            sum += term;
            term *= cos2 * (2 * k) as f64 / (2 * k + 1) as f64;
        }
        std::f64::consts::FRAC_2_PI * (theta + sin * sum)
    } else {
        // sinθ·[1 + (1/2)cos²θ + (1·3)/(2·4)cos⁴θ + … up to cos^(df−2)θ]
        let mut term = 1.0;
        let mut sum = 0.0;
        for k in 1..=df / 2 {
            sum += term;
            term *= cos2 * (2 * k - 1) as f64 / (2 * k) as f64;
        }
        sin * sum
    }
}

/// Cornish–Fisher expansion of the t quantile around the normal one, four terms in 1/df.
fn cornish_fisher_975(df: f64) -> f64 {
    let z = Z_95;
    let z3 = z.powi(3);
    let z5 = z.powi(5);
    let z7 = z.powi(7);
    let z9 = z.powi(9);
    z + (z3 + z) / (4.0 * df)
        + (5.0 * z5 + 16.0 * z3 + 3.0 * z) / (96.0 * df.powi(2))
        + (3.0 * z7 + 19.0 * z5 + 17.0 * z3 - 15.0 * z) / (384.0 * df.powi(3))
        + (79.0 * z9 + 776.0 * z7 + 1482.0 * z5 - 1920.0 * z3 - 945.0 * z) / (92160.0 * df.powi(4))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tolerance: f64) -> bool {
        (a - b).abs() <= tolerance
    }

    #[test]
    fn t_quantiles_match_the_printed_tables() {
        // Standard two-sided 95 % critical values.
        for (df, expected) in [
            (1, 12.7062),
            (2, 4.3027),
            (3, 3.1824),
            (4, 2.7764),
            (9, 2.2622),
            (10, 2.2281),
            (29, 2.0452),
            (30, 2.0423),
            (100, 1.9840),
            (1000, 1.9623),
        ] {
            let t = t_quantile_975(df);
            assert!(close(t, expected, 5e-4), "df {df}: {t} vs {expected}");
        }
        // The expansion takes over above EXACT_T_MAX_DF without a jump.
        let exact = t_quantile_975(EXACT_T_MAX_DF);
        let expanded = cornish_fisher_975(EXACT_T_MAX_DF as f64);
        assert!(close(exact, expanded, 1e-9), "{exact} vs {expanded}");
        assert!(close(t_quantile_975(1_000_000), Z_95, 1e-5));
    }

    #[test]
    fn wilson_interval_by_hand() {
        // 8 of 10: p = 0.8, z² = 3.8415; centre = (0.8 + 0.19207)/1.38415 = 0.71674,
        // half = 1.95996/1.38415 · √(0.016 + 0.0096037) = 0.22657.
        let e = wilson(8, 10);
        assert_eq!(e.value, 0.8);
        assert!(close(e.low.unwrap(), 0.49016, 1e-4), "{e:?}");
        assert!(close(e.high.unwrap(), 0.94331, 1e-4), "{e:?}");
        assert_eq!((e.ci, e.n), (CiMethod::Wilson, 10));
        // At 0 of n the interval starts at 0 and still has width: [0, z²/(n + z²)].
        let zero = wilson(0, 20);
        assert_eq!(zero.low, Some(0.0));
        assert!(
            close(zero.high.unwrap(), 3.8415 / 23.8415, 1e-4),
            "{zero:?}"
        );
        let all = wilson(20, 20);
        assert_eq!(all.high, Some(1.0));
        assert!(close(all.low.unwrap(), 20.0 / 23.8415, 1e-4), "{all:?}");
    }

    #[test]
    fn poisson_score_interval_by_hand() {
        // 10 events in 50 s: μ = 10 + 1.92073 ± 1.95996·√(10.96037) = 11.92073 ± 6.48871.
        let e = poisson_rate(10, 50.0);
        assert!(close(e.value, 0.2, 1e-12));
        assert!(close(e.low.unwrap(), 5.43202 / 50.0, 1e-5), "{e:?}");
        assert!(close(e.high.unwrap(), 18.40944 / 50.0, 1e-5), "{e:?}");
        let none = poisson_rate(0, 100.0);
        assert_eq!((none.value, none.low), (0.0, Some(0.0)));
        assert!(close(none.high.unwrap(), 3.84146 / 100.0, 1e-6), "{none:?}");
    }

    #[test]
    fn t_interval_by_hand() {
        // 2, 4, 6, 8: mean 5, s² = 20/3, s/√n = 1.29099, t(3) = 3.18245 → ± 4.10850.
        let e = mean_t(&[2.0, 4.0, 6.0, 8.0]);
        assert_eq!(e.value, 5.0);
        assert!(close(e.half_width().unwrap(), 4.10850, 1e-4), "{e:?}");
        assert!(close(e.low.unwrap(), 0.89150, 1e-4));
        let single = mean_t(&[3.0]);
        assert_eq!((single.value, single.low, single.high), (3.0, None, None));
    }

    #[test]
    fn bootstrap_of_a_maximum_is_seeded_and_within_the_sample() {
        let values: Vec<f64> = (1..=40).map(f64::from).collect();
        let a = bootstrap_max(&values, 7);
        assert_eq!(a, bootstrap_max(&values, 7), "same seed, same interval");
        assert_eq!(a.value, 40.0);
        // The resampled maximum misses the top value with probability (39/40)^40 ≈ 0.36, the
        // top three with (37/40)^40 ≈ 0.044: the 2.5 % point lies a few values below the top.
        let low = a.low.unwrap();
        assert!((35.0..=39.0).contains(&low), "{a:?}");
        assert_eq!(a.high, Some(40.0));
        let flat = bootstrap_max(&[2.5, 2.5, 2.5], 1);
        assert_eq!((flat.low, flat.high), (Some(2.5), Some(2.5)));
        assert_eq!(bootstrap_max(&[1.0], 1).low, None);
    }
}
