/// Clamp applied to the gradient path of [`trunc_exp`] (nerfstudio's `trunc_exp`).
pub const TRUNC_EXP_GRAD_MAX: f32 = 15.0;
/// Forward clamp so that `exp` never overflows to `inf`; exp(88) ≈ 1.7e38 is still finite, so
/// this equals `exp(x)` wherever `exp(x)` is representable.
const TRUNC_EXP_FWD_MAX: f32 = 88.0;

/// Density activation: `exp(x)` forward (saturating before f32 overflow).
#[inline]
pub fn trunc_exp(x: f32) -> f32 {
    x.min(TRUNC_EXP_FWD_MAX).exp()
}

/// The (deliberately truncated) derivative used for [`trunc_exp`]: `exp(min(x, 15))`.
///
/// Keeping the gradient bounded is what stops a single huge density from blowing up training.
#[inline]
pub fn trunc_exp_grad(x: f32) -> f32 {
    x.min(TRUNC_EXP_GRAD_MAX).exp()
}

/// Logistic sigmoid.
#[inline]
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}
