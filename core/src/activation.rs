//! The policy network's activation, tanh, and its gradient on plain slices: one definition for
//! every place a policy runs (the learner's passes, the Rust actors, the Python package's
//! `junction.policy` through `junction._native`), so they act bit for bit alike. Compiled twice:
//! for the baseline x86-64 target and, where the CPU has them (checked once at run time), AVX2
//! and FMA, which the compiler then uses to handle eight values at a time.

use std::sync::LazyLock;

/// Whether this CPU runs the AVX2 and FMA variants (checked once).
pub fn avx2_fma() -> bool {
    *AVX2
}

static AVX2: LazyLock<bool> = LazyLock::new(|| {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
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
            let error = ulps(tanh_f32(x), exact);
            if error > worst.0 {
                worst = (error, x);
            }
            x += 3.7e-5;
        }
        assert!(worst.0 <= 2, "{} ulp at x = {}", worst.0, worst.1);
        for x in [0.0f32, -0.0, 1e-30, 1e-8, 0.3, 9.0, 1e4, f32::INFINITY] {
            let exact = f64::from(x).tanh() as f32;
            assert!(ulps(tanh_f32(x), exact) <= 1, "x = {x}");
            assert!(ulps(tanh_f32(-x), -exact) <= 1, "x = -{x}");
        }
        assert!(tanh_f32(f32::NAN).is_nan());
        // The slice version (vectorised, with fused multiply-adds where the CPU has them) is
        // as close.
        let inputs: Vec<f32> = (0..100_001)
            .map(|i| (i as f32 - 50_000.0) * 2.1e-4)
            .collect();
        let mut values = inputs.clone();
        tanh(&mut values);
        for (x, y) in inputs.iter().zip(&values) {
            let exact = f64::from(*x).tanh() as f32;
            assert!(ulps(*y, exact) <= 2, "tanh({x}) = {y}, exactly {exact}");
        }
    }
}
