//! Adam (spec 5.3 "Optimisers": β1 0.9, β2 0.999, ε 1e-8, no clipping, no weight decay), in place.
//!
//! Not `tch::nn::Optimizer`: libtorch's C++ optimizer state (moments, step) is not reachable
//! through tch, and spec 4.1 needs it in checkpoints ("each model's state = params + optimizer
//! state + step"). The update is torch's single-tensor Adam, in place; gradients come from
//! `torch::autograd::grad` (no `.grad` accumulation, no zeroing).
//!
//! On the CPU a step is one pass over each parameter ([`adam_in_one_pass`]): as a chain of
//! libtorch ops it was seven passes over the ensemble's parameters and moments, which are larger
//! than the caches, and libtorch's own fused Adam (`_fused_adam_`) is not reachable through tch.
//! Elsewhere (CUDA) the step stays a chain of in-place libtorch ops.
use num_traits::Float;
use tch::kind::Element;
use tch::{nn, Device, Tensor};

#[derive(Debug)]
pub struct Adam {
    /// The parameters' names, sorted; `tensors` holds them and their state in this order.
    names: Vec<String>,
    /// Every parameter and its state: the slice that [`step`](Self::step) steps.
    tensors: AdamSlice,
    step: i64,
    lr: f64,
    beta1: f64,
    beta2: f64,
    eps: f64,
}

impl Adam {
    /// Adam over every trainable variable of `vs`.
    pub fn new(vs: &nn::VarStore, lr: f64, beta1: f64, beta2: f64, eps: f64) -> Self {
        let mut named: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
        named.sort_by(|a, b| a.0.cmp(&b.0));
        let (names, params): (Vec<String>, Vec<Tensor>) = named.into_iter().unzip();
        let zeros = || params.iter().map(|p| p.zeros_like().detach()).collect();
        Self {
            names,
            tensors: AdamSlice {
                exp_avg: zeros(),
                exp_avg_sq: zeros(),
                scratch: zeros(),
                params,
            },
            step: 0,
            lr,
            beta1,
            beta2,
            eps,
        }
    }

    /// The parameters, in the order [`step`](Self::step) expects their gradients.
    pub fn params(&self) -> Vec<&Tensor> {
        self.tensors.params.iter().collect()
    }

    /// Gradients of `loss` w.r.t. the parameters only (autograd computes nothing for other
    /// leaves, e.g. a critic inside the actor loss), then one Adam step.
    pub fn minimize(&mut self, loss: &Tensor) {
        let grads = Tensor::run_backward(&[loss], &self.params(), false, false);
        self.step(grads);
    }

    /// One Adam step with the given gradients (consumed as scratch).
    pub fn step(&mut self, grads: Vec<Tensor>) {
        let step = self.begin_step();
        self.tensors.step(step, grads);
    }

    /// Counts a step and returns its scalars, for [`AdamSlice::step`] on every slice of the
    /// parameters (see [`slice`](Self::slice)).
    pub fn begin_step(&mut self) -> AdamStep {
        self.step += 1;
        let bias1 = 1.0 - self.beta1.powi(self.step as i32);
        let bias2_sqrt = (1.0 - self.beta2.powi(self.step as i32)).sqrt();
        // lr · m̂ / (√v̂ + ε) = m / ((√v + ε·√c2) · c1 / (lr · √c2))
        AdamStep {
            step_size: self.lr * bias2_sqrt / bias1,
            eps: self.eps * bias2_sqrt,
            beta1: self.beta1,
            beta2: self.beta2,
        }
    }

    /// Entries `start..start + len` along the first dimension of every parameter and of its
    /// optimiser state, as views of them: a critic ensemble's members, whose disjoint slices
    /// threads can step at once. Every parameter must have that first dimension.
    pub fn slice(&self, start: i64, len: i64) -> AdamSlice {
        let narrow = |ts: &[Tensor]| -> Vec<Tensor> {
            ts.iter()
                .map(|t| t.detach().narrow(0, start, len))
                .collect()
        };
        let all = &self.tensors;
        AdamSlice {
            params: narrow(&all.params),
            exp_avg: narrow(&all.exp_avg),
            exp_avg_sq: narrow(&all.exp_avg_sq),
            scratch: narrow(&all.scratch),
        }
    }

    /// Steps taken so far.
    pub fn step_count(&self) -> i64 {
        self.step
    }

    /// The optimizer state as named tensors (`exp_avg.<param>`, `exp_avg_sq.<param>`, `step`),
    /// for checkpoints.
    pub fn state(&self) -> Vec<(String, Tensor)> {
        let mut state = vec![("step".to_string(), Tensor::from(self.step))];
        for (i, name) in self.names.iter().enumerate() {
            state.push((
                format!("exp_avg.{name}"),
                self.tensors.exp_avg[i].shallow_clone(),
            ));
            state.push((
                format!("exp_avg_sq.{name}"),
                self.tensors.exp_avg_sq[i].shallow_clone(),
            ));
        }
        state
    }

