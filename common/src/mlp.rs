//! The multilayer perceptron every policy and critic is made of, with two ways through it:
//!
//! - [`Module::forward`]: libtorch all the way, differentiable by autograd (the meta-gradients
//!   of the learned LCFs take second derivatives through it);
//! - [`Mlp::forward_pass`] and [`MlpPass::backward`]: the PPO update's path, whose gradients are
//!   taken by hand: the matrix products in libtorch, the tanh and its derivative in one pass
//!   over each activation in Rust on the CPU. Autograd then sees only the small loss graph on
//!   the network's output; on two cores this takes the update from slower than PyTorch's own
//!   to faster (BENCHMARKS.md, "Learner update against PyTorch").

use std::sync::LazyLock;

use tch::nn::{self, Module};
use tch::{Device, Kind, Tensor};

/// An MLP with tanh hidden activations and orthogonal initialisation (gain √2 on hidden
/// layers, `out_gain` on the output layer, zero biases), as in well-tuned PPO implementations.
#[derive(Debug)]
pub struct Mlp {
    layers: Vec<nn::Linear>,
}

impl Mlp {
    pub fn new(path: nn::Path, in_dim: i64, hidden: &[i64], out_dim: i64, out_gain: f64) -> Self {
        let mut layers = Vec::with_capacity(hidden.len() + 1);
        let mut width = in_dim;
        let sizes = hidden.iter().copied().chain(std::iter::once(out_dim));
        for (i, size) in sizes.enumerate() {
            let gain = if i == hidden.len() {
                out_gain
            } else {
                std::f64::consts::SQRT_2
            };
            let config = nn::LinearConfig {
                ws_init: nn::Init::Orthogonal { gain },
                bs_init: Some(nn::Init::Const(0.0)),
                bias: true,
            };
            layers.push(nn::linear(&path / format!("l{i}"), width, size, config));
            width = size;
        }
        Mlp { layers }
    }

    /// The same network, not a copy: its parameters (and their gradients) are shared. Owned,
    /// so it can go to another thread.
    pub fn shallow_clone(&self) -> Mlp {
        let layers = self
            .layers
            .iter()
            .map(|l| nn::Linear {
                ws: l.ws.shallow_clone(),
                bs: l.bs.as_ref().map(Tensor::shallow_clone),
            })
            .collect();
        Mlp { layers }
    }

    /// The forward pass for [`MlpPass::backward`]: no autograd graph through the layers; the
    /// output is a leaf that requires grad, for the loss to be built on.
    pub fn forward_pass(&self, x: &Tensor) -> MlpPass<'_> {
        let mut inputs = Vec::with_capacity(self.layers.len());
        let output = self.run(x, |h| inputs.push(h.shallow_clone()));
        MlpPass {
            mlp: self,
            inputs,
            output: output.set_requires_grad(true),
        }
    }

    /// The forward pass without autograd, with the tanh of the training path: what actors act
    /// with and the update's value estimates.
    pub fn infer(&self, x: &Tensor) -> Tensor {
        self.run(x, |_| {})
    }

    /// Through the layers without autograd, showing `keep` each layer's input.
    fn run(&self, x: &Tensor, mut keep: impl FnMut(&Tensor)) -> Tensor {
        let last = self.layers.len() - 1;
        tch::no_grad(|| {
            let mut h = x.shallow_clone();
            for (i, layer) in self.layers.iter().enumerate() {
                keep(&h);
                let z = linear(layer, &h);
                h = if i == last { z } else { tanh_in_place(z) };
            }
            h
        })
    }
}

impl Module for Mlp {
    fn forward(&self, x: &Tensor) -> Tensor {
        let last = self.layers.len() - 1;
        self.layers
            .iter()
            .enumerate()
            .fold(x.shallow_clone(), |h, (i, layer)| {
                let h = layer.forward(&h);
                if i == last { h } else { h.tanh() }
            })
    }
}

/// x·Wᵀ + b as one fused matrix product (what `nn::Linear` computes).
fn linear(layer: &nn::Linear, x: &Tensor) -> Tensor {
    match &layer.bs {
        Some(bias) => bias.addmm(x, &layer.ws.tr()),
        None => x.mm(&layer.ws.tr()),
    }
}

/// What one [`Mlp::forward_pass`] keeps for its backward pass.
pub struct MlpPass<'a> {
    mlp: &'a Mlp,
    /// Each layer's input: the network's input, then every hidden layer's tanh output.
    inputs: Vec<Tensor>,
    /// The network's output, an autograd leaf: losses are built on it, and its gradient is
    /// what [`MlpPass::backward`] takes through the layers.
    pub output: Tensor,
}

