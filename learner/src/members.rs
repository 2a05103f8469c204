//! Member-parallel execution of the critic ensemble: the members of a critic or actor update
//! split over threads, on a CPU, when libtorch's own per-op threading leaves cores idle for
//! networks of RFCL's size (benches/RESULTS.md; docs/LEARNER.md "Threads").
//!
//! The maths are those of the single batched computation in [`crate::sac`] (same losses, same
//! gradients up to float summation order, same RNG draws: [`Sac`](crate::Sac) draws noise and
//! target members before choosing how to run an update); only the work is spread. This module
//! holds the how: which members go to which shard ([`shard_ranges`]), the threads that take the
//! shards ([`run_on_threads`]), and how the shards' parts are joined back into the update's loss
//! and gradients. CUDA ignores it (one batched computation per update).
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

use tch::{Device, Tensor};

use crate::batch::Batch;
use crate::nets::{CriticEnsemble, PolicySample};
use crate::sac::{mean_squared_td_error, policy_loss, CriticStep};

/// Shards per member thread (see [`MemberThreads::per_thread`]). One: on the 2-core machine with a
/// MetaWorld run's actors beside the learner, two shards per thread (finer work, balanced by the
/// queue) were no faster (54-62 critic updates/s; one shard per thread 54-70 in the same run).
pub const SHARDS_PER_THREAD: usize = 1;

/// How an agent runs its critic ensemble's members: on how many threads (1 = one batched
/// computation on the calling thread), split into how many contiguous shards.
///
/// With more than one thread, every critic and actor update splits the members into shards, which
/// the threads (each with single-threaded libtorch ops) take from a shared queue until none is
/// left; then their gradients are joined.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MemberThreads {
    threads: usize,
    shards: usize,
}

impl MemberThreads {
    /// Everything on the calling thread: the batched computation.
    pub const SERIAL: Self = Self {
        threads: 1,
        shards: 1,
    };

    /// `threads` threads with [`SHARDS_PER_THREAD`] shards each.
    pub fn per_thread(threads: usize, members: usize, device: Device) -> Self {
        Self::new(
            threads,
            threads.saturating_mul(SHARDS_PER_THREAD),
            members,
            device,
        )
    }

    /// `threads` clamped to 1..=members (1 off the CPU), `shards` to threads..=members.
    pub fn new(threads: usize, shards: usize, members: usize, device: Device) -> Self {
        let threads = match device {
            Device::Cpu => threads.clamp(1, members),
            _ => 1,
        };
        Self {
            threads,
            shards: shards.clamp(threads, members),
        }
    }

    pub fn threads(&self) -> usize {
        self.threads
    }

    pub fn shards(&self) -> usize {
        self.shards
    }

    /// Whether updates run on several threads (otherwise: the batched computation).
    pub fn is_parallel(&self) -> bool {
        self.threads > 1
    }

    /// The critic loss's value and its gradients (in the critic optimiser's parameter order) for
    /// regression target `target`, with the members split over the threads. Shard s of E_s
    /// members returns its mean squared TD error times E_s/E: the shards' losses then add up to
    /// the mean over all E members, and each member's gradient is the one of the whole loss.
    pub fn critic_gradients(
        &self,
        critic: &CriticEnsemble,
        minibatch: &Batch,
        target: &Tensor,
    ) -> (CriticStep, Vec<Tensor>) {
        let members = critic.members();
        let jobs: Vec<CriticShardJob> = shard_ranges(members, self.shards)
            .into_iter()
            .map(|(start, len)| CriticShardJob {
                shard: critic.shard(start, len, true),
                weight: len as f64 / members as f64,
                obs: minibatch.obs.shallow_clone(),
                action: minibatch.action.shallow_clone(),
                target: target.shallow_clone(),
            })
            .collect();
        let parts = run_on_threads(jobs, self.threads, CriticShardJob::run);
        let loss = Tensor::stack(&parts.iter().map(|p| &p.loss).collect::<Vec<_>>(), 0).sum(None);
        let q_sum = Tensor::stack(&parts.iter().map(|p| &p.q_sum).collect::<Vec<_>>(), 0).sum(None);
        let params = parts[0].grads.len();
        let grads = (0..params)
            .map(|i| Tensor::cat(&parts.iter().map(|p| &p.grads[i]).collect::<Vec<_>>(), 0))
            .collect();
        let q = q_sum / (members * minibatch.rows()) as f64;
        (CriticStep { loss, q }, grads)
    }

