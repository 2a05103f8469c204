//! The critic ensemble's loss and gradients on the CPU with the elementwise work fused
//! (`learner.backend: fused`; docs/LEARNER.md "Backends").
//!
//! The same maths as [`CriticEnsemble::forward`] followed by autograd (spec 5.1, 5.3 "Critic"):
//! per hidden layer z = h·W + b, LayerNorm over the features, learned scale and bias, ReLU; then
//! Q = h·w + b and the loss `weight · mean_{k,rows} (Q_k − y)²`. The matrix products stay
//! libtorch's (batched over the members, MKL on the CPU); what changes is everything between
//! them. Autograd runs LayerNorm, its affine part and the ReLU as separate kernels, forward and
//! backward, each a pass over the `[E, B, H]` activations, and keeps the tape; here the forward is
//! one pass per layer ([`norm_relu_forward`]) that leaves the normalised values, the inverse
//! standard deviations and the output for the backward, and the backward is one pass per layer
//! ([`norm_relu_backward`]) that also sums the gradients of the LayerNorm's scale and bias and of
//! the Dense bias. The matrix products of the backward are written out: dW = hᵀ·dz and
//! dh = dz·Wᵀ.
//!
//! With `sac.matmul_precision: bf16` the hidden layers' products, forward and backward, round
//! both operands to bfloat16 and return the product in f32, as [`affine`] and its autograd
//! backward do (AMX or AVX512-BF16 run these several times faster than f32 products); the
//! output layer's dot products and every elementwise pass stay in f32, where the libtorch path
//! rounds the output layer's operands to bf16 too (docs/LEARNER.md "bf16 matmuls").
//!
//! Only contiguous CPU tensors in f32 or f64 (f32 for bf16 matmuls) take this path;
//! [`critic_loss_and_grads`] says `None` otherwise and the caller runs autograd.
//!
//! [`affine`]: crate::nets::affine
use num_traits::Float;
use tch::kind::Element;
use tch::{Device, Kind, Tensor};

use crate::nets::CriticEnsemble;

/// One critic shard's share of a critic update: its weighted loss, the sum of its Q values and
/// the gradients of the loss, in [`CriticEnsemble::named_parameters`] order.
#[derive(Debug)]
pub struct CriticGrads {
    pub loss: Tensor,
    pub q_sum: Tensor,
    pub grads: Vec<Tensor>,
}

/// `weight · mean_{k,b} (Q_k(obs_b, action_b) − target_b)²` over the ensemble's members and
/// its gradients with respect to every parameter (spec 5.3 "Critic" step 4; `weight` is a
/// shard's E_s/E, see [`crate::members`]), or `None` where the fused path does not apply: not
/// the CPU, not f32 or f64, or bf16 matmuls on f64 parameters.
pub fn critic_loss_and_grads(
    critic: &CriticEnsemble,
    obs: &Tensor,
    action: &Tensor,
    target: &Tensor,
    weight: f64,
) -> Option<CriticGrads> {
    if !applies(critic, &[obs, action, target]) {
        return None;
    }
    tch::no_grad(|| match critic.kind() {
        Kind::Float => Some(run::<f32>(critic, obs, action, target, weight)),
        Kind::Double => Some(run::<f64>(critic, obs, action, target, weight)),
        _ => None,
    })
}

/// Whether the fused path takes these inputs: CPU tensors of the parameters' kind, f32 or f64
/// with fp32 matmuls, f32 with bf16 ones.
fn applies(critic: &CriticEnsemble, inputs: &[&Tensor]) -> bool {
    let kind = critic.kind();
    let precision_fits = critic.fp32_matmuls() || kind == Kind::Float;
    precision_fits
        && inputs
            .iter()
            .all(|t| t.device() == Device::Cpu && t.kind() == kind)
}

/// The operand of a product in the critic's matmul precision: itself, or rounded to bfloat16.
fn operand(t: &Tensor, critic: &CriticEnsemble) -> Tensor {
    if critic.fp32_matmuls() {
        t.shallow_clone()
    } else {
        t.to_kind(Kind::BFloat16)
    }
}

/// `a · b` of two [`operand`]s (batched over the leading dim when either is 3-D), in `kind`.
fn product(a: &Tensor, b: &Tensor, kind: Kind) -> Tensor {
    let p = a.matmul(b);
    if p.kind() == kind {
        p
    } else {
        p.to_kind(kind)
    }
}

/// What one hidden layer's forward keeps for the backward.
struct Saved {
    /// The layer's input as a matmul [`operand`]: the shared `[B, I]` input for the first
    /// layer, else `[E, B, H]`.
    input: Tensor,
    /// The layer's kernels as a matmul [`operand`], `[E, I, H]`.
    kernel: Tensor,
    /// LayerNorm's normalised values x̂ `[E, B, H]` (without LayerNorm: unused, empty).
    xhat: Tensor,
    /// 1/√(var + ε) per row, `[E, B]` (without LayerNorm: empty).
    rstd: Tensor,
    /// The layer's output after the ReLU, `[E, B, H]`.
    out: Tensor,
}

