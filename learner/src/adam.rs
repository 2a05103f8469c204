//! Adam (spec 5.3 "Optimisers": β1 0.9, β2 0.999, ε 1e-8, no clipping, no weight decay), in place.
//!
//! Not `tch::nn::Optimizer`: libtorch's C++ optimizer state (moments, step) is not reachable
//! through tch, and spec 4.1 needs it in checkpoints ("each model's state = params + optimizer
//! state + step"). The update is torch's single-tensor Adam, written in place into preallocated
//! buffers; gradients come from `torch::autograd::grad` (no `.grad` accumulation, no zeroing).
//!
//! Every parameter of a network lives in one contiguous buffer ([`flatten_variables`]), so a step is
//! seven tensor ops for the whole network instead of seven per parameter tensor: with the small
//! networks of a CPU run, op dispatch, not arithmetic, is most of an update's cost.
use tch::{nn, Kind, Tensor};

/// Re-homes every variable of `vs` into one contiguous 1-D buffer, in name order, and returns it:
/// each variable becomes a view of its slice (`set_data`, like `param.data = ...` in PyTorch), keeps
/// its values, its `requires_grad` and its identity (the layers holding it see the change), and an
/// in-place op on the buffer updates every variable at once. Call once per store, after the
/// variables are created and initialised.
pub fn flatten_variables(vs: &nn::VarStore) -> Tensor {
    let mut vars: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    let total: i64 = vars.iter().map(|(_, v)| v.numel() as i64).sum();
    let kind = vars.first().map_or(Kind::Float, |(_, v)| v.kind());
    let flat = Tensor::zeros([total], (kind, vs.device()));
    tch::no_grad(|| {
        let mut offset = 0;
        for (_, var) in vars.iter_mut() {
            let n = var.numel() as i64;
            let slice = flat.narrow(0, offset, n).view(var.size().as_slice());
            let _ = slice.shallow_clone().copy_(var);
            var.set_data(&slice);
            offset += n;
        }
    });
    flat
}

#[derive(Debug)]
pub struct Adam {
    /// (name, parameter), sorted by name: views into `flat`.
    params: Vec<(String, Tensor)>,
    /// Every parameter, back to back (see [`flatten_variables`]).
    flat: Tensor,
    exp_avg: Tensor,
    exp_avg_sq: Tensor,
    /// Scratch for the denominator.
    scratch: Tensor,
    step: i64,
    lr: f64,
    beta1: f64,
    beta2: f64,
    eps: f64,
}

impl Adam {
    /// Adam over every trainable variable of `vs`, which it flattens ([`flatten_variables`]).
    pub fn new(vs: &nn::VarStore, lr: f64, beta1: f64, beta2: f64, eps: f64) -> Self {
        let flat = flatten_variables(vs);
        let mut params: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
        params.sort_by(|a, b| a.0.cmp(&b.0));
        let zeros = || flat.zeros_like().detach();
        Self {
            exp_avg: zeros(),
            exp_avg_sq: zeros(),
            scratch: zeros(),
            flat,
            params,
            step: 0,
            lr,
            beta1,
            beta2,
            eps,
        }
    }

    /// The parameters, in the order [`step`](Self::step) expects their gradients.
    pub fn params(&self) -> Vec<&Tensor> {
        self.params.iter().map(|(_, p)| p).collect()
    }

    /// All parameters as one flat tensor (name order): in-place ops on it change the network.
    pub fn flat_params(&self) -> &Tensor {
        &self.flat
    }

    /// Gradients of `loss` w.r.t. the parameters only (autograd computes nothing for other
    /// leaves, e.g. a critic inside the actor loss), then one Adam step.
    pub fn minimize(&mut self, loss: &Tensor) {
        let grads = Tensor::run_backward(&[loss], &self.params(), false, false);
        self.step(grads);
    }

    /// One Adam step with the given gradients, one per parameter in [`params`](Self::params)
    /// order.
    pub fn step(&mut self, grads: Vec<Tensor>) {
        self.step += 1;
        let bias1 = 1.0 - self.beta1.powi(self.step as i32);
        let bias2_sqrt = (1.0 - self.beta2.powi(self.step as i32)).sqrt();
        // lr · m̂ / (√v̂ + ε) = m / ((√v + ε·√c2) · c1 / (lr · √c2))
        let step_size = self.lr * bias2_sqrt / bias1;
        let eps = self.eps * bias2_sqrt;
        tch::no_grad(|| {
            let flat: Vec<Tensor> = grads.iter().map(|g| g.reshape([-1])).collect();
            let mut grad = Tensor::cat(&flat, 0);
            let (m, v, denom) = (&mut self.exp_avg, &mut self.exp_avg_sq, &mut self.scratch);
            let _ = m.lerp_(&grad, 1.0 - self.beta1);
            let _ = grad.square_();
            let _ = v.lerp_(&grad, 1.0 - self.beta2);
            let _ = v.sqrt_out(denom);
            let _ = denom.g_add_scalar_(eps);
            let _ = denom.g_mul_scalar_(-1.0 / step_size);
            let _ = self.flat.addcdiv_(m, denom);
        });
    }

    /// Steps taken so far.
    pub fn step_count(&self) -> i64 {
        self.step
    }

    /// `buffer`'s slice that belongs to parameter `i`, shaped like it.
    fn slice_of(&self, buffer: &Tensor, i: usize) -> Tensor {
        let offset: i64 = self.params[..i].iter().map(|(_, p)| p.numel() as i64).sum();
        let p = &self.params[i].1;
        buffer
            .narrow(0, offset, p.numel() as i64)
            .view(p.size().as_slice())
    }

    /// The optimizer state as named tensors (`exp_avg.<param>`, `exp_avg_sq.<param>`, `step`),
    /// for checkpoints.
    pub fn state(&self) -> Vec<(String, Tensor)> {
        let mut state = vec![("step".to_string(), Tensor::from(self.step))];
        for (i, (name, _)) in self.params.iter().enumerate() {
            state.push((format!("exp_avg.{name}"), self.slice_of(&self.exp_avg, i)));
            state.push((
                format!("exp_avg_sq.{name}"),
                self.slice_of(&self.exp_avg_sq, i),
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
            for (i, (name, _)) in self.params.iter().enumerate() {
                self.slice_of(&self.exp_avg, i)
                    .f_copy_(find(&format!("exp_avg.{name}"))?)?;
                self.slice_of(&self.exp_avg_sq, i)
                    .f_copy_(find(&format!("exp_avg_sq.{name}"))?)?;
            }
            Ok(())
        })
    }
}
