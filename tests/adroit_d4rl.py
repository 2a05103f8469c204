"""Writes a small Adroit Door file in D4RL's format (like door-human-v1.hdf5), for the Rust tests
of `rfcl demos convert` (tests/demos_suites.rs, tests/train_adroit.rs).

    python tests/adroit_d4rl.py OUT N_OPEN N_CLOSED STEPS

N_OPEN episodes start with the door already open (hinge at 1.5 rad, past the 1.35 success bar),
so that they succeed; N_CLOSED start from a seeded reset and do not. Each episode takes STEPS
smooth random actions. The layout is D4RL's (docs/SUITES.md "Adroit"): episodes concatenated, one
row per action, `timeouts` true on each episode's last row, the state before each action in
`infos/qpos`, `infos/qvel`, `infos/door_body_pos`.
"""
import sys
import warnings

import h5py
import numpy as np

from rfcl_sim import adapters

warnings.filterwarnings("ignore")


def main(out: str, n_open: int, n_closed: int, steps: int) -> None:
    env = adapters.make("adroit", "door")
    rng = np.random.default_rng(0)
    layout = env.state_layout()
    rows = {"observations": [], "actions": [], "timeouts": []}
    fields = {name: [] for name, _, _ in layout}
    try:
        for k in range(n_open + n_closed):
            obs = env.reset(k, {})
            if k < n_open:
                state = env.get_state()
                state[env._env.door_hinge_addrs] = 1.5  # qpos comes first in the state
                obs = env.set_state(state)
            action = np.zeros(env.action_dim)
            for t in range(steps):
                state, offset = env.get_state(), 0
                for name, _, n in layout:
                    fields[name].append(state[offset:offset + n])
                    offset += n
                action = np.clip(0.8 * action + 0.3 * rng.normal(size=env.action_dim), -1, 1)
                rows["observations"].append(obs)
                rows["actions"].append(action.astype(np.float32))
                rows["timeouts"].append(t == steps - 1)
                obs, _ = env.step(action)
    finally:
        env.close()
    n = len(rows["actions"])
    with h5py.File(out, "w") as f:
        for key, values in rows.items():
            f[key] = np.stack(values) if key != "timeouts" else np.asarray(values, dtype=bool)
        f["rewards"] = np.zeros(n, dtype=np.float32)
        f["terminals"] = np.zeros(n, dtype=bool)
        for name, values in fields.items():
            f[f"infos/{name}"] = np.stack(values)


if __name__ == "__main__":
    out, n_open, n_closed, steps = sys.argv[1], *map(int, sys.argv[2:5])
    main(out, n_open, n_closed, steps)