fn run<T: Element + Float>(
    critic: &CriticEnsemble,
    obs: &Tensor,
    action: &Tensor,
    target: &Tensor,
    weight: f64,
) -> CriticGrads {
    let pass = Forward::<T>::run(critic, obs, action);
    // The loss and dL/dQ = weight · 2 (Q − y) / (E·B).
    let target = target.contiguous();
    let mut dq = pass.q.empty_like();
    let (loss, q_sum) = {
        let (qs, ys, dqs) = (
            slice::<T>(&pass.q),
            slice::<T>(&target),
            slice_mut::<T>(&mut dq),
        );
        squared_error(qs, ys, dqs, weight)
    };
    let (grads, _) = pass.backward(&dq, Wanted::Parameters);
    let scalar = |v: f64| Tensor::from(v).to_kind(pass.q.kind());
    CriticGrads {
        loss: scalar(loss),
        q_sum: scalar(q_sum),
        grads,
    }
}

/// Q of every member at (obs, action), `[E, B]`, and the gradient with respect to the actions,
/// `[B, A]`, of `coefficient · Σ_{k,b} Q_k(obs_b, action_b)`: the critic's part of the actor
/// loss of spec 5.3 "Actor" (−weight · mean_b mean_k Q_k, so coefficient = −weight / (E·B)).
/// The critic's parameters get no gradient. `None` where the fused path does not apply (see
/// [`critic_loss_and_grads`]).
pub fn critic_action_grad(
    critic: &CriticEnsemble,
    obs: &Tensor,
    action: &Tensor,
    coefficient: f64,
) -> Option<(Tensor, Tensor)> {
    if !applies(critic, &[obs, action]) {
        return None;
    }
    fn run<T: Element + Float>(
        critic: &CriticEnsemble,
        obs: &Tensor,
        action: &Tensor,
        coefficient: f64,
    ) -> (Tensor, Tensor) {
        let pass = Forward::<T>::run(critic, obs, action);
        let dq = pass.q.full_like(coefficient);
        let from = obs.size()[1];
        let (_, action_grad) = pass.backward(&dq, Wanted::Input { from });
        (pass.q, action_grad.expect("asked for"))
    }
    tch::no_grad(|| match critic.kind() {
        Kind::Float => Some(run::<f32>(critic, obs, action, coefficient)),
        Kind::Double => Some(run::<f64>(critic, obs, action, coefficient)),
        _ => None,
    })
}

/// What a backward computes: the parameters' gradients (a critic update), or the gradient with
/// respect to the input's columns `from..` (an actor update wants the actions' and no parameter
/// gradient: those matrix products are skipped).
#[derive(Clone, Copy, PartialEq, Eq)]
enum Wanted {
    Parameters,
    Input { from: i64 },
}

/// A forward pass and what its backward needs.
struct Forward<'a, T> {
    critic: &'a CriticEnsemble,
    /// The shared input concat(obs, action), `[B, I]`.
    x: Tensor,
    /// One per hidden layer.
    saved: Vec<Saved>,
    /// Q, `[E, B]`.
    q: Tensor,
    _kind: std::marker::PhantomData<T>,
}

impl<'a, T: Element + Float> Forward<'a, T> {
    /// Spec 5.1's critic on every member: one GEMM and one fused pass per hidden layer, then
    /// the output layer.
    fn run(critic: &'a CriticEnsemble, obs: &Tensor, action: &Tensor) -> Self {
        let layers = critic.layers();
        let members = critic.members();
        let x = Tensor::cat(&[obs, action], 1).contiguous();
        let rows = x.size()[0];
        let eps = T::from(critic.layer_norm_eps()).expect("ε fits the float type");
        let mut saved: Vec<Saved> = Vec::with_capacity(layers.hidden.len());
        for (i, dense) in layers.hidden.iter().enumerate() {
            let input = operand(
                match saved.last() {
                    Some(prev) => &prev.out,
                    None => &x,
                },
                critic,
            );
            let kernel = operand(&dense.w, critic);
            let batched = if i == 0 {
                input.expand([members, rows, input.size()[1]], false)
            } else {
                input.shallow_clone()
            };
            let mut z = if critic.fp32_matmuls() {
                dense.b.baddbmm(&batched, &kernel, 1.0, 1.0).contiguous()
            } else {
                (product(&batched, &kernel, x.kind()) + &dense.b).contiguous()
            };
            let width = z.size()[2] as usize;
            let per_member = rows as usize * width;
            match layers.norms.get(i) {
                Some(norm) => {
                    let mut out = z.empty_like();
                    let mut rstd = Tensor::empty([members, rows], (z.kind(), Device::Cpu));
                    let (scale, bias) = (norm.scale.contiguous(), norm.bias.contiguous());
                    {
                        let (zs, outs, rs) = (
                            slice_mut::<T>(&mut z),
                            slice_mut::<T>(&mut out),
                            slice_mut::<T>(&mut rstd),
                        );
                        let (scale, bias) = (slice::<T>(&scale), slice::<T>(&bias));
                        for k in 0..members as usize {
                            let part = k * per_member..(k + 1) * per_member;
                            norm_relu_forward(
                                &mut zs[part.clone()],
                                &mut outs[part],
                                &mut rs[k * rows as usize..(k + 1) * rows as usize],
                                &scale[k * width..(k + 1) * width],
                                &bias[k * width..(k + 1) * width],
                                eps,
                            );
                        }
                    }
                    saved.push(Saved {
                        input,
                        kernel,
                        xhat: z,
                        rstd,
                        out,
                    });
                }
                None => {
                    let _ = z.relu_();
                    saved.push(Saved {
                        input,
                        kernel,
                        xhat: Tensor::empty([0], (z.kind(), Device::Cpu)),
                        rstd: Tensor::empty([0], (z.kind(), Device::Cpu)),
                        out: z,
                    });
                }
            }
        }
        let last = &saved
            .last()
            .expect("at least one hidden layer (validated)")
            .out;
        let width = last.size()[2] as usize;
        let per_member = rows as usize * width;
        let (w_out, b_out) = (layers.output.w.contiguous(), layers.output.b.contiguous());
        let (w_out, b_out) = (slice::<T>(&w_out), slice::<T>(&b_out));
        let h_last = slice::<T>(last);
        let mut q = Tensor::empty([members, rows], (last.kind(), Device::Cpu));
        {
            let qs = slice_mut::<T>(&mut q);
            for k in 0..members as usize {
                output_forward(
                    &h_last[k * per_member..(k + 1) * per_member],
                    &w_out[k * width..(k + 1) * width],
                    b_out[k],
                    &mut qs[k * rows as usize..(k + 1) * rows as usize],
                );
            }
        }
        Self {
            critic,
            x,
            saved,
            q,
            _kind: std::marker::PhantomData,
        }
    }

