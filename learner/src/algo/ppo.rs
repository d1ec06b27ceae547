//! The PPO loss terms shared by every PPO-family algorithm (Schulman et al. 2017).

use tch::{Kind, Tensor};

pub struct SurrogateTerms {
    /// −E[min(ρ·A, clip(ρ, 1 − ε, 1 + ε)·A)]
    pub loss: Tensor,
    /// E[(ρ − 1) − log ρ], a low-variance KL(old ‖ new) estimate.
    pub approx_kl: Tensor,
    /// Fraction of samples whose ratio left [1 − ε, 1 + ε].
    pub clip_fraction: Tensor,
}

pub fn clipped_surrogate(
    new_log_probs: &Tensor,
    old_log_probs: &Tensor,
    advantages: &Tensor,
    clip: f64,
) -> SurrogateTerms {
    let log_ratio = new_log_probs - old_log_probs;
    let ratio = log_ratio.exp();
    let unclipped = &ratio * advantages;
    let clipped = ratio.clamp(1.0 - clip, 1.0 + clip) * advantages;
    let loss = -unclipped.minimum(&clipped).mean(unclipped.kind());
    let (approx_kl, clip_fraction) = tch::no_grad(|| {
        let kl = ((&ratio - 1.0) - &log_ratio).mean(Kind::Float);
        let clipped_share = (&ratio - 1.0)
            .abs()
            .gt(clip)
            .to_kind(Kind::Float)
            .mean(Kind::Float);
        (kl, clipped_share)
    });
    SurrogateTerms {
        loss,
        approx_kl,
        clip_fraction,
    }
}

/// ½·E[(V − R)²], or with `clip > 0` the pessimistic maximum of that and the loss of the value
/// clipped to ± clip around the old prediction.
pub fn value_loss(values: &Tensor, old_values: &Tensor, returns: &Tensor, clip: f64) -> Tensor {
    let unclipped = (values - returns).square();
    if clip <= 0.0 {
        return unclipped.mean(Kind::Float) * 0.5;
    }
    let clipped_values = old_values + (values - old_values).clamp(-clip, clip);
    let clipped = (clipped_values - returns).square();
    unclipped.maximum(&clipped).mean(Kind::Float) * 0.5
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t(v: &[f32]) -> Tensor {
        Tensor::from_slice(v)
    }

    fn scalar(x: &Tensor) -> f64 {
        f64::try_from(x).unwrap()
    }

    #[test]
    fn surrogate_on_a_fixed_batch() {
        // Ratios e^0.5 ≈ 1.6487 (A = 1), e^−0.5 ≈ 0.6065 (A = −2), 1 (A = 3); ε = 0.2.
        // min terms: min(1.6487, 1.2) = 1.2; min(−1.2131, −1.6) = −1.6; 3.
        let new = t(&[0.5, -0.5, 0.0]);
        let old = t(&[0.0, 0.0, 0.0]);
        let adv = t(&[1.0, -2.0, 3.0]);
        let terms = clipped_surrogate(&new, &old, &adv, 0.2);
        let expected = -(1.2 - 1.6 + 3.0) / 3.0;
        assert!(
            (scalar(&terms.loss) - expected).abs() < 1e-5,
            "{}",
            scalar(&terms.loss)
        );
        assert!((scalar(&terms.clip_fraction) - 2.0 / 3.0).abs() < 1e-6);
        let kl = ((0.5f64.exp() - 1.0 - 0.5) + ((-0.5f64).exp() - 1.0 + 0.5)) / 3.0;
        assert!((scalar(&terms.approx_kl) - kl).abs() < 1e-5);
    }

    #[test]
    fn surrogate_gradient_vanishes_where_clipped_in_the_advantages_direction() {
        let new = t(&[0.5, 0.0]).set_requires_grad(true);
        let terms = clipped_surrogate(&new, &t(&[0.0, 0.0]), &t(&[1.0, 1.0]), 0.2);
        terms.loss.backward();
        let g = Vec::<f32>::try_from(new.grad()).unwrap();
        assert_eq!(g[0], 0.0, "ratio 1.65 > 1.2 with A > 0 gives no gradient");
        assert!(
            (g[1] + 0.5).abs() < 1e-6,
            "unclipped: −A·ρ/n = −0.5, got {}",
            g[1]
        );
    }

    #[test]
    fn value_loss_with_and_without_clipping() {
        let v = t(&[3.0, 0.0]);
        let old = t(&[0.0, 0.0]);
        let ret = t(&[3.0, 2.0]);
        // Unclipped: ½·((3−3)² + (0−2)²)/2 = 1.
        assert!((scalar(&value_loss(&v, &old, &ret, 0.0)) - 1.0).abs() < 1e-6);
        // Clip 1: the first prediction counts as 1 → max(0, (1−3)²) = 4; second 4 → ½·4 = 2.
        assert!((scalar(&value_loss(&v, &old, &ret, 1.0)) - 2.0).abs() < 1e-6);
        // Inside the clip range clipping changes nothing: ½·((0.2−3)² + 4)/2.
        let inside = t(&[0.2, 0.0]);
        let expected = 0.5 * ((0.2f64 - 3.0).powi(2) + 4.0) / 2.0;
        assert!((scalar(&value_loss(&inside, &old, &ret, 0.5)) - expected).abs() < 1e-5);
    }
}