impl MlpPass<'_> {
    /// After the loss's backward pass has filled `output`'s gradient: takes it back through
    /// the layers and adds each layer's weight and bias gradients to theirs, as autograd
    /// would. A pass whose output took no part in the loss contributes nothing.
    pub fn backward(self) {
        let mut grad = self.output.grad();
        if !grad.defined() {
            return;
        }
        tch::no_grad(|| {
            for (i, (layer, input)) in self.mlp.layers.iter().zip(&self.inputs).enumerate().rev() {
                deposit_product(&layer.ws, &grad.tr(), input);
                if let Some(bias) = &layer.bs {
                    deposit(bias, &grad.sum_dim_intlist(0, false, Kind::Float));
                }
                if i > 0 {
                    // Through the tanh that made this layer's input: × (1 − h²).
                    grad = tanh_grad(grad.mm(&layer.ws), input);
                }
            }
        });
    }
}

/// Adds a·b to the parameter's accumulated gradient, as one in-place matrix product.
fn deposit_product(parameter: &Tensor, a: &Tensor, b: &Tensor) {
    let mut accumulated = parameter.grad();
    if accumulated.defined() {
        let _ = accumulated.addmm_(a, b);
    } else {
        deposit(parameter, &a.mm(b));
    }
}

/// Adds `gradient` to the parameter's accumulated gradient (creating it on first use).
fn deposit(parameter: &Tensor, gradient: &Tensor) {
    let mut accumulated = parameter.grad();
    if accumulated.defined() {
        let _ = accumulated.g_add_(gradient);
    } else {
        // No gradient yet (the optimiser had not given it one): let autograd create it.
        tch::with_grad(|| (parameter * gradient).sum(Kind::Float).backward());
    }
}

/// tanh of every element of `z`, in place where `z` is a contiguous f32 tensor on the CPU.
fn tanh_in_place(mut z: Tensor) -> Tensor {
    if !is_cpu_f32(&z) {
        return z.tanh_();
    }
    // SAFETY: `z` is a contiguous f32 CPU tensor (checked) and the fresh result of a matrix
    // product, so nothing else reads or writes its storage while the slice lives.
    elementwise::tanh(unsafe { values_mut(&mut z) });
    z
}

/// `grad` × (1 − h²) for h = tanh(z): the gradient with respect to z, in place.
fn tanh_grad(mut grad: Tensor, h: &Tensor) -> Tensor {
    if !(is_cpu_f32(&grad) && is_cpu_f32(h) && grad.size() == h.size()) {
        return Tensor::tanh_backward(&grad, h);
    }
    // SAFETY: both are contiguous f32 CPU tensors of one shape (checked); `grad` is the fresh
    // result of a matrix product, `h` a stored activation only read here.
    let h = unsafe { std::slice::from_raw_parts(h.data_ptr() as *const f32, h.numel()) };
    elementwise::tanh_grad(unsafe { values_mut(&mut grad) }, h);
    grad
}

fn is_cpu_f32(t: &Tensor) -> bool {
    t.device() == Device::Cpu && t.kind() == Kind::Float && t.is_contiguous()
}

/// The values of a tensor that [`is_cpu_f32`].
///
/// # Safety
/// The tensor must be a contiguous f32 CPU tensor whose storage nothing else touches while
/// the slice lives.
unsafe fn values_mut(t: &mut Tensor) -> &mut [f32] {
    let len = t.numel();
    if len == 0 {
        return &mut [];
    }
    // SAFETY: the caller's promise: `len` floats from the data pointer, used by us alone.
    unsafe { std::slice::from_raw_parts_mut(t.data_ptr() as *mut f32, len) }
}

/// The elementwise parts of the passes, on plain slices, compiled twice: for the baseline
/// x86-64 target and, where the CPU has them (checked once at run time), AVX2 and FMA, which
/// the compiler then uses to handle eight values at a time.
pub mod elementwise {
    use super::LazyLock;

    /// Whether this CPU runs the AVX2 and FMA variants (checked once).
    pub fn avx2_fma() -> bool {
        *AVX2
    }