    /// Backpropagates dL/dQ (`[E, B]`): the parameters' gradients in
    /// [`CriticEnsemble::named_parameters`] order (empty unless `wanted` says parameters), and
    /// dL/dx of the input columns `wanted` names, `[B, ·]`, summed over the members.
    fn backward(&self, dq: &Tensor, wanted: Wanted) -> (Vec<Tensor>, Option<Tensor>) {
        let layers = self.critic.layers();
        let members = self.critic.members();
        let rows = self.x.size()[0];
        let kind = self.q.kind();
        let params = wanted == Wanted::Parameters;
        let last = &self.saved.last().expect("at least one hidden layer").out;
        let width = last.size()[2] as usize;
        let per_member = rows as usize * width;
        let w_out = layers.output.w.contiguous();
        let mut grads: Vec<(String, Tensor)> = Vec::with_capacity(4 * layers.hidden.len() + 2);
        let mut d_w_out = Tensor::zeros([members, width as i64, 1], (kind, Device::Cpu));
        let mut dh = last.empty_like();
        {
            let (h_last, dqs, w_out) = (slice::<T>(last), slice::<T>(dq), slice::<T>(&w_out));
            let (dws, dhs) = (slice_mut::<T>(&mut d_w_out), slice_mut::<T>(&mut dh));
            for k in 0..members as usize {
                output_backward(
                    &h_last[k * per_member..(k + 1) * per_member],
                    &dqs[k * rows as usize..(k + 1) * rows as usize],
                    &w_out[k * width..(k + 1) * width],
                    &mut dws[k * width..(k + 1) * width],
                    &mut dhs[k * per_member..(k + 1) * per_member],
                );
            }
        }
        if params {
            grads.push(("output.kernel".into(), d_w_out));
            grads.push((
                "output.bias".into(),
                dq.sum_dim_intlist(1, false, None).view([members, 1, 1]),
            ));
        }
        let mut input_grad = None;
        for (i, layer) in self.saved.iter().enumerate().rev() {
            let dense = &layers.hidden[i];
            let width = dh.size()[2] as usize;
            let per_member = rows as usize * width;
            let stacked = || Tensor::zeros([members, 1, width as i64], (kind, Device::Cpu));
            let mut dbias = stacked();
            match layers.norms.get(i) {
                Some(norm) => {
                    let (mut dscale, mut dnorm_bias) = (stacked(), stacked());
                    let scale = norm.scale.contiguous();
                    {
                        let dhs = slice_mut::<T>(&mut dh);
                        let (outs, xs, rs) = (
                            slice::<T>(&layer.out),
                            slice::<T>(&layer.xhat),
                            slice::<T>(&layer.rstd),
                        );
                        let scale = slice::<T>(&scale);
                        let (ds, dn, db) = (
                            slice_mut::<T>(&mut dscale),
                            slice_mut::<T>(&mut dnorm_bias),
                            slice_mut::<T>(&mut dbias),
                        );
                        for k in 0..members as usize {
                            let part = k * per_member..(k + 1) * per_member;
                            let feature = k * width..(k + 1) * width;
                            norm_relu_backward(
                                &mut dhs[part.clone()],
                                &outs[part.clone()],
                                &xs[part],
                                &rs[k * rows as usize..(k + 1) * rows as usize],
                                &scale[feature.clone()],
                                NormGrads {
                                    scale: &mut ds[feature.clone()],
                                    bias: &mut dn[feature.clone()],
                                    dense_bias: &mut db[feature],
                                },
                            );
                        }
                    }
                    if params {
                        grads.push((format!("norm{i}.scale"), dscale));
                        grads.push((format!("norm{i}.bias"), dnorm_bias));
                    }
                }
                None => {
                    let dhs = slice_mut::<T>(&mut dh);
                    let outs = slice::<T>(&layer.out);
                    let db = slice_mut::<T>(&mut dbias);
                    for k in 0..members as usize {
                        let part = k * per_member..(k + 1) * per_member;
                        relu_backward(
                            &mut dhs[part.clone()],
                            &outs[part],
                            &mut db[k * width..(k + 1) * width],
                        );
                    }
                }
            }
            let dz = operand(&dh, self.critic);
            if params {
                let kernel_grad = if i == 0 {
                    product(&layer.input.tr(), &dz, kind)
                } else {
                    product(&layer.input.transpose(1, 2), &dz, kind)
                };
                grads.push((format!("hidden{i}.kernel"), kernel_grad));
                grads.push((format!("hidden{i}.bias"), dbias));
            }
            dh = if i > 0 {
                product(&dz, &layer.kernel.transpose(1, 2), kind).contiguous()
            } else {
                if let Wanted::Input { from } = wanted {
                    // dL/dx[from..] = Σ_k dz_k · W_k[from..]ᵀ: only the input columns asked for.
                    let fan_in = dense.w.size()[1];
                    let w = layer.kernel.narrow(1, from, fan_in - from).transpose(1, 2);
                    input_grad = Some(product(&dz, &w, kind).sum_dim_intlist(0, false, None));
                }
                dh
            };
        }
        grads.sort_by(|a, b| a.0.cmp(&b.0));
        (grads.into_iter().map(|(_, g)| g).collect(), input_grad)
    }
}

