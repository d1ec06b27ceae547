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
    weighted_clipped_surrogate(new_log_probs, old_log_probs, advantages, clip, None)
}

/// The decoupled PPO objective (Hilton et al. 2021, "Batch size-invariance for policy
/// optimization") for data from lagging actors: the ratio is taken against the proximal
/// policy π_prox (the policy when the update began), so the clip bounds this update's step
/// whatever the data's age, and each sample is weighted by how much likelier π_prox makes
/// its action than the behaviour policy did, truncated at `max_weight` (IMPALA's ρ̄):
/// −E[min(π_prox/π_b, ρ̄) · min(ρ·A, clip(ρ, 1 ± ε)·A)] with ρ = π/π_prox.
pub fn decoupled_surrogate(
    new_log_probs: &Tensor,
    proximal_log_probs: &Tensor,
    behaviour_log_probs: &Tensor,
    advantages: &Tensor,
    clip: f64,
    max_weight: f64,
) -> SurrogateTerms {
    let weights = (proximal_log_probs - behaviour_log_probs)
        .exp()
        .clamp_max(max_weight)
        .detach();
    weighted_clipped_surrogate(
        new_log_probs,
        proximal_log_probs,
        advantages,
        clip,
        Some(&weights),
    )
}

/// [`clipped_surrogate`] with each row's term weighted (None: all 1).
pub fn weighted_clipped_surrogate(
    new_log_probs: &Tensor,
    old_log_probs: &Tensor,
    advantages: &Tensor,
    clip: f64,
    weights: Option<&Tensor>,
) -> SurrogateTerms {
    let log_ratio = new_log_probs - old_log_probs;
    let ratio = log_ratio.exp();
    let unclipped = &ratio * advantages;
    let clipped = ratio.clamp(1.0 - clip, 1.0 + clip) * advantages;
    let pessimistic = unclipped.minimum(&clipped);
    let pessimistic = match weights {
        Some(w) => pessimistic * w,
        None => pessimistic,
    };
    let loss = -pessimistic.mean(unclipped.kind());
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
    fn decoupled_surrogate_clips_around_the_proximal_policy_and_weights_by_truncated_lag() {
        // Row 0: π_prox/π_b = e^0.5 ≈ 1.65, truncated to 1.2; ρ = π/π_prox = 1, A = 1.
        // Row 1: π_prox/π_b = e^−1 ≈ 0.368; ρ = e^0.5 ≈ 1.65 clipped to 1.2 (ε = 0.2), A = 2.
        let behaviour = t(&[-1.0, 0.0]);
        let proximal = t(&[-0.5, -1.0]);
        let new = t(&[-0.5, -0.5]).set_requires_grad(true);
        let terms = decoupled_surrogate(&new, &proximal, &behaviour, &t(&[1.0, 2.0]), 0.2, 1.2);
        let w1 = (-1.0f64).exp();
        let expected = -(1.2 * 1.0 + w1 * 1.2 * 2.0) / 2.0;
        assert!(
            (scalar(&terms.loss) - expected).abs() < 1e-5,
            "{}",
            scalar(&terms.loss)
        );
        // The clip is taken around π_prox, not π_b: row 1 is clipped, row 0 is not.
        assert!((scalar(&terms.clip_fraction) - 0.5).abs() < 1e-6);
        terms.loss.backward();
        let g = Vec::<f32>::try_from(new.grad()).unwrap();
        assert!(
            (g[0] + 0.6).abs() < 1e-5,
            "−w·A·ρ/n = −1.2·1·1/2, got {}",
            g[0]
        );
        assert_eq!(
            g[1], 0.0,
            "clipped in the advantage's direction: no gradient"
        );
        // With no lag (π_prox = π_b) it is plain PPO.
        let plain = clipped_surrogate(&new, &proximal, &t(&[1.0, 2.0]), 0.2);
        let same = decoupled_surrogate(&new, &proximal, &proximal, &t(&[1.0, 2.0]), 0.2, 1.0);
        assert!((scalar(&plain.loss) - scalar(&same.loss)).abs() < 1e-6);
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
