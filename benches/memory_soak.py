#!/usr/bin/env python3
"""Memory soak: one `rfcl train` PointMaze run long enough to fill its replay buffer, the resident
memory (RSS) of every process sampled every 10 s. Once the online buffer is full nothing should
grow: each process's RSS after the fill should stay within 5 % of its value at the fill.

    benches/memory_soak.py [--capacity 100000] [--steps 300000] [--out runs/bench-soak]

Prints one CSV row per sample (time, learner env steps, RSS per process in MiB) to OUT/rss.csv and
a table per process (RSS at fill, largest after it, growth) for benches/RESULTS.md. Uses only the
standard library and the release binaries (`cargo build --release --workspace`).
"""
import argparse
import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RFCL = ROOT / "target" / "release" / "rfcl"


def rss_mib(pid):
    """Resident set size of `pid` in MiB, or None when it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def learner_env_steps(run_dir):
    """Env steps in the learner's last metrics row (0 before the first)."""
    try:
        lines = (run_dir / "metrics.csv").read_text().splitlines()
    except OSError:
        return 0
    if len(lines) < 2:
        return 0
    header = lines[0].split(",")
    row = lines[-1].split(",")
    if len(row) != len(header):
        row = lines[-2].split(",") if len(lines) > 2 else row
    try:
        return int(float(row[header.index("env_steps")]))
    except (ValueError, IndexError):
        return 0


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--capacity", type=int, default=100_000, help="sac.replay_buffer_capacity")
    p.add_argument("--steps", type=int, default=300_000, help="train.steps")
    p.add_argument("--every", type=float, default=10.0, help="seconds between samples")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-soak")
    args = p.parse_args()
    if args.steps <= args.capacity:
        sys.exit("--steps must exceed --capacity: the run has to fill the buffer and go on")
    args.out.mkdir(parents=True, exist_ok=True)
    demos = args.out / "demos.h5"
    if not demos.exists():
        subprocess.run([RFCL, "demos", "generate", "--env", "pointmaze", "-n", "5", "--out", demos],
                       check=True)
    run_dir = args.out / "run"
    subprocess.run(["rm", "-rf", run_dir], check=True)
    log = open(args.out / "train.log", "w")
    train = subprocess.Popen(
        [RFCL, "train", ROOT / "configs" / "pointmaze_test.yml",
         f"train.dataset_path={demos}", f"sac.replay_buffer_capacity={args.capacity}",
         f"train.steps={args.steps}", "service.stop_at_eval_success=null",
         "--run-dir", run_dir],
        stdout=log, stderr=subprocess.STDOUT)
    samples = []  # (t, env_steps, {name: rss})
    start = time.time()
    try:
        while train.poll() is None:
            time.sleep(args.every)
            try:
                children = json.loads((run_dir / "processes.json").read_text())["children"]
            except (OSError, ValueError, KeyError):
                continue
            rss = {c["name"]: rss_mib(c["pid"]) for c in children}
            rss["rfcl"] = rss_mib(train.pid)
            steps = learner_env_steps(run_dir)
            samples.append((time.time() - start, steps, rss))
            print(f"soak: {time.time() - start:6.0f} s  {steps:8d} env steps  " +
                  "  ".join(f"{n} {v:.0f}" for n, v in sorted(rss.items()) if v), flush=True)
    except KeyboardInterrupt:
        train.send_signal(signal.SIGINT)
        train.wait()
    names = sorted({n for _, _, r in samples for n in r})
    with open(args.out / "rss.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_s", "env_steps"] + [f"{n}_mib" for n in names])
        for t, steps, r in samples:
            w.writerow([f"{t:.0f}", steps] + [f"{r[n]:.1f}" if r.get(n) else "" for n in names])
    fill = next((i for i, (_, steps, _) in enumerate(samples) if steps >= args.capacity), None)
    if fill is None:
        sys.exit(f"the buffer never filled ({samples[-1][1] if samples else 0} env steps): "
                 f"see {args.out / 'train.log'}")
    print(f"\nfilled at {samples[fill][0]:.0f} s ({samples[fill][1]} env steps); "
          f"{len(samples) - fill - 1} samples after, to {samples[-1][1]} env steps\n")
    print("| process | RSS at fill (MiB) | largest after (MiB) | growth |")
    print("|---|---|---|---|")
    for n in names:
        at = samples[fill][2].get(n)
        after = [r[n] for _, _, r in samples[fill + 1:] if r.get(n)]
        if not at or not after:
            continue
        top = max(after)
        print(f"| {n} | {at:.0f} | {top:.0f} | {100 * (top - at) / at:+.1f} % |")
    return train.returncode or 0


if __name__ == "__main__":
    sys.exit(main())