/// Spec 5.3 "Critic" step 4 for one shard, with its gradient: over Q `[E, B]` (row-major, member
/// by member) and targets y `[B]`, returns (weight · mean (Q − y)², Σ Q) and writes
/// dQ = weight · 2 (Q − y) / (E·B). Sums in f64.
pub fn squared_error<T: Float>(q: &[T], y: &[T], dq: &mut [T], weight: f64) -> (f64, f64) {
    let n = q.len() as f64;
    let (mut loss, mut q_sum) = (0.0f64, 0.0f64);
    for (i, (&qi, d)) in q.iter().zip(dq.iter_mut()).enumerate() {
        let qi = qi.to_f64().unwrap_or(f64::NAN);
        let diff = qi - y[i % y.len()].to_f64().unwrap_or(f64::NAN);
        loss += diff * diff;
        q_sum += qi;
        *d = T::from(weight * 2.0 * diff / n).unwrap_or_else(T::nan);
    }
    (weight * loss / n, q_sum)
}

/// Values per lane group: the kernels' inner loops run over fixed groups of this many values,
/// with this many partial sums, which the compiler turns into vector code (two 256-bit vectors of
/// f32 under AVX2).
const LANES: usize = 16;

/// Defines `pub fn $name` that runs `$generic` compiled for AVX2 and FMA where the processor has
/// them (checked once per call, cached by std), else as the crate is compiled (SSE2 on x86-64).
/// libtorch picks its vector kernels at run time the same way.
macro_rules! vectorized {
    ($(#[$doc:meta])* fn $name:ident / $generic:ident <T>($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)?) => {
        $(#[$doc])*
        pub fn $name<T: Float>($($arg: $ty),*) $(-> $ret)? {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2,fma")]
                unsafe fn avx2<T: Float>($($arg: $ty),*) $(-> $ret)? {
                    $generic($($arg),*)
                }
                if std::arch::is_x86_feature_detected!("avx2")
                    && std::arch::is_x86_feature_detected!("fma")
                {
                    // SAFETY: the processor has AVX2 and FMA (checked just above).
                    return unsafe { avx2($($arg),*) };
                }
            }
            $generic($($arg),*)
        }
    };
}

vectorized! {
    /// One member's hidden-layer activation forward (spec 5.1: LayerNorm, learned scale and
    /// bias, ReLU), a row of `scale.len()` features at a time: z ← x̂ = (z − mean) / √(var + ε),
    /// the normalised row kept for the backward; out ← max(0, x̂ · scale + bias);
    /// rstd ← 1/√(var + ε), one per row. The variance is the biased one over the row, as
    /// LayerNorm's.
    fn norm_relu_forward / norm_relu_forward_generic<T>(
        z: &mut [T],
        out: &mut [T],
        rstd: &mut [T],
        scale: &[T],
        bias: &[T],
        eps: T,
    )
}

#[inline(always)]
fn norm_relu_forward_generic<T: Float>(
    z: &mut [T],
    out: &mut [T],
    rstd: &mut [T],
    scale: &[T],
    bias: &[T],
    eps: T,
) {
    let width = scale.len();
    let n = T::from(width).expect("a width fits the float type");
    for ((row, out), r) in z
        .chunks_exact_mut(width)
        .zip(out.chunks_exact_mut(width))
        .zip(rstd.iter_mut())
    {
        let mean = lane_sum(row, |v| v) / n;
        let var = lane_sum(row, |v| (v - mean) * (v - mean)) / n;
        let inv = T::one() / (var + eps).sqrt();
        *r = inv;
        for (((v, o), &s), &b) in row.iter_mut().zip(out.iter_mut()).zip(scale).zip(bias) {
            let xhat = (*v - mean) * inv;
            *v = xhat;
            *o = relu(xhat * s + b);
        }
    }
}

/// The gradients one hidden layer's backward sums over its rows, one value per feature.
pub struct NormGrads<'a, T> {
    /// LayerNorm's scale: Σ g · x̂.
    pub scale: &'a mut [T],
    /// LayerNorm's bias: Σ g.
    pub bias: &'a mut [T],
    /// The Dense layer's bias: Σ dz.
    pub dense_bias: &'a mut [T],
}

