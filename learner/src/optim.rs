//! Adam with global gradient-norm clipping, written out so its state is ours to checkpoint
//! and resume exactly (moments and step count).

use tch::{Kind, Tensor};

use junction_common::weights::{Decoded, WeightsError};

pub struct Adam {
    params: Vec<Tensor>,
    first_moment: Vec<Tensor>,
    second_moment: Vec<Tensor>,
    steps: i64,
    learning_rate: f64,
    eps: f64,
    beta1: f64,
    beta2: f64,
}

impl Adam {
    pub fn new(params: Vec<Tensor>, learning_rate: f64, eps: f64) -> Self {
        let zeros = |ps: &[Tensor]| ps.iter().map(Tensor::zeros_like).collect::<Vec<_>>();
        Adam {
            first_moment: zeros(&params),
            second_moment: zeros(&params),
            params,
            steps: 0,
            learning_rate,
            eps,
            beta1: 0.9,
            beta2: 0.999,
        }
    }

    pub fn learning_rate(&self) -> f64 {
        self.learning_rate
    }

    /// For schedules: the moments and step count carry on, only the step size changes.
    pub fn set_learning_rate(&mut self, learning_rate: f64) {
        self.learning_rate = learning_rate;
    }

    pub fn zero_grad(&mut self) {
        for p in &mut self.params {
            let mut grad = p.grad();
            if grad.defined() {
                let _ = grad.zero_();
            }
        }
    }

    /// Scales gradients so their global L2 norm is at most `max_norm` (0 = no clipping);
    /// returns the norm before clipping.
    pub fn clip_grad_norm(&mut self, max_norm: f64) -> f64 {
        let grads: Vec<Tensor> = self
            .params
            .iter()
            .map(Tensor::grad)
            .filter(Tensor::defined)
            .collect();
        if grads.is_empty() {
            return 0.0;
        }
        let norm = tch::no_grad(|| {
            grads
                .iter()
                .map(|g| g.square().sum(Kind::Float))
                .fold(Tensor::from(0.0f32), |a, b| a + b)
                .sqrt()
        });
        let norm = f64::try_from(norm).unwrap_or(f64::NAN);
        if max_norm > 0.0 && norm > max_norm {
            let scale = max_norm / (norm + 1e-6);
            tch::no_grad(|| {
                for mut g in grads {
                    let _ = g.g_mul_scalar_(scale);
                }
            });
        }
        norm
    }

    pub fn step(&mut self) {
        self.steps += 1;
        let correction1 = 1.0 - self.beta1.powi(self.steps as i32);
        let correction2 = 1.0 - self.beta2.powi(self.steps as i32);
        let step_size = self.learning_rate / correction1;
        tch::no_grad(|| {
            for ((p, m), v) in self
                .params
                .iter_mut()
                .zip(&mut self.first_moment)
                .zip(&mut self.second_moment)
            {
                let g = p.grad();
                if !g.defined() {
                    continue;
                }
                let _ = m
                    .g_mul_scalar_(self.beta1)
                    .g_add_(&(&g * (1.0 - self.beta1)));
                let _ = v
                    .g_mul_scalar_(self.beta2)
                    .addcmul_(&(&g * (1.0 - self.beta2)), &g);
                let denom = (&*v / correction2).sqrt() + self.eps;
                let _ = p.g_add_(&(&*m / denom * -step_size));
            }
        });
    }

    /// Moments and step count, for checkpoints (names prefixed by `prefix`).
    pub fn state(&self, prefix: &str) -> Vec<(String, Tensor)> {
        let mut out = vec![(
            format!("{prefix}.steps"),
            Tensor::from_slice(&[self.steps as f32]),
        )];
        for (i, (m, v)) in self
            .first_moment
            .iter()
            .zip(&self.second_moment)
            .enumerate()
        {
            out.push((format!("{prefix}.m.{i:03}"), m.shallow_clone()));
            out.push((format!("{prefix}.v.{i:03}"), v.shallow_clone()));
        }
        out
    }

    pub fn load_state(&mut self, prefix: &str, decoded: &mut Decoded) -> Result<(), WeightsError> {
        let steps = decoded.take(&format!("{prefix}.steps"), &[1])?;
        let mut moments = Vec::with_capacity(self.params.len());
        for (i, p) in self.params.iter().enumerate() {
            let m = decoded.take(&format!("{prefix}.m.{i:03}"), &p.size())?;
            let v = decoded.take(&format!("{prefix}.v.{i:03}"), &p.size())?;
            moments.push((m, v));
        }
        self.steps = f64::try_from(steps.sum(Kind::Float))? as i64;
        let device = self
            .params
            .first()
            .map(Tensor::device)
            .unwrap_or(tch::Device::Cpu);
        self.first_moment = moments.iter().map(|(m, _)| m.to_device(device)).collect();
        self.second_moment = moments.iter().map(|(_, v)| v.to_device(device)).collect();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_step_moves_each_weight_by_the_learning_rate_against_its_gradient() {
        // Adam's bias-corrected first step is lr · sign(g) (up to eps).
        let w = Tensor::from_slice(&[1.0f32, -2.0, 0.5]).set_requires_grad(true);
        let mut adam = Adam::new(vec![w.shallow_clone()], 0.1, 1e-8);
        let loss = (&w * Tensor::from_slice(&[3.0f32, -1.0, 0.0])).sum(Kind::Float);
        adam.zero_grad();
        loss.backward();
        adam.step();
        let after = Vec::<f32>::try_from(w.detach()).unwrap();
        assert!(
            (after[0] - 0.9).abs() < 1e-5 && (after[1] + 1.9).abs() < 1e-5,
            "{after:?}"
        );
        assert_eq!(after[2], 0.5, "a zero gradient leaves the weight alone");
    }

    #[test]
    fn clipping_bounds_the_global_norm() {
        let w = Tensor::from_slice(&[0.0f32, 0.0]).set_requires_grad(true);
        let mut adam = Adam::new(vec![w.shallow_clone()], 0.1, 1e-8);
        (&w * Tensor::from_slice(&[3.0f32, 4.0]))
            .sum(Kind::Float)
            .backward();
        let norm = adam.clip_grad_norm(1.0);
        assert!((norm - 5.0).abs() < 1e-5);
        let g = Vec::<f32>::try_from(w.grad()).unwrap();
        assert!(
            ((g[0] * g[0] + g[1] * g[1]).sqrt() - 1.0).abs() < 1e-4,
            "{g:?}"
        );
    }
}