    /// Spec 5.3 "Actor" for the policy sample `pi` at `obs`, with the critic members split over
    /// the threads: (the loss's value, a surrogate with the loss's gradient for the actor).
    /// Each shard returns Σ_k Q_k(s, a) over its members and its gradient with respect to the
    /// action; with g = ∂ mean_k Q_k / ∂a, the surrogate replaces mean_k Q_k(s, a) by a·g, whose
    /// gradient through a = tanh(u(θ)) is the same.
    pub fn actor_loss(
        &self,
        critic: &CriticEnsemble,
        alpha: &Tensor,
        obs: &Tensor,
        pi: &PolicySample,
    ) -> (Tensor, Tensor) {
        let members = critic.members();
        let jobs: Vec<ActorShardJob> = shard_ranges(members, self.shards)
            .into_iter()
            .map(|(start, len)| ActorShardJob {
                shard: critic.shard(start, len, false),
                obs: obs.shallow_clone(),
                action: pi.action.detach().set_requires_grad(true),
            })
            .collect();
        let parts = run_on_threads(jobs, self.threads, ActorShardJob::run);
        let sum = |ts: Vec<&Tensor>| Tensor::stack(&ts, 0).sum_dim_intlist(0, false, None);
        let q_mean = sum(parts.iter().map(|p| &p.q_sum).collect()) / members as f64;
        let grad_mean = sum(parts.iter().map(|p| &p.action_grad).collect()) / members as f64;
        let value = policy_loss(alpha, &pi.log_prob.detach(), &q_mean.unsqueeze(0));
        let linearised_q = (&pi.action * grad_mean).sum_dim_intlist(-1, false, None);
        let surrogate = policy_loss(alpha, &pi.log_prob, &linearised_q.unsqueeze(0));
        (value, surrogate)
    }
}

/// `shards` contiguous (start, len) member ranges covering 0..members, sizes differing by at most
/// one (the first ones get the extra members).
pub fn shard_ranges(members: i64, shards: usize) -> Vec<(i64, i64)> {
    let shards = (shards as i64).clamp(1, members.max(1));
    let (base, extra) = (members / shards, members % shards);
    let mut start = 0;
    (0..shards)
        .map(|s| {
            let len = base + i64::from(s < extra);
            let range = (start, len);
            start += len;
            range
        })
        .collect()
}

/// Runs `work` on every job with `threads` threads, the calling one and `threads − 1` scoped
/// threads with single-threaded libtorch ops, each taking the next job from a shared queue until
/// none is left; results in job order, whoever ran them. A panic in a job is re-raised.
fn run_on_threads<J: Send, T: Send>(jobs: Vec<J>, threads: usize, work: fn(J) -> T) -> Vec<T> {
    let count = jobs.len();
    let queue: Vec<Mutex<Option<J>>> = jobs.into_iter().map(|j| Mutex::new(Some(j))).collect();
    let results: Vec<Mutex<Option<T>>> = (0..count).map(|_| Mutex::new(None)).collect();
    let next = AtomicUsize::new(0);
    let drain = || loop {
        let i = next.fetch_add(1, Ordering::Relaxed);
        if i >= count {
            break;
        }
        let job = queue[i]
            .lock()
            .expect("job slot")
            .take()
            .expect("each job taken once");
        *results[i].lock().expect("result slot") = Some(work(job));
    };
    std::thread::scope(|scope| {
        let helpers: Vec<_> = (1..threads.min(count))
            .map(|_| {
                scope.spawn(|| {
                    tch::set_num_threads(1);
                    drain()
                })
            })
            .collect();
        drain();
        for helper in helpers {
            helper
                .join()
                .unwrap_or_else(|e| std::panic::resume_unwind(e));
        }
    });
    results
        .into_iter()
        .map(|r| r.into_inner().expect("result slot").expect("every job ran"))
        .collect()
}

