//! rfcl-policy: the policy weights format shared by the learner and the actors, and the CPU
//! policy that acts with them (spec 5.1, 5.4, 5.7).
//!
//! The format is a contract between two services: the learner publishes a version after every
//! training iteration and exports the last one into the run directory; actors, eval actors and
//! `rfcl eval` load them. Both sides depend on this crate alone for it, so an actor builds without
//! the learner's training code, service and metrics, and neither side can change the format
//! without the other seeing it. `docs/POLICY.md` shows how to load an exported policy in PyTorch.
//!
//! * [`format`]: the safetensors layout and its validation ([`encode_vars`], [`load_vars`]),
//!   [`PolicyShape`], `policy.json` ([`PolicyDescription`]) and [`PolicyError`].
//! * [`mlp`]: the actor network itself and its initialisation.
//! * [`net`]: [`PolicyNet`], the actor on the CPU with loaded weights, for acting.
//!
//! # Wire format
//!
//! A policy version travels as the [safetensors](https://github.com/huggingface/safetensors)
//! bytes of the actor network alone (`PolicyWeights.safetensors`, and `policy.safetensors` in a
//! run directory). Tensor names are the actor var store's variable names, all `f32`, Flax layout
//! (`y = x · kernel + bias`, `kernel` `[fan_in, fan_out]`):
//!
//! | name                               | shape                | role                         |
//! |------------------------------------|----------------------|------------------------------|
//! | `trunk{i}.kernel`, `trunk{i}.bias` | `[in, H_i]`, `[H_i]` | hidden layer i, then ReLU    |
//! | `mean.kernel`, `mean.bias`         | `[H, A]`, `[A]`      | μ, the pre-tanh mean         |
//! | `log_std.kernel`, `log_std.bias`   | `[H, A]`, `[A]`      | h, the raw log-std head      |
//!
//! log σ = min + ½(max − min)(tanh(h) + 1) with the run's `network.log_std_min/max`. A training
//! actor samples a = tanh(μ + σ·ε), ε ~ N(0, I); an eval actor takes tanh(μ) (spec 5.7). Actions
//! are in agent units, in (−1, 1); with `train.data_action_scale` the env action is a / s
//! clipped to [−1, 1] (spec 6.4), with the s that [`PolicyDescription::action_scale`] records for
//! exported policies and `RunInfo.action_scale` gives actors.
//!
//! The safetensors header metadata holds one entry, `format` = [`FORMAT`] (one entry keeps the
//! bytes deterministic: equal weights give equal bytes); the dims are the shapes of
//! `trunk0.kernel` (`[obs_dim, H_0]`) and `mean.bias` (`[action_dim]`).
#![forbid(unsafe_code)]

mod format;
pub mod mlp;
mod net;

pub use format::{
    encode_vars, load_vars, tensor_names, PolicyDescription, PolicyError, PolicyShape, FORMAT,
};
pub use net::PolicyNet;