vectorized! {
    /// The backward of [`norm_relu_forward`] for one member's rows: given dL/d(out) in `grad`,
    /// `out`, x̂ and rstd from the forward, and the LayerNorm scale, writes dL/dz into `grad` and
    /// adds the rows' parameter gradients to `sums`. With g = grad · [out > 0] (ReLU's derivative,
    /// 0 at 0 as libtorch's) and ĝ = g · scale: dz = rstd · (ĝ − mean ĝ − x̂ · mean(ĝ · x̂)).
    fn norm_relu_backward / norm_relu_backward_generic<T>(
        grad: &mut [T],
        out: &[T],
        xhat: &[T],
        rstd: &[T],
        scale: &[T],
        sums: NormGrads<'_, T>,
    )
}

#[inline(always)]
fn norm_relu_backward_generic<T: Float>(
    grad: &mut [T],
    out: &[T],
    xhat: &[T],
    rstd: &[T],
    scale: &[T],
    sums: NormGrads<'_, T>,
) {
    let width = scale.len();
    let n = T::from(width).expect("a width fits the float type");
    let NormGrads {
        scale: d_scale,
        bias: d_bias,
        dense_bias: d_dense,
    } = sums;
    for (((g_row, o_row), x_row), &r) in grad
        .chunks_exact_mut(width)
        .zip(out.chunks_exact(width))
        .zip(xhat.chunks_exact(width))
        .zip(rstd)
    {
        // ĝ into the row, the parameter sums, and the two means' partial sums, per lane: fixed
        // groups of LANES values, so that the loop has no bounds checks and becomes vector code.
        let (mut acc_g, mut acc_gx) = ([T::zero(); LANES], [T::zero(); LANES]);
        let groups = g_row
            .chunks_exact_mut(LANES)
            .zip(o_row.chunks_exact(LANES))
            .zip(x_row.chunks_exact(LANES))
            .zip(scale.chunks_exact(LANES))
            .zip(d_scale.chunks_exact_mut(LANES))
            .zip(d_bias.chunks_exact_mut(LANES));
        for (((((g, o), x), s), ds), db) in groups {
            let g: &mut [T; LANES] = g.try_into().expect("a full group");
            let o: &[T; LANES] = o.try_into().expect("a full group");
            let x: &[T; LANES] = x.try_into().expect("a full group");
            let s: &[T; LANES] = s.try_into().expect("a full group");
            let ds: &mut [T; LANES] = ds.try_into().expect("a full group");
            let db: &mut [T; LANES] = db.try_into().expect("a full group");
            for l in 0..LANES {
                // A select on the (random) ReLU mask, not a branch.
                let masked = if o[l] > T::zero() { g[l] } else { T::zero() };
                ds[l] = ds[l] + masked * x[l];
                db[l] = db[l] + masked;
                let gs = masked * s[l];
                g[l] = gs;
                acc_g[l] = acc_g[l] + gs;
                acc_gx[l] = acc_gx[l] + gs * x[l];
            }
        }
        let (mut sum_g, mut sum_gx) = (fold(&acc_g), fold(&acc_gx));
        for k in width - width % LANES..width {
            let masked = if o_row[k] > T::zero() {
                g_row[k]
            } else {
                T::zero()
            };
            d_scale[k] = d_scale[k] + masked * x_row[k];
            d_bias[k] = d_bias[k] + masked;
            let gs = masked * scale[k];
            g_row[k] = gs;
            sum_g = sum_g + gs;
            sum_gx = sum_gx + gs * x_row[k];
        }
        let (mean_g, mean_gx) = (sum_g / n, sum_gx / n);
        for ((g, &x), db) in g_row.iter_mut().zip(x_row).zip(d_dense.iter_mut()) {
            let dz = r * (*g - mean_g - x * mean_gx);
            *g = dz;
            *db = *db + dz;
        }
    }
}

vectorized! {
    /// ReLU's backward without LayerNorm, for one member's rows: grad ← grad · [out > 0], and
    /// the Dense bias's gradient Σ grad per feature added to `dense_bias`.
    fn relu_backward / relu_backward_generic<T>(grad: &mut [T], out: &[T], dense_bias: &mut [T])
}

#[inline(always)]
fn relu_backward_generic<T: Float>(grad: &mut [T], out: &[T], dense_bias: &mut [T]) {
    let width = dense_bias.len();
    for (g_row, o_row) in grad.chunks_exact_mut(width).zip(out.chunks_exact(width)) {
        for ((g, &o), db) in g_row.iter_mut().zip(o_row).zip(dense_bias.iter_mut()) {
            if o <= T::zero() {
                *g = T::zero();
            }
            *db = *db + *g;
        }
    }
}

vectorized! {
    /// The output layer Dense(1) of one member, forward: q_r = h_r · w + b for every row r of
    /// `h` (`w.len()` features each).
    fn output_forward / output_forward_generic<T>(h: &[T], w: &[T], b: T, q: &mut [T])
}

