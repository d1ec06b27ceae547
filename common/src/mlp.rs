//! The multilayer perceptron every policy and critic is made of, with two ways through it:
//!
//! - [`Module::forward`]: libtorch all the way, differentiable by autograd (the meta-gradients
//!   of the learned LCFs take second derivatives through it);
//! - [`Mlp::forward_pass`] and [`MlpPass::backward`]: the PPO update's path, whose gradients are
//!   taken by hand: the matrix products in libtorch, the tanh and its derivative in one pass
//!   over each activation in Rust on the CPU. Autograd then sees only the small loss graph on
//!   the network's output; on two cores this takes the update from slower than PyTorch's own
//!   to faster (BENCHMARKS.md, "Learner update against PyTorch").

use tch::nn::{self, Module};
use tch::{Device, Kind, Tensor};

use junction_core::activation;

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
    activation::tanh(unsafe { values_mut(&mut z) });
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
    activation::tanh_grad(unsafe { values_mut(&mut grad) }, h);
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

#[cfg(test)]
mod tests {
    use super::*;

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
