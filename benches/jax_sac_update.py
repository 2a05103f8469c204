#!/usr/bin/env python
"""The SAC update of `cargo bench -p rfcl-learner --bench sac_update`, in JAX/Flax, jitted.

The yardstick: the Rust learner should run at least 1.5x the updates/s of this
implementation of the same update on the same machine, measured side by side
(benches/compare_sac.sh runs both). It implements exactly what learner/src/sac.rs does per
training iteration (spec 5.2, 5.3), with the reference implementation's JAX idioms:

* actor: 3 x [Dense 256, ReLU], heads mu and h, log std = -5 + 3.5 (tanh h + 1), tanh-squashed
  Gaussian, log pi from the pre-tanh sample;
* critic ensemble: 10 Flax critics (3 x [Dense 256, LayerNorm eps 1e-6, ReLU], Dense 1),
  parameters stacked and applied with jax.vmap (the reference's vmapped ensemble);
* critic update: a' ~ pi(s') from the current actor, 2 target members drawn without replacement
  from the 10 (only those 2 are computed), y = r + gamma mask min_k Qbar_k(s', a'), loss = mean over
  members and rows of (Q_k(s, a) - y)^2, Adam, then the Polyak step (tau 0.005);
* after every F critic updates: an actor update on the round's last minibatch (mean over the 10
  critics, alpha constant) and a temperature update (target entropy -A/2); Adam 3e-4 everywhere.

One iteration (G critic updates, G/F actor + temperature updates) is one jitted call (lax.scan
over the rounds and the minibatches), timed after a warm-up call that compiles it, with the batch
already on the device, as the Rust bench times `Sac::train_iteration` on a prepared batch.
Prints JSON shaped like the Rust bench's report.

Threads: `--threads N` restricts the process to N cores (sched_setaffinity) before JAX starts:
XLA's CPU thread pool sizes itself from the schedulable CPUs.
"""
import argparse
import json
import os
import platform
import sys
import time


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--obs-dim", type=int, default=42)
    p.add_argument("--action-dim", type=int, default=8)
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--hidden", default="256,256,256")
    p.add_argument("--critic-ensemble", type=int, default=10)
    p.add_argument("--num-min-qs", type=int, default=2)
    p.add_argument("--schedules", default="80/20,16/1", help="G/F,...")
    p.add_argument("--threads", type=int, default=None, help="cores to use (default: all)")
    p.add_argument("--windows", type=int, default=3)
    p.add_argument("--window-seconds", type=float, default=5.0)
    p.add_argument("--seed", type=int, default=0)
    return p.parse_args()


ARGS = parse_args()
if ARGS.threads is not None:
    cpus = sorted(os.sched_getaffinity(0))
    if ARGS.threads < 1 or ARGS.threads > len(cpus):
        sys.exit(f"--threads must be in 1..={len(cpus)}, got {ARGS.threads}")
    os.sched_setaffinity(0, cpus[: ARGS.threads])

import jax  # noqa: E402  (after the affinity: XLA reads it at start)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402
from flax import linen as nn  # noqa: E402

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0
DISCOUNT, TAU, LR = 0.99, 0.005, 3e-4
hidden_init = nn.initializers.orthogonal(np.sqrt(2.0))


class Actor(nn.Module):
    hidden: tuple
    action_dim: int

    @nn.compact
    def __call__(self, obs):
        x = obs
        for width in self.hidden:
            x = nn.relu(nn.Dense(width, kernel_init=hidden_init)(x))
        head = nn.initializers.orthogonal(1.0)
        mu = nn.Dense(self.action_dim, kernel_init=head)(x)
        h = nn.Dense(self.action_dim, kernel_init=head)(x)
        log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (jnp.tanh(h) + 1.0)
        return mu, log_std


class Critic(nn.Module):
    hidden: tuple

    @nn.compact
    def __call__(self, obs, action):
        x = jnp.concatenate([obs, action], -1)
        for width in self.hidden:
            x = nn.Dense(width, kernel_init=hidden_init)(x)
            x = nn.relu(nn.LayerNorm(epsilon=1e-6)(x))
        return nn.Dense(1)(x)[..., 0]


def sample(actor, params, obs, key):
    """a = tanh(u), u ~ N(mu, sigma); log pi(a) from u (spec 5.1)."""
    mu, log_std = actor.apply(params, obs)
    eps = jax.random.normal(key, mu.shape)
    u = mu + jnp.exp(log_std) * eps
    log_normal = -0.5 * eps**2 - log_std - 0.5 * np.log(2 * np.pi)
    correction = 2.0 * (np.log(2.0) - u - jax.nn.softplus(-2.0 * u))
    return jnp.tanh(u), (log_normal - correction).sum(-1)