#[inline(always)]
fn output_forward_generic<T: Float>(h: &[T], w: &[T], b: T, q: &mut [T]) {
    for (row, q) in h.chunks_exact(w.len()).zip(q.iter_mut()) {
        *q = b + lane_dot(row, w);
    }
}

vectorized! {
    /// The output layer Dense(1) of one member, backward: given dL/dq per row, adds
    /// Σ_r dq_r · h_r to `dw` and writes dL/dh_r = dq_r · w into `dh`.
    fn output_backward / output_backward_generic<T>(
        h: &[T],
        dq: &[T],
        w: &[T],
        dw: &mut [T],
        dh: &mut [T],
    )
}

#[inline(always)]
fn output_backward_generic<T: Float>(h: &[T], dq: &[T], w: &[T], dw: &mut [T], dh: &mut [T]) {
    let width = w.len();
    for ((row, &d), dh_row) in h
        .chunks_exact(width)
        .zip(dq)
        .zip(dh.chunks_exact_mut(width))
    {
        for (((&x, acc), out), &wj) in row.iter().zip(dw.iter_mut()).zip(dh_row.iter_mut()).zip(w) {
            *acc = *acc + d * x;
            *out = d * wj;
        }
    }
}

#[inline(always)]
fn relu<T: Float>(y: T) -> T {
    if y > T::zero() {
        y
    } else {
        T::zero()
    }
}

/// Σ f(v) over `values`, in [`LANES`] partial sums.
#[inline(always)]
fn lane_sum<T: Float>(values: &[T], f: impl Fn(T) -> T) -> T {
    let mut acc = [T::zero(); LANES];
    let chunks = values.chunks_exact(LANES);
    let rest = chunks.remainder();
    for chunk in chunks {
        for l in 0..LANES {
            acc[l] = acc[l] + f(chunk[l]);
        }
    }
    rest.iter().fold(fold(&acc), |s, &v| s + f(v))
}

/// Σ a·b over two equally long slices, in [`LANES`] partial sums.
#[inline(always)]
fn lane_dot<T: Float>(a: &[T], b: &[T]) -> T {
    let mut acc = [T::zero(); LANES];
    let (ca, cb) = (a.chunks_exact(LANES), b.chunks_exact(LANES));
    let rest = ca.remainder().iter().zip(cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..LANES {
            acc[l] = acc[l] + x[l] * y[l];
        }
    }
    rest.fold(fold(&acc), |s, (&x, &y)| s + x * y)
}

#[inline(always)]
fn fold<T: Float>(acc: &[T; LANES]) -> T {
    acc.iter().fold(T::zero(), |s, &v| s + v)
}

/// The elements of a contiguous CPU tensor of element type `T`.
fn slice<T: Element>(t: &Tensor) -> &[T] {
    assert!(
        t.device() == Device::Cpu && t.kind() == T::KIND && t.is_contiguous(),
        "a contiguous CPU tensor of {:?}",
        T::KIND
    );
    let numel = t.numel();
    if numel == 0 {
        return &[];
    }
    // SAFETY: `t` is a contiguous CPU tensor of `numel` elements of type `T` (checked above), so
    // its data pointer addresses `numel` initialised `T`s, which live as long as `t` does.
    unsafe { std::slice::from_raw_parts(t.data_ptr() as *const T, numel) }
}