    /// Restores a state written by [`state`](Self::state) (missing names are an error).
    pub fn load_state(&mut self, state: &[(String, Tensor)]) -> Result<(), tch::TchError> {
        let find = |name: &str| {
            state
                .iter()
                .find(|(n, _)| n == name)
                .map(|(_, t)| t)
                .ok_or_else(|| {
                    tch::TchError::TensorNameNotFound(name.to_string(), "adam state".into())
                })
        };
        self.step = find("step")?.int64_value(&[]);
        tch::no_grad(|| -> Result<(), tch::TchError> {
            for (i, name) in self.names.iter().enumerate() {
                let t = &mut self.tensors;
                t.exp_avg[i].f_copy_(find(&format!("exp_avg.{name}"))?)?;
                t.exp_avg_sq[i].f_copy_(find(&format!("exp_avg_sq.{name}"))?)?;
            }
            Ok(())
        })
    }
}

/// The scalars of one Adam step, the same for every parameter and every slice of one.
#[derive(Debug, Clone, Copy)]
pub struct AdamStep {
    /// lr · √(1 − β2ᵗ) / (1 − β1ᵗ).
    step_size: f64,
    /// ε · √(1 − β2ᵗ).
    eps: f64,
    beta1: f64,
    beta2: f64,
}

impl AdamStep {
    /// Spec 5.3 "Optimisers": torch's Adam update of `param` with moments `m`, `v`, in place,
    /// with the bias corrections folded into the step's scalars: in one pass where the tensors
    /// allow it ([`adam_in_one_pass`]), otherwise as libtorch ops with `denom` as scratch and
    /// `grad` consumed as scratch.
    fn apply(
        &self,
        param: &Tensor,
        m: &mut Tensor,
        v: &mut Tensor,
        denom: &mut Tensor,
        mut grad: Tensor,
    ) {
        // Autograd's gradients are contiguous in practice; a copy keeps the one pass otherwise.
        let contiguous = grad.contiguous();
        if self.apply_in_one_pass::<f32>(param, m, v, &contiguous)
            || self.apply_in_one_pass::<f64>(param, m, v, &contiguous)
        {
            return;
        }
        let _ = m.lerp_(&grad, 1.0 - self.beta1);
        let _ = grad.square_();
        let _ = v.lerp_(&grad, 1.0 - self.beta2);
        let _ = v.sqrt_out(denom);
        let _ = denom.g_add_scalar_(self.eps);
        let _ = denom.g_mul_scalar_(-1.0 / self.step_size);
        let _ = param.shallow_clone().addcdiv_(m, denom);
    }

    /// [`adam_in_one_pass`] on the tensors' memory when all four are contiguous CPU tensors of
    /// element type `T` with as many elements; false (nothing done) otherwise.
    fn apply_in_one_pass<T: Element + Float>(
        &self,
        param: &Tensor,
        m: &Tensor,
        v: &Tensor,
        grad: &Tensor,
    ) -> bool {
        let numel = param.numel();
        let fits = |t: &Tensor| {
            t.device() == Device::Cpu
                && t.kind() == T::KIND
                && t.is_contiguous()
                && t.numel() == numel
        };
        if numel == 0 || ![param, m, v, grad].into_iter().all(fits) {
            return false;
        }
        let (param, m, v, grad) = (
            param.data_ptr() as *mut T,
            m.data_ptr() as *mut T,
            v.data_ptr() as *mut T,
            grad.data_ptr() as *const T,
        );
        // SAFETY: the four tensors are contiguous CPU tensors of `numel` elements of type `T`, so
        // each pointer addresses `numel` initialised `T`s. The parameter and the two moments are
        // tensors of their own (the optimiser allocated the moments; a slice of them is a view of
        // the same members of each), so the three mutable slices do not overlap, and the gradient
        // is autograd's fresh output. Nothing else touches these elements during the step: a
        // parameter slice is stepped by the one thread that owns its members.
        let (param, m, v, grad) = unsafe {
            (
                std::slice::from_raw_parts_mut(param, numel),
                std::slice::from_raw_parts_mut(m, numel),
                std::slice::from_raw_parts_mut(v, numel),
                std::slice::from_raw_parts(grad, numel),
            )
        };
        adam_in_one_pass(param, m, v, grad, self);
        true
    }
}

/// Spec 5.3 "Optimisers": one Adam step of one parameter, elementwise in a single pass:
/// m ← m + (1 − β1)(g − m), v ← v + (1 − β2)(g² − v), p ← p − step_size · m / (√v + ε′), with
/// the bias corrections folded into `step_size` and ε′ (see [`Adam::begin_step`]).
pub fn adam_in_one_pass<T: Float>(
    param: &mut [T],
    m: &mut [T],
    v: &mut [T],
    grad: &[T],
    step: &AdamStep,
) {
    let cast = |x: f64| T::from(x).expect("an f64 scalar fits a float type");
    let (one_minus_beta1, one_minus_beta2) = (cast(1.0 - step.beta1), cast(1.0 - step.beta2));
    let (step_size, eps) = (cast(step.step_size), cast(step.eps));
    for (((p, m), v), &g) in param.iter_mut().zip(m).zip(v).zip(grad) {
        *m = *m + one_minus_beta1 * (g - *m);
        *v = *v + one_minus_beta2 * (g * g - *v);
        *p = *p - step_size * *m / (v.sqrt() + eps);
    }
}