/// One shard's share of a critic update (see [`MemberThreads::critic_gradients`]).
struct CriticShardJob {
    shard: CriticEnsemble,
    /// E_s / E.
    weight: f64,
    obs: Tensor,
    action: Tensor,
    target: Tensor,
}

struct CriticShardPart {
    loss: Tensor,
    q_sum: Tensor,
    grads: Vec<Tensor>,
}

impl CriticShardJob {
    fn run(self) -> CriticShardPart {
        let q = self.shard.forward(&self.obs, &self.action);
        let loss = mean_squared_td_error(&q, &self.target) * self.weight;
        let params: Vec<Tensor> = self
            .shard
            .named_parameters()
            .into_iter()
            .map(|(_, p)| p)
            .collect();
        let grads = Tensor::run_backward(&[&loss], &params, false, false);
        CriticShardPart {
            loss: loss.detach(),
            q_sum: q.detach().sum(None),
            grads,
        }
    }
}

/// One shard's share of an actor update (see [`MemberThreads::actor_loss`]).
struct ActorShardJob {
    /// Parameters without gradients: only ∂Q/∂a is taken.
    shard: CriticEnsemble,
    obs: Tensor,
    /// A leaf copy of the policy's action, requiring gradients.
    action: Tensor,
}

struct ActorShardPart {
    /// Σ_k Q_k(s, a) over the shard's members, `[B]`.
    q_sum: Tensor,
    /// ∂ Σ_k Σ_b Q_k(s_b, a_b) / ∂a, `[B, A]`.
    action_grad: Tensor,
}

impl ActorShardJob {
    fn run(self) -> ActorShardPart {
        let q_sum = self
            .shard
            .forward(&self.obs, &self.action)
            .sum_dim_intlist(0, false, None);
        let mut grads = Tensor::run_backward(&[&q_sum.sum(None)], &[&self.action], false, false);
        ActorShardPart {
            q_sum: q_sum.detach(),
            action_grad: grads.pop().expect("one input, one gradient"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shard_ranges_split_members_evenly_and_contiguously() {
        assert_eq!(shard_ranges(10, 1), vec![(0, 10)]);
        assert_eq!(shard_ranges(10, 2), vec![(0, 5), (5, 5)]);
        assert_eq!(shard_ranges(10, 3), vec![(0, 4), (4, 3), (7, 3)]);
        assert_eq!(shard_ranges(2, 5), vec![(0, 1), (1, 1)]);
        assert_eq!(shard_ranges(4, 0), vec![(0, 4)]);
    }

    #[test]
    fn threads_and_shards_are_clamped_to_the_members() {
        let cpu = MemberThreads::per_thread(4, 10, Device::Cpu);
        assert_eq!((cpu.threads(), cpu.shards()), (4, 4 * SHARDS_PER_THREAD));
        let few = MemberThreads::new(8, 3, 2, Device::Cpu);
        assert_eq!((few.threads(), few.shards()), (2, 2));
        let none = MemberThreads::per_thread(0, 10, Device::Cpu);
        assert_eq!(none, MemberThreads::SERIAL);
        assert!(!none.is_parallel());
        let cuda = MemberThreads::per_thread(4, 10, Device::Cuda(0));
        assert_eq!(cuda.threads(), 1);
        assert!(!cuda.is_parallel());
    }
}