/// The elements of a contiguous CPU tensor of element type `T`, to write. Callers pass only
/// tensors this module allocated and has not shared, so no other view writes them meanwhile.
fn slice_mut<T: Element>(t: &mut Tensor) -> &mut [T] {
    let numel = slice::<T>(t).len();
    if numel == 0 {
        return &mut [];
    }
    // SAFETY: as in `slice`; the tensor is borrowed mutably and is one this module made (a fresh
    // matmul output or allocation), whose storage no other tensor views.
    unsafe { std::slice::from_raw_parts_mut(t.data_ptr() as *mut T, numel) }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sac::mean_squared_td_error;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rfcl_core::config::{MatmulPrecision, NetworkConfig};
    use tch::nn;

    /// The loss and gradients of autograd, as the libtorch path takes them.
    fn autograd(
        critic: &CriticEnsemble,
        obs: &Tensor,
        action: &Tensor,
        target: &Tensor,
        weight: f64,
    ) -> (f64, Vec<Tensor>) {
        let q = critic.forward(obs, action);
        let loss = mean_squared_td_error(&q, target) * weight;
        let params: Vec<Tensor> = critic
            .named_parameters()
            .into_iter()
            .map(|(_, p)| p)
            .collect();
        let grads = Tensor::run_backward(&[&loss], &params, false, false);
        (loss.double_value(&[]), grads)
    }

    /// A trained-looking critic: its parameters moved off their init so LayerNorm's scale and
    /// bias and every bias matter.
    fn critic(
        kind: Kind,
        members: i64,
        layer_norm: bool,
        widths: &[u32],
    ) -> (nn::VarStore, CriticEnsemble) {
        critic_in(kind, members, layer_norm, widths, MatmulPrecision::Fp32)
    }

    fn critic_in(
        kind: Kind,
        members: i64,
        layer_norm: bool,
        widths: &[u32],
        precision: MatmulPrecision,
    ) -> (nn::VarStore, CriticEnsemble) {
        let mut vs = nn::VarStore::new(Device::Cpu);
        vs.set_kind(kind);
        let net = NetworkConfig {
            critic_features: widths.to_vec(),
            critic_layer_norm: layer_norm,
            ..NetworkConfig::default()
        };
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let critic = CriticEnsemble::new(&vs.root(), &mut rng, 11, members, &net, precision);
        tch::manual_seed(3);
        tch::no_grad(|| {
            for (_, p) in vs.variables() {
                let _ = p.shallow_clone().g_add_(&(p.randn_like() * 0.3));
            }
        });
        (vs, critic)
    }

    /// The fused path's loss and every gradient equal autograd's: exactly up to summation order
    /// in f64, within fp32 tolerance in f32; for the whole ensemble, for a shard of it (narrowed
    /// parameters, as the member threads run it), and without LayerNorm.
    #[test]
    fn loss_and_gradients_equal_autograds() {
        for (kind, tol) in [(Kind::Double, 1e-10), (Kind::Float, 2e-5)] {
            for (layer_norm, widths) in [(true, &[32u32, 24, 16][..]), (false, &[20, 12][..])] {
                let (_vs, full) = critic(kind, 5, layer_norm, widths);
                let rows = 9;
                let obs = Tensor::randn([rows, 8], (kind, Device::Cpu));
                let action = Tensor::randn([rows, 3], (kind, Device::Cpu));
                let target = Tensor::randn([rows], (kind, Device::Cpu));
                for (shard, weight) in
                    [(full.shard(0, 5, true), 1.0), (full.shard(1, 3, true), 0.6)]
                {
                    let (loss, grads) = autograd(&shard, &obs, &action, &target, weight);
                    let fused =
                        critic_loss_and_grads(&shard, &obs, &action, &target, weight).unwrap();
                    let rel = |a: f64, b: f64| (a - b).abs() / b.abs().max(1.0);
                    assert!(
                        rel(fused.loss.double_value(&[]), loss) < tol,
                        "{kind:?} loss"
                    );
                    let q_sum = shard
                        .forward(&obs, &action)
                        .sum(Kind::Double)
                        .double_value(&[]);
                    assert!(rel(fused.q_sum.double_value(&[]), q_sum) < tol);
                    let names: Vec<String> = shard
                        .named_parameters()
                        .into_iter()
                        .map(|(n, _)| n)
                        .collect();
                    assert_eq!(fused.grads.len(), grads.len());
                    for ((name, got), want) in names.iter().zip(&fused.grads).zip(&grads) {
                        assert_eq!(got.size(), want.size(), "{name}");
                        let scale = want.abs().max().double_value(&[]).max(1e-3);
                        let diff = (got - want).abs().max().double_value(&[]) / scale;
                        assert!(
                            diff < tol,
                            "{kind:?} layer_norm {layer_norm} {name}: {diff:e}"
                        );
                    }
                }
            }
        }
    }

    /// The critic's part of the actor update: Q and the gradient with respect to the actions
    /// equal autograd's, with no gradient for the critic's parameters.
    #[test]
    fn action_gradient_equals_autograds() {
        for (kind, tol) in [(Kind::Double, 1e-10), (Kind::Float, 2e-5)] {
            let (_vs, full) = critic(kind, 4, true, &[32, 24]);
            let frozen = full.shard(0, 4, false);
            let obs = Tensor::randn([7, 8], (kind, Device::Cpu));
            let action = Tensor::randn([7, 3], (kind, Device::Cpu)).set_requires_grad(true);
            let coefficient = -0.3 / 28.0;
            let q = frozen.forward(&obs, &action);
            let want =
                Tensor::run_backward(&[&(q.sum(None) * coefficient)], &[&action], false, false);
            let (got_q, got) =
                critic_action_grad(&frozen, &obs, &action.detach(), coefficient).unwrap();
            let scale = want[0].abs().max().double_value(&[]);
            let diff = (&got - &want[0]).abs().max().double_value(&[]) / scale;
            assert!(diff < tol, "{kind:?}: {diff:e}");
            assert_eq!(got.size(), [7, 3]);
            let q_diff = (&got_q - q.detach()).abs().max().double_value(&[]);
            assert!(q_diff < tol, "{kind:?} q: {q_diff:e}");
        }
    }

    /// Inputs on another kind than the parameters, or bf16 matmuls on f64 parameters: not this
    /// path.
    #[test]
    fn other_precisions_and_kinds_are_left_to_autograd() {
        let (_vs, full) = critic(Kind::Float, 2, true, &[8]);
        let obs = Tensor::randn([4, 8], (Kind::Double, Device::Cpu));
        let action = Tensor::randn([4, 3], (Kind::Double, Device::Cpu));
        let target = Tensor::randn([4], (Kind::Double, Device::Cpu));
        assert!(critic_loss_and_grads(&full, &obs, &action, &target, 1.0).is_none());
        let (_vs, f64_bf16) = critic_in(Kind::Double, 2, true, &[8], MatmulPrecision::Bf16);
        assert!(critic_loss_and_grads(&f64_bf16, &obs, &action, &target, 1.0).is_none());
        assert!(critic_action_grad(&f64_bf16, &obs, &action, 1.0).is_none());
    }

    /// With bf16 matmuls the fused loss, Q and gradients stay within bf16's rounding of
    /// autograd's through the bf16 products (8 significant bits: a few 1e-3 relative per
    /// product; the fused output layer stays f32, autograd's rounds it too), and the same
    /// holds for the action gradient of an actor update.
    #[test]
    fn bf16_matmuls_stay_within_bf16_rounding_of_autograds() {
        let tol = 3e-2;
        let (_vs, full) = critic_in(Kind::Float, 4, true, &[64, 48], MatmulPrecision::Bf16);
        let rows = 32;
        let obs = Tensor::randn([rows, 8], (Kind::Float, Device::Cpu));
        let action = Tensor::randn([rows, 3], (Kind::Float, Device::Cpu));
        let target = Tensor::randn([rows], (Kind::Float, Device::Cpu));
        let shard = full.shard(0, 4, true);
        let (loss, grads) = autograd(&shard, &obs, &action, &target, 0.7);
        let fused = critic_loss_and_grads(&shard, &obs, &action, &target, 0.7).unwrap();
        let got = fused.loss.double_value(&[]);
        assert!(
            (got - loss).abs() / loss.abs() < tol,
            "loss {got} vs {loss}"
        );
        assert_eq!(fused.grads.len(), grads.len());
        for (got, want) in fused.grads.iter().zip(&grads) {
            assert_eq!(got.kind(), Kind::Float);
            let scale = want.abs().max().double_value(&[]).max(1e-3);
            let diff = (got - want).abs().max().double_value(&[]) / scale;
            assert!(diff < tol, "{diff:e}");
        }
        let frozen = full.shard(0, 4, false);
        let action = action.set_requires_grad(true);
        let q = frozen.forward(&obs, &action);
        let want = Tensor::run_backward(&[&(q.sum(None) * -0.01)], &[&action], false, false);
        let (got_q, got) = critic_action_grad(&frozen, &obs, &action.detach(), -0.01).unwrap();
        let scale = want[0].abs().max().double_value(&[]);
        let diff = (&got - &want[0]).abs().max().double_value(&[]) / scale;
        assert!(diff < tol, "action gradient {diff:e}");
        let q_scale = q.abs().max().double_value(&[]).max(1.0);
        let q_diff = (&got_q - q.detach()).abs().max().double_value(&[]) / q_scale;
        assert!(q_diff < tol, "q {q_diff:e}");
    }

    /// One row of 4 features by hand: z = (1, 2, 3, 6), mean 3, var (4 + 1 + 0 + 9)/4 = 3.5,
    /// rstd = 1/√(3.5 + 0.5) = 0.5, x̂ = (−1, −0.5, 0, 1.5); scale 2, bias (0, 0, 1, −4):
    /// out = relu(−2, −1, 1, −1) = (0, 0, 1, 0).
    #[test]
    fn norm_relu_forward_by_hand() {
        let mut z = [1.0f64, 2.0, 3.0, 6.0];
        let (mut out, mut rstd) = ([9.0; 4], [9.0]);
        norm_relu_forward(
            &mut z,
            &mut out,
            &mut rstd,
            &[2.0; 4],
            &[0.0, 0.0, 1.0, -4.0],
            0.5,
        );
        assert_eq!(z, [-1.0, -0.5, 0.0, 1.5]);
        assert_eq!(out, [0.0, 0.0, 1.0, 0.0]);
        assert_eq!(rstd, [0.5]);
    }

    /// The backward of the row above with dL/dout = (1, 1, 1, 1): only feature 2 passes the ReLU,
    /// g = (0, 0, 1, 0), ĝ = g · 2 = (0, 0, 2, 0), mean ĝ = 0.5, mean(ĝ·x̂) = 0;
    /// dz = 0.5 · (ĝ − 0.5 − x̂·0) = (−0.25, −0.25, 0.75, −0.25). Sums: scale Σ g·x̂ = (0, 0, 0, 0),
    /// bias Σ g = (0, 0, 1, 0), Dense bias Σ dz = dz.
    #[test]
    fn norm_relu_backward_by_hand() {
        let mut grad = [1.0f64; 4];
        let (mut ds, mut db, mut dd) = ([0.0; 4], [0.0; 4], [0.0; 4]);
        norm_relu_backward(
            &mut grad,
            &[0.0, 0.0, 1.0, 0.0],
            &[-1.0, -0.5, 0.0, 1.5],
            &[0.5],
            &[2.0; 4],
            NormGrads {
                scale: &mut ds,
                bias: &mut db,
                dense_bias: &mut dd,
            },
        );
        assert_eq!(grad, [-0.25, -0.25, 0.75, -0.25]);
        assert_eq!((ds, db, dd), ([0.0; 4], [0.0, 0.0, 1.0, 0.0], grad));
    }

    /// Q = (1, 3) for one member, y = (0, 1), weight 0.5: loss = 0.5 · (1 + 4)/2 = 1.25,
    /// Σ Q = 4, dQ = 0.5 · 2 · (1, 2)/2 = (0.5, 1).
    #[test]
    fn squared_error_by_hand() {
        let mut dq = [0.0f32; 2];
        let (loss, q_sum) = squared_error(&[1.0f32, 3.0], &[0.0, 1.0], &mut dq, 0.5);
        assert_eq!((loss, q_sum), (1.25, 4.0));
        assert_eq!(dq, [0.5, 1.0]);
    }
}