    static AVX2: LazyLock<bool> = LazyLock::new(|| {
        #[cfg(target_arch = "x86_64")]
        {
            std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    });

    /// Each value replaced by its tanh (within 2 ulp of the exact value; NaN stays NaN).
    pub fn tanh(values: &mut [f32]) {
        #[cfg(target_arch = "x86_64")]
        if *AVX2 {
            // SAFETY: the CPU has AVX2 and FMA (checked above).
            return unsafe { tanh_avx2(values) };
        }
        values
            .iter_mut()
            .for_each(|x| *x = tanh_with::<Separate>(*x));
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn tanh_avx2(values: &mut [f32]) {
        values.iter_mut().for_each(|x| *x = tanh_with::<Fused>(*x));
    }

    /// grad[i] × (1 − h[i]²) into grad.
    pub fn tanh_grad(grad: &mut [f32], h: &[f32]) {
        #[cfg(target_arch = "x86_64")]
        if *AVX2 {
            // SAFETY: as in `tanh`.
            return unsafe { tanh_grad_avx2(grad, h) };
        }
        grad.iter_mut().zip(h).for_each(|(g, h)| *g *= 1.0 - h * h);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn tanh_grad_avx2(grad: &mut [f32], h: &[f32]) {
        grad.iter_mut().zip(h).for_each(|(g, h)| *g *= 1.0 - h * h);
    }

    /// a·b + c, fused into one rounding where the code is compiled with FMA (a call to a slow
    /// software fused multiply-add otherwise, hence the two kinds).
    pub trait MulAdd {
        fn mul_add(a: f32, b: f32, c: f32) -> f32;
    }

    pub struct Fused;
    pub struct Separate;

    impl MulAdd for Fused {
        #[inline(always)]
        fn mul_add(a: f32, b: f32, c: f32) -> f32 {
            a.mul_add(b, c)
        }
    }

    impl MulAdd for Separate {
        #[inline(always)]
        fn mul_add(a: f32, b: f32, c: f32) -> f32 {
            a * b + c
        }
    }

    const LOG2_E: f32 = std::f32::consts::LOG2_E;
    /// ln 2 in two parts (Cody and Waite), so k·ln 2 is exact to f32 for the k used here.
    const LN2_HI: f32 = 0.693_145_75;
    const LN2_LO: f32 = 1.428_606_8e-6;
    /// 1.5 · 2²³: adding it rounds a float of magnitude < 2²² to an integer, which its bits
    /// then hold, with plain additions (vectorisable without SSE4.1's rounding).
    const ROUNDER: f32 = 12_582_912.0;
    /// tanh rounds to ±1 in f32 beyond this.
    const SATURATION: f32 = 9.0;
    /// Below this |x| the odd series is used: (1 − e)/(1 + e) would cancel.
    const SERIES_BELOW: f32 = 0.3;

    /// tanh(x) = sign(x)·(1 − e)/(1 + e) with e = e^(−2|x|), e computed as 2^k·e^r, r within
    /// ±ln 2 / 2, e^r by its Taylor series to r⁷; below |x| = 0.3 the odd series to x⁹
    /// instead. Branch-free, so a loop over it vectorises.
    #[inline(always)]
    pub fn tanh_with<M: MulAdd>(x: f32) -> f32 {
        let a = x.abs();
        // NaN > 9 is false: NaN goes on through and comes out NaN.
        let a = if a > SATURATION { SATURATION } else { a };
        let y = -2.0 * a;
        let shifted = M::mul_add(y, LOG2_E, ROUNDER);
        let k_bits = shifted.to_bits().wrapping_sub(ROUNDER.to_bits()) as i32;
        let k = shifted - ROUNDER;
        let r = M::mul_add(-k, LN2_LO, M::mul_add(-k, LN2_HI, y));
        let horner = |coefficients: &[f32], v: f32| {
            coefficients
                .iter()
                .rev()
                .fold(0.0, |acc, &c| M::mul_add(acc, v, c))
        };
        const EXP: [f32; 8] = [
            1.0,
            1.0,
            1.0 / 2.0,
            1.0 / 6.0,
            1.0 / 24.0,
            1.0 / 120.0,
            1.0 / 720.0,
            1.0 / 5040.0,
        ];
        // 2^k for k in [−26, 0]: the exponent field alone.
        let e = horner(&EXP, r) * f32::from_bits(((k_bits + 127) as u32) << 23);
        let far = (1.0 - e) / (1.0 + e);
        const ODD: [f32; 5] = [1.0, -1.0 / 3.0, 2.0 / 15.0, -17.0 / 315.0, 62.0 / 2835.0];
        let near = a * horner(&ODD, a * a);
        let magnitude = if a < SERIES_BELOW { near } else { far };
        magnitude.copysign(x)
    }

    /// [`tanh_with`] without fused multiply-adds (what any x86-64 CPU runs).
    pub fn tanh_f32(x: f32) -> f32 {
        tanh_with::<Separate>(x)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ulps(a: f32, b: f32) -> i64 {
        (i64::from(a.to_bits() as i32) - i64::from(b.to_bits() as i32)).abs()
    }

    #[test]
    fn fast_tanh_is_within_two_ulp_of_the_exact_value_everywhere() {
        let mut worst = (0, 0.0f32);
        let mut x = -12.0f32;
        while x < 12.0 {
            let exact = f64::from(x).tanh() as f32;
            let error = ulps(elementwise::tanh_f32(x), exact);
            if error > worst.0 {
                worst = (error, x);
            }
            x += 3.7e-5;
        }
        assert!(worst.0 <= 2, "{} ulp at x = {}", worst.0, worst.1);
        for x in [0.0f32, -0.0, 1e-30, 1e-8, 0.3, 9.0, 1e4, f32::INFINITY] {
            let exact = f64::from(x).tanh() as f32;
            assert!(ulps(elementwise::tanh_f32(x), exact) <= 1, "x = {x}");
            assert!(ulps(elementwise::tanh_f32(-x), -exact) <= 1, "x = -{x}");
        }
        assert!(elementwise::tanh_f32(f32::NAN).is_nan());
        // The slice version (vectorised, with fused multiply-adds where the CPU has them) is
        // as close.
        let inputs: Vec<f32> = (0..100_001)
            .map(|i| (i as f32 - 50_000.0) * 2.1e-4)
            .collect();
        let mut values = inputs.clone();
        elementwise::tanh(&mut values);
        for (x, y) in inputs.iter().zip(&values) {
            let exact = f64::from(*x).tanh() as f32;
            assert!(ulps(*y, exact) <= 2, "tanh({x}) = {y}, exactly {exact}");
        }
    }

    #[test]
    fn hand_written_gradients_equal_autograds() {
        let vs = nn::VarStore::new(Device::Cpu);
        tch::manual_seed(3);
        let mlp = Mlp::new(vs.root() / "m", 5, &[7, 6], 3, 0.5);
        let x = Tensor::randn([11, 5], (Kind::Float, Device::Cpu));
        let target = Tensor::randn([11, 3], (Kind::Float, Device::Cpu));
        let loss_of = |out: &Tensor| (out - &target).square().sum(Kind::Float);
        let grads = |vs: &nn::VarStore| -> Vec<Tensor> {
            let mut named: Vec<_> = vs.variables().into_iter().collect();
            named.sort_by(|a, b| a.0.cmp(&b.0));
            named.into_iter().map(|(_, v)| v.grad().copy()).collect()
        };
        loss_of(&mlp.forward(&x)).backward();
        let by_autograd = grads(&vs);
        for (_, v) in vs.variables() {
            let _ = v.grad().zero_();
        }
        let pass = mlp.forward_pass(&x);
        assert!(
            (&pass.output - mlp.forward(&x))
                .abs()
                .max()
                .double_value(&[])
                < 1e-6,
            "the two forward passes agree"
        );
        loss_of(&pass.output).backward();
        pass.backward();
        let by_hand = grads(&vs);
        assert_eq!(by_autograd.len(), 6);
        for (a, h) in by_autograd.iter().zip(&by_hand) {
            let scale = a.abs().max().double_value(&[]).max(1e-6);
            let diff = (a - h).abs().max().double_value(&[]);
            assert!(diff / scale < 1e-5, "autograd {a} vs by hand {h}");
        }
    }

    #[test]
    fn a_pass_adds_to_gradients_it_finds_and_creates_missing_ones() {
        let vs = nn::VarStore::new(Device::Cpu);
        let mlp = Mlp::new(vs.root() / "m", 2, &[3], 1, 1.0);
        let x = Tensor::from_slice(&[0.5f32, -1.0]).reshape([1, 2]);
        let run = || {
            let pass = mlp.forward_pass(&x);
            pass.output.sum(Kind::Float).backward();
            pass.backward();
        };
        run();
        let bias_grad = |vs: &nn::VarStore| vs.variables()["m.l1.bias"].grad().double_value(&[0]);
        assert_eq!(bias_grad(&vs), 1.0, "d(sum of outputs)/d(output bias) = 1");
        run();
        assert_eq!(
            bias_grad(&vs),
            2.0,
            "a second pass accumulates, as autograd does"
        );
    }
}
