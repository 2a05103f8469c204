//! Member-parallel execution of SAC updates: on a CPU, the work of one update spread over threads
//! with single-threaded libtorch ops, where libtorch's own per-op threading leaves cores idle for
//! networks of RFCL's size (benches/RESULTS.md; docs/LEARNER.md "Threads").
//!
//! The maths are those of one batched computation on one thread (same losses, same gradients up
//! to float summation order, same RNG draws: [`Sac`](crate::Sac) draws noise and target members
//! before the work is spread); only the work is spread, two ways:
//! * a critic update splits the ensemble's members into contiguous shards ([`shard_ranges`]);
//!   each shard computes its members' loss and gradients and then steps the optimiser and the
//!   Polyak average for its own members ([`MemberThreads::critic_update`]);
//! * per-row work (the critic's regression target, the actor's loss and gradients) splits the
//!   minibatch's rows, one range per thread ([`MemberThreads::by_rows`]).
//!
//! The threads ([`run_on_threads`]: the calling one and helpers kept for the process) take jobs
//! from a shared queue until none is left. With one thread, the same jobs run on the calling
//! thread (one shard of all members, one range of all rows), which is also how CUDA runs them.
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

use rfcl_core::config::Backend;
use tch::{Device, Tensor};

use crate::adam::{Adam, AdamSlice, AdamStep};
use crate::batch::Batch;
use crate::fused;
use crate::nets::CriticEnsemble;
use crate::sac::{mean_squared_td_error, polyak_update, CriticStep};

/// Shards per member thread (see [`MemberThreads::per_thread`]). One: finer work, balanced by the
/// queue, was slower in whole runs on the 2-core machine, where the simulators share the cores
/// (benches/RESULTS.md, "Finer work per thread"): the smaller matrix products cost more than a
/// descheduled thread's share of the joins.
pub const SHARDS_PER_THREAD: usize = 1;

/// How an agent spreads its updates: on how many threads (1 = everything on the calling thread),
/// with the critic ensemble's members split into how many contiguous shards.
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

    /// One critic update with the members split over the threads: each shard computes its
    /// members' loss and gradients for regression target `target`, steps its slice of the
    /// optimiser (`opt`, step `step`) and then Polyak-averages its slice of the target critic
    /// (`polyak`: (target, online) pairs, every one member-stacked; spec 5.2 3.1), so the
    /// optimiser and Polyak steps run on every thread too. Shard s of E_s members takes its mean
    /// squared TD error times E_s/E: the shards' losses add up to the mean over all E members, and
    /// each member's gradient is the one of the whole loss.
    pub fn critic_update(
        &self,
        backend: Backend,
        critic: &CriticEnsemble,
        (opt, step): (&Adam, AdamStep),
        (polyak, tau): (&[(Tensor, Tensor)], f64),
        minibatch: &Batch,
        target: &Tensor,
    ) -> CriticStep {
        let members = critic.members();
        let jobs: Vec<CriticShardJob> = shard_ranges(members, self.shards)
            .into_iter()
            .map(|(start, len)| CriticShardJob {
                shard: critic.shard(start, len, true),
                backend,
                weight: len as f64 / members as f64,
                obs: minibatch.obs.shallow_clone(),
                action: minibatch.action.shallow_clone(),
                target: target.shallow_clone(),
                opt: opt.slice(start, len),
                step,
                polyak: polyak
                    .iter()
                    .map(|(t, o)| (t.narrow(0, start, len), o.narrow(0, start, len)))
                    .collect(),
                tau,
            })
            .collect();
        let parts = run_on_threads(jobs, self.threads, CriticShardJob::run);
        CriticStep {
            loss: sum(parts.iter().map(|p| &p.loss)),
            q: sum(parts.iter().map(|p| &p.q_sum)) / (members * minibatch.rows()) as f64,
        }
    }

    /// A per-row computation on `rows` rows, such as the critic's regression target or the
    /// actor's loss and gradients: the rows split into one contiguous range per thread,
    /// `job(start, len)` prepares each range's work (on the calling thread), the threads `run`
    /// them; the parts in row order. Not parallel: one job on all rows, run here.
    pub fn by_rows<J: Send, T: Send>(
        &self,
        rows: i64,
        job: impl Fn(i64, i64) -> J,
        run: fn(J) -> T,
    ) -> Vec<T> {
        if !self.is_parallel() {
            return vec![run(job(0, rows))];
        }
        let jobs = shard_ranges(rows, self.threads)
            .into_iter()
            .map(|(start, len)| job(start, len))
            .collect();
        run_on_threads(jobs, self.threads, run)
    }
}

