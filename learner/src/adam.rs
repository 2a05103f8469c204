//! Adam (spec 5.3 "Optimisers": β1 0.9, β2 0.999, ε 1e-8, no clipping, no weight decay), in place.
//!
//! Not `tch::nn::Optimizer`: libtorch's C++ optimizer state (moments, step) is not reachable
//! through tch, and spec 4.1 needs it in checkpoints ("each model's state = params + optimizer
//! state + step"). The update is torch's single-tensor Adam, written in place into preallocated
//! buffers; gradients come from `torch::autograd::grad` (no `.grad` accumulation, no zeroing).
use tch::{nn, Tensor};

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
    /// with the bias corrections folded into the step's scalars; `denom` is scratch and `grad`
    /// is consumed as scratch.
    fn apply(
        &self,
        param: &Tensor,
        m: &mut Tensor,
        v: &mut Tensor,
        denom: &mut Tensor,
        mut grad: Tensor,
    ) {
        let _ = m.lerp_(&grad, 1.0 - self.beta1);
        let _ = grad.square_();
        let _ = v.lerp_(&grad, 1.0 - self.beta2);
        let _ = v.sqrt_out(denom);
        let _ = denom.g_add_scalar_(self.eps);
        let _ = denom.g_mul_scalar_(-1.0 / self.step_size);
        let _ = param.shallow_clone().addcdiv_(m, denom);
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