def build(args, g, f):
    hidden = tuple(int(w) for w in args.hidden.split(","))
    obs_dim, act_dim, b = args.obs_dim, args.action_dim, args.batch_size
    e, k_min = args.critic_ensemble, args.num_min_qs
    actor, critic = Actor(hidden, act_dim), Critic(hidden)
    target_entropy = -act_dim / 2.0

    def ensemble(params, obs, action):
        return jax.vmap(lambda p: critic.apply(p, obs, action))(params)  # [E, B]

    key = jax.random.PRNGKey(args.seed)
    ka, kc, key = jax.random.split(key, 3)
    o, a = jnp.zeros((1, obs_dim)), jnp.zeros((1, act_dim))
    actor_params = actor.init(ka, o)
    critic_params = jax.vmap(critic.init, in_axes=(0, None, None))(jax.random.split(kc, e), o, a)
    log_alpha = jnp.zeros(())
    opt = optax.adam(LR, b1=0.9, b2=0.999, eps=1e-8)
    state = dict(
        actor=actor_params,
        critic=critic_params,
        target=jax.tree_util.tree_map(jnp.copy, critic_params),  # own buffers (donated)
        log_alpha=log_alpha,
        actor_opt=opt.init(actor_params),
        critic_opt=opt.init(critic_params),
        temp_opt=opt.init(log_alpha),
        key=key,
    )

    def critic_update(state, mb):
        key, k_pi, k_members = jax.random.split(state["key"], 3)
        next_a, _ = sample(actor, state["actor"], mb["next_obs"], k_pi)
        members = jax.random.choice(k_members, e, (k_min,), replace=False)
        drawn = jax.tree_util.tree_map(lambda p: p[members], state["target"])
        next_v = ensemble(drawn, mb["next_obs"], next_a).min(0)
        y = jax.lax.stop_gradient(mb["reward"] + DISCOUNT * mb["mask"] * next_v)

        def loss_fn(params):
            q = ensemble(params, mb["obs"], mb["action"])
            return ((q - y) ** 2).mean(), q.mean()

        (loss, q), grads = jax.value_and_grad(loss_fn, has_aux=True)(state["critic"])
        updates, critic_opt = opt.update(grads, state["critic_opt"], state["critic"])
        critic_params = optax.apply_updates(state["critic"], updates)
        target = optax.incremental_update(critic_params, state["target"], TAU)
        state = dict(state, critic=critic_params, target=target, critic_opt=critic_opt, key=key)
        return state, (loss, q)

    def actor_and_temp_update(state, obs):
        key, k_pi = jax.random.split(state["key"])
        alpha = jnp.exp(state["log_alpha"])

        def loss_fn(params):
            a, log_prob = sample(actor, params, obs, k_pi)
            q = ensemble(state["critic"], obs, a).mean(0)
            return (alpha * log_prob - q).mean(), -log_prob.mean()

        (actor_loss, entropy), grads = jax.value_and_grad(loss_fn, has_aux=True)(state["actor"])
        updates, actor_opt = opt.update(grads, state["actor_opt"], state["actor"])
        actor_params = optax.apply_updates(state["actor"], updates)

        def temp_loss_fn(log_alpha):
            return jnp.exp(log_alpha) * (jax.lax.stop_gradient(entropy) - target_entropy)

        temp_loss, grad = jax.value_and_grad(temp_loss_fn)(state["log_alpha"])
        updates, temp_opt = opt.update(grad, state["temp_opt"], state["log_alpha"])
        log_alpha = optax.apply_updates(state["log_alpha"], updates)
        state = dict(
            state,
            actor=actor_params,
            actor_opt=actor_opt,
            log_alpha=log_alpha,
            temp_opt=temp_opt,
            key=key,
        )
        return state, (actor_loss, entropy, alpha, temp_loss)

    def iteration(state, batch):
        """G critic updates in G/F rounds of F, each round ending with an actor and a
        temperature update on its last minibatch (spec 5.2). `batch` leaves are [G/F, F, B, ...]."""

        def round_(state, rb):
            state, (critic_loss, q) = jax.lax.scan(critic_update, state, rb)
            last_obs = rb["obs"][-1]
            state, actor_metrics = actor_and_temp_update(state, last_obs)
            return state, (critic_loss.mean(), q.mean()) + actor_metrics

        state, metrics = jax.lax.scan(round_, state, batch)
        return state, jax.tree_util.tree_map(jnp.mean, metrics)

    rng = np.random.default_rng(args.seed)

    def random_batch():
        rows = (g // f, f, b)
        u = lambda *s: rng.uniform(-1.0, 1.0, rows + s).astype(np.float32)  # noqa: E731
        host = dict(
            obs=u(obs_dim),
            action=u(act_dim),
            reward=u(),
            mask=np.ones(rows, np.float32),
            next_obs=u(obs_dim),
        )
        return jax.device_put(host)

    return state, jax.jit(iteration, donate_argnums=0), random_batch


def flops(args, hidden):
    """Matmul FLOPs per critic / actor update, the formula of learner/src/bench.rs."""
    b, obs, act = args.batch_size, args.obs_dim, args.action_dim
    e, k = args.critic_ensemble, args.num_min_qs

    def macs(dims):
        return sum(x * y for x, y in zip(dims, dims[1:]))

    actor_dims = [obs] + hidden
    actor_fwd = macs(actor_dims) + actor_dims[-1] * 2 * act
    actor_first = actor_dims[0] * actor_dims[1]
    critic_dims = [obs + act] + hidden + [1]
    critic_fwd = macs(critic_dims)
    critic_first = critic_dims[0] * critic_dims[1]
    critic = 2 * b * (actor_fwd + k * critic_fwd + e * (3 * critic_fwd - critic_first))
    actor_u = 2 * b * (actor_fwd + e * 2 * critic_fwd + 2 * actor_fwd - actor_first)
    return float(critic), float(actor_u)


def main(args):
    hidden = [int(w) for w in args.hidden.split(",")]
    schedules = [tuple(int(x) for x in s.split("/")) for s in args.schedules.split(",")]
    critic_flop, actor_flop = flops(args, hidden)
    results = []
    for g, f in schedules:
        if g % f:
            sys.exit(f"schedule {g}/{f}: G must be a multiple of F")
        state, iteration, random_batch = build(args, g, f)
        start = time.perf_counter()
        state, metrics = iteration(state, random_batch())
        jax.block_until_ready(metrics)
        compile_s = time.perf_counter() - start
        flop_per_update = critic_flop + actor_flop / f
        windows = []
        best = None
        for _ in range(max(1, args.windows)):
            iterations, busy = 0, 0.0
            while busy < args.window_seconds:
                batch = random_batch()
                jax.block_until_ready(batch)
                t0 = time.perf_counter()
                state, metrics = iteration(state, batch)
                jax.block_until_ready(metrics)
                busy += time.perf_counter() - t0
                iterations += 1
            critic_updates = iterations * g
            window = dict(
                schedule=f"G{g}/F{f}",
                grad_updates_per_step=g,
                actor_update_freq=f,
                iterations=iterations,
                seconds=busy,
                updates_per_s=critic_updates / busy,
                critic_updates_per_s=critic_updates / busy,
                actor_updates_per_s=iterations * (g // f) / busy,
                flop_per_update=flop_per_update,
                flop_per_critic_update=critic_flop,
                flop_per_actor_update=actor_flop,
                gflop_per_s=critic_updates * flop_per_update / busy / 1e9,
                compile_seconds=compile_s,
            )
            windows.append(window["updates_per_s"])
            if best is None or window["updates_per_s"] > best["updates_per_s"]:
                best = window
        best["window_updates_per_s"] = windows
        finite = all(bool(np.isfinite(np.asarray(m))) for m in metrics)
        best["metrics_finite"] = finite
        results.append(best)
    report = dict(
        config=dict(
            obs_dim=args.obs_dim,
            action_dim=args.action_dim,
            batch_size=args.batch_size,
            hidden=hidden,
            critic_ensemble=args.critic_ensemble,
            target_pool=args.critic_ensemble,
            num_min_qs=args.num_min_qs,
            schedules=schedules,
            matmul_precision="fp32",
            threads=len(os.sched_getaffinity(0)),
            windows=args.windows,
            window_seconds=args.window_seconds,
            seed=args.seed,
        ),
        device=f"jax {jax.__version__} on {jax.devices()[0].platform}, "
        f"{len(os.sched_getaffinity(0))} cores, python {platform.python_version()}",
        results=results,
    )
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main(ARGS)
