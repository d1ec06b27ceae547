//! Adam with global gradient-norm clipping, written out so its state is ours to checkpoint
//! and resume exactly (moments and step count).
//!
//! The parameters it trains live in one flat buffer, and so do their gradients: each
//! parameter (and its gradient) is a view of its stretch. Zeroing, the gradient norm, the
//! clip and the step are then one pass over a few buffers instead of a dozen operations per
//! parameter tensor, and on the CPU the step is one fused loop in Rust.

use tch::{Device, Kind, Tensor};

use junction_common::weights::{Decoded, WeightsError};
use junction_core::activation;

pub struct Adam {
    params: Vec<Tensor>,
    /// Every parameter's values, one after another; `params` are views of it.
    values: Tensor,
    /// Their gradients likewise; each parameter's gradient is a view of its stretch.
    grads: Tensor,
    first_moment: Tensor,
    second_moment: Tensor,
    steps: i64,
    learning_rate: f64,
    eps: f64,
    beta1: f64,
    beta2: f64,
}

impl Adam {
    /// Adam over `params` (f32 tensors on one device, each trained by no other optimiser),
    /// which from now on share one buffer: their values stay what they were.
    pub fn new(params: Vec<Tensor>, learning_rate: f64, eps: f64) -> Self {
        let device = params.first().map_or(Device::Cpu, Tensor::device);
        let total: i64 = params.iter().map(|p| p.numel() as i64).sum();
        let zeros = || Tensor::zeros([total], (Kind::Float, device));
        let (values, grads) = (zeros(), zeros());
        // Every parameter needs a gradient to be re-pointed: autograd makes them (zeros).
        if !params.is_empty() {
            tch::with_grad(|| {
                params
                    .iter()
                    .map(|p| p.sum(Kind::Float) * 0.0)
                    .fold(Tensor::zeros([], (Kind::Float, device)), |a, b| a + b)
                    .backward()
            });
        }
        tch::no_grad(|| {
            let mut offset = 0;
            for p in &params {
                let (len, shape) = (p.numel() as i64, p.size());
                let stretch =
                    |buffer: &Tensor| buffer.narrow(0, offset, len).view(shape.as_slice());
                let value = stretch(&values);
                value.shallow_clone().copy_(p);
                p.shallow_clone().set_data(&value);
                p.grad().set_data(&stretch(&grads));
                offset += len;
            }
        });
        Adam {
            params,
            values,
            grads,
            first_moment: zeros(),
            second_moment: zeros(),
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
        let _ = self.grads.zero_();
    }

    /// Scales gradients so their global L2 norm is at most `max_norm` (0 = no clipping);
    /// returns the norm before clipping.
    pub fn clip_grad_norm(&mut self, max_norm: f64) -> f64 {
        if self.params.is_empty() {
            return 0.0;
        }
        let norm = tch::no_grad(|| self.grads.norm());
        let norm = f64::try_from(norm).unwrap_or(f64::NAN);
        if max_norm > 0.0 && norm > max_norm {
            let scale = max_norm / (norm + 1e-6);
            tch::no_grad(|| {
                let _ = self.grads.g_mul_scalar_(scale);
            });
        }
        norm
    }

    pub fn step(&mut self) {
        self.steps += 1;
        let step = AdamStep {
            beta1: self.beta1 as f32,
            beta2: self.beta2 as f32,
            one_minus_beta1: (1.0 - self.beta1) as f32,
            one_minus_beta2: (1.0 - self.beta2) as f32,
            correction2: (1.0 - self.beta2.powi(self.steps as i32)) as f32,
            step_size: (self.learning_rate / (1.0 - self.beta1.powi(self.steps as i32))) as f32,
            eps: self.eps as f32,
        };
        tch::no_grad(|| {
            if self.values.device() == Device::Cpu {
                // SAFETY: four distinct contiguous f32 CPU buffers of one length, made in `new`
                // (or restored into by copy) and touched by nothing else during the step.
                unsafe {
                    step.apply(
                        slice(&self.values),
                        slice(&self.grads),
                        slice(&self.first_moment),
                        slice(&self.second_moment),
                    )
                }
            } else {
                step.apply_tensors(
                    &mut self.values,
                    &self.grads,
                    &mut self.first_moment,
                    &mut self.second_moment,
                );
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
            .per_parameter(&self.first_moment)
            .into_iter()
            .zip(self.per_parameter(&self.second_moment))
            .enumerate()
        {
            out.push((format!("{prefix}.m.{i:03}"), m));
            out.push((format!("{prefix}.v.{i:03}"), v));
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
        let (first, second) = (
            self.per_parameter(&self.first_moment),
            self.per_parameter(&self.second_moment),
        );
        tch::no_grad(|| {
            for ((m, v), (mut m_to, mut v_to)) in moments.iter().zip(first.into_iter().zip(second))
            {
                m_to.copy_(m);
                v_to.copy_(v);
            }
        });
        Ok(())
    }

    /// Views of `buffer`'s stretches, shaped like the parameters.
    fn per_parameter(&self, buffer: &Tensor) -> Vec<Tensor> {
        let mut offset = 0;
        self.params
            .iter()
            .map(|p| {
                let len = p.numel() as i64;
                let view = buffer.narrow(0, offset, len).view(p.size().as_slice());
                offset += len;
                view
            })
            .collect()
    }
}

/// The values of a flat f32 CPU buffer made by [`Adam::new`].
///
/// # Safety
/// `t` must be a contiguous f32 CPU tensor that nothing else reads or writes while the slice
/// lives.
unsafe fn slice<'a>(t: &Tensor) -> &'a mut [f32] {
    let len = t.numel();
    if len == 0 {
        return &mut [];
    }
    // SAFETY: the caller's promise.
    unsafe { std::slice::from_raw_parts_mut(t.data_ptr() as *mut f32, len) }
}

/// One Adam step's constants, in f32 as the tensors hold them.
struct AdamStep {
    beta1: f32,
    beta2: f32,
    /// 1 − β taken in f64, then rounded (as a tensor op with an f64 scalar has it).
    one_minus_beta1: f32,
    one_minus_beta2: f32,
    correction2: f32,
    /// The learning rate over the first moment's bias correction.
    step_size: f32,
    eps: f32,
}

impl AdamStep {
    /// m ← β₁m + (1 − β₁)g;  v ← β₂v + (1 − β₂)g²;  θ ← θ − step · m / (√(v / c₂) + ε),
    /// in one pass (eight values at a time where the CPU has AVX2; the same arithmetic).
    fn apply(&self, values: &mut [f32], grads: &[f32], m: &mut [f32], v: &mut [f32]) {
        #[cfg(target_arch = "x86_64")]
        if activation::avx2_fma() {
            // SAFETY: the CPU has AVX2 and FMA.
            return unsafe { self.apply_avx2(values, grads, m, v) };
        }
        self.apply_portable(values, grads, m, v);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn apply_avx2(&self, values: &mut [f32], grads: &[f32], m: &mut [f32], v: &mut [f32]) {
        self.apply_portable(values, grads, m, v);
    }

    #[inline(always)]
    fn apply_portable(&self, values: &mut [f32], grads: &[f32], m: &mut [f32], v: &mut [f32]) {
        let (b1, b2) = (self.beta1, self.beta2);
        let (one_minus_b1, one_minus_b2) = (self.one_minus_beta1, self.one_minus_beta2);
        for (((theta, g), m), v) in values.iter_mut().zip(grads).zip(m).zip(v) {
            *m = *m * b1 + g * one_minus_b1;
            *v = *v * b2 + g * one_minus_b2 * g;
            let denom = (*v / self.correction2).sqrt() + self.eps;
            *theta += *m / denom * -self.step_size;
        }
    }

    /// The same with tensor operations, for other devices.
    fn apply_tensors(&self, values: &mut Tensor, grads: &Tensor, m: &mut Tensor, v: &mut Tensor) {
        let _ = m
            .g_mul_scalar_(f64::from(self.beta1))
            .g_add_(&(grads * f64::from(self.one_minus_beta1)));
        let _ = v
            .g_mul_scalar_(f64::from(self.beta2))
            .addcmul_(&(grads * f64::from(self.one_minus_beta2)), grads);
        let denom = (&*v / f64::from(self.correction2)).sqrt() + f64::from(self.eps);
        let _ = values.g_add_(&(&*m / denom * -f64::from(self.step_size)));
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