/// The elementwise sum of same-shaped tensors (at least one): joins the threads' parts.
pub fn sum<'a>(tensors: impl Iterator<Item = &'a Tensor>) -> Tensor {
    Tensor::stack(&tensors.collect::<Vec<_>>(), 0).sum_dim_intlist(0, false, None)
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

/// Runs `work` on every job with `threads` threads, the calling one and `threads − 1` helpers from
/// [`helper_pool`], each taking the next job from a shared queue until none is left; results in
/// job order, whoever ran them. A panic in a job is re-raised.
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
    let helpers = threads.min(count).saturating_sub(1);
    if helpers == 0 {
        drain();
    } else {
        let drain = &drain;
        // The calling thread drains too and then waits (blocked, not spinning) for the helpers.
        helper_pool(helpers).in_place_scope(|scope| {
            for _ in 0..helpers {
                scope.spawn(move |_| drain());
            }
            drain();
        });
    }
    results
        .into_iter()
        .map(|r| r.into_inner().expect("result slot").expect("every job ran"))
        .collect()
}

/// `helpers` threads with single-threaded libtorch ops, started on first use and kept for the
/// process (one pool per size). Threads started per job, tens of times a second in a run, each
/// faulted a fresh stack in and set up libtorch's and MKL's per-thread state again, and MKL's
/// buffers were freed at every thread's exit.
fn helper_pool(helpers: usize) -> &'static rayon::ThreadPool {
    static POOLS: Mutex<BTreeMap<usize, &'static rayon::ThreadPool>> = Mutex::new(BTreeMap::new());
    let mut pools = POOLS.lock().unwrap_or_else(|e| e.into_inner());
    pools.entry(helpers).or_insert_with(|| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(helpers)
            .thread_name(|i| format!("learner-member-{}", i + 1))
            .start_handler(|_| tch::set_num_threads(1))
            .build()
            .unwrap_or_else(|e| panic!("could not start {helpers} member threads: {e}"));
        Box::leak(Box::new(pool))
    })
}

/// One shard's share of a critic update (see [`MemberThreads::critic_update`]).
struct CriticShardJob {
    shard: CriticEnsemble,
    backend: Backend,
    /// E_s / E.
    weight: f64,
    obs: Tensor,
    action: Tensor,
    target: Tensor,
    /// The shard's slice of the critic optimiser, and the step to take.
    opt: AdamSlice,
    step: AdamStep,
    /// The shard's slices of the (target, online) parameter pairs, and the Polyak rate.
    polyak: Vec<(Tensor, Tensor)>,
    tau: f64,
}

struct CriticShardPart {
    loss: Tensor,
    q_sum: Tensor,
}

impl CriticShardJob {
    fn run(mut self) -> CriticShardPart {
        let fused = match self.backend {
            Backend::Fused => fused::critic_loss_and_grads(
                &self.shard,
                &self.obs,
                &self.action,
                &self.target,
                self.weight,
            ),
            Backend::Libtorch => None,
        };
        let (part, grads) = match fused {
            Some(f) => (
                CriticShardPart {
                    loss: f.loss,
                    q_sum: f.q_sum,
                },
                f.grads,
            ),
            None => self.autograd(),
        };
        self.opt.step(self.step, grads);
        polyak_update(&self.polyak, self.tau);
        part
    }

    /// The shard's loss and its gradients by libtorch's autograd.
    fn autograd(&self) -> (CriticShardPart, Vec<Tensor>) {
        let shard = &self.shard;
        let q = shard.forward(&self.obs, &self.action);
        let loss = mean_squared_td_error(&q, &self.target) * self.weight;
        let params: Vec<Tensor> = shard
            .named_parameters()
            .into_iter()
            .map(|(_, p)| p)
            .collect();
        let grads = Tensor::run_backward(&[&loss], &params, false, false);
        let part = CriticShardPart {
            loss: loss.detach(),
            q_sum: q.detach().sum(None),
        };
        (part, grads)
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

    #[test]
    fn helper_threads_are_started_once_and_kept() {
        use std::sync::{Arc, Barrier};
        use std::thread::ThreadId;
        // Two jobs that wait for each other: each of the two threads runs exactly one.
        fn meet(barrier: Arc<Barrier>) -> (ThreadId, i32) {
            barrier.wait();
            (std::thread::current().id(), tch::get_num_threads())
        }
        let helper = || {
            let barrier = Arc::new(Barrier::new(2));
            let ran = run_on_threads(vec![barrier.clone(), barrier], 2, meet);
            let caller = std::thread::current().id();
            assert!(
                ran.iter().any(|(id, _)| *id == caller),
                "the caller works too"
            );
            *ran.iter()
                .find(|(id, _)| *id != caller)
                .expect("a helper ran the other job")
        };
        let (first, libtorch_threads) = helper();
        assert_eq!(
            libtorch_threads, 1,
            "helpers run single-threaded libtorch ops"
        );
        assert_eq!(helper().0, first, "the next call reuses the helper thread");
    }
}