/// Parameters and their Adam state, one entry per parameter in the optimiser's order: all of an
/// [`Adam`]'s, or a slice of them sharing their memory (see [`Adam::slice`]).
#[derive(Debug)]
pub struct AdamSlice {
    params: Vec<Tensor>,
    /// First and second moments.
    exp_avg: Vec<Tensor>,
    exp_avg_sq: Vec<Tensor>,
    /// Scratch for the denominator.
    scratch: Vec<Tensor>,
}

impl AdamSlice {
    /// The slice's part of step `step`, with the gradients of the sliced parameters (in
    /// [`Adam::params`] order, consumed as scratch).
    pub fn step(&mut self, step: AdamStep, grads: Vec<Tensor>) {
        tch::no_grad(|| {
            for (i, grad) in grads.into_iter().enumerate() {
                step.apply(
                    &self.params[i],
                    &mut self.exp_avg[i],
                    &mut self.exp_avg_sq[i],
                    &mut self.scratch[i],
                    grad,
                );
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Step 1 with lr 0.1, β1 0.9, β2 0.999, ε 1e-8, by hand: step_size = 0.1 · √0.001 / 0.1
    /// = 0.0316228, ε′ = 1e-8 · √0.001. From zero moments and g = 0.5: m = 0.05, v = 0.00025 and
    /// p moves by lr · √v / (√v + ε′) = 0.1 · (1 − 2e-8), to 0.900000002. From m = 0.2, v = 0.01
    /// and g = −1: m = 0.2 + 0.1 · (−1.2) = 0.08, v = 0.01 + 0.001 · (1 − 0.01) = 0.01099,
    /// p = 2 − 0.0316228 · 0.08 / 0.104833 = 1.975868.
    #[test]
    fn one_pass_step_by_hand() {
        let vs = nn::VarStore::new(Device::Cpu);
        let mut adam = Adam::new(&vs, 0.1, 0.9, 0.999, 1e-8);
        let step = adam.begin_step();
        let (mut p, mut m, mut v) = ([1.0f64, 2.0], [0.0, 0.2], [0.0, 0.01]);
        adam_in_one_pass(&mut p, &mut m, &mut v, &[0.5, -1.0], &step);
        let close = |got: f64, want: f64| (got - want).abs() < 1e-9;
        assert!(close(m[0], 0.05) && close(v[0], 0.00025), "{m:?} {v:?}");
        assert!(close(m[1], 0.08) && close(v[1], 0.01099), "{m:?} {v:?}");
        assert!(
            close(p[0], 0.900000002) && close(p[1], 1.975868121),
            "{p:?}"
        );
    }

    /// The one pass and the chain of libtorch ops take the same step: a CUDA-less stand-in for the
    /// op chain is a non-contiguous parameter, which the one pass refuses.
    #[test]
    fn one_pass_and_op_chain_agree() {
        let make = |contiguous: bool| {
            let base = Tensor::from_slice(&[0.3f32, -1.2, 2.5, 0.7, -0.4, 1.1]).view([2, 3]);
            if contiguous {
                base
            } else {
                base.tr().contiguous().tr()
            }
        };
        let (fast, chain) = (make(true), make(false));
        assert!(fast.is_contiguous() && !chain.is_contiguous());
        let grad = Tensor::from_slice(&[0.5f32, -0.25, 1.5, -2.0, 0.1, 0.0]).view([2, 3]);
        let vs = nn::VarStore::new(Device::Cpu);
        let mut adam = Adam::new(&vs, 1e-2, 0.9, 0.999, 1e-8);
        let moments = |p: &Tensor| (p.zeros_like(), p.zeros_like(), p.zeros_like());
        let (mut m1, mut v1, mut d1) = moments(&fast);
        let (mut m2, mut v2, mut d2) = moments(&chain);
        for _ in 0..3 {
            let step = adam.begin_step();
            step.apply(&fast, &mut m1, &mut v1, &mut d1, grad.copy());
            step.apply(&chain, &mut m2, &mut v2, &mut d2, grad.copy());
        }
        // The op chain wrote its scratch, the one pass did not.
        assert_eq!(d1.abs().sum(None).double_value(&[]), 0.0);
        assert!(d2.abs().sum(None).double_value(&[]) > 0.0);
        let diff = (&fast - &chain).abs().max().double_value(&[]);
        assert!(diff < 1e-6, "{diff}");
        assert!((&m1 - &m2).abs().max().double_value(&[]) < 1e-7);
    }
}
