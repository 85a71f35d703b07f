"""The batched core against another checkout of marlmerge, side by side, printed as JSON.

Each measurement is a fresh process that imports marlmerge from one source tree, builds a core
of B worlds at a mainline flow, and drives it with random ego commands for `--calls` calls of
`rollout` (finished egos replaced at once; arrivals drawn as the calls need them), timed by the
wall clock after `--warmup` calls. Both trees get the same seeds and commands, so they do the
same work: the measurement also hashes every observation the calls return, and `identical` says
whether the two trees' simulations agreed bit for bit. (Fresh processes, because two trees
imported into one process share Numba's compiled kernels: tried, both ran at the speed of the
tree imported first.) The trees take turns for `--rounds` rounds (so that the shared host's load
drifts the same for both); medians and the ratio (this tree over the other) are reported per
configuration, and with them the ratio within each round (`ratio_per_round`, the two trees
measured one right after the other) and its median (`ratio_paired_median`), which a host whose
speed drifts between rounds moves less. `--threads N` runs the measurements with N kernel
threads (`NUMBA_NUM_THREADS`; default: as the machine has).

    git worktree add ../marlmerge-before <commit>
    python benchmarks/bench_core_against.py --against ../marlmerge-before
    python benchmarks/bench_core_against.py --against ../marlmerge-before --batches 1024 --flows ''
    python benchmarks/bench_core_against.py --against ../marlmerge-before --threads 1 --rounds 7

The default window (20 warm-up calls, 300 timed: the first 128 s of simulated time) runs mostly
on the arrivals a core draws at its start. Later in a run each call also draws ahead for the
worlds that need it (`marlmerge.sim.draws`): `--warmup 400` times that steady state
([speed](../docs/architecture.md#speed)).

The other tree's kernels compile on its first measurement (cached on disk afterwards): run
once with `--rounds 1 --calls 5` to warm both caches first when timing matters.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent.parent


def worker(tree: str, batch: int, flow: float, calls: int, warmup: int) -> dict:
    """One measurement in this process, with marlmerge imported from `tree`."""
    sys.path.insert(0, tree)
    import numpy as np

    import marlmerge
    from marlmerge.config import ScenarioConfig
    from marlmerge.sim import OUTCOME_NONE, TrafficCore

    if not str(Path(marlmerge.__file__).resolve()).startswith(str(Path(tree).resolve())):
        raise SystemExit(f"marlmerge was imported from {marlmerge.__file__}, not from {tree}")
    cfg = ScenarioConfig().replace(**{"traffic.flow_vph_per_lane": flow})
    core = TrafficCore(cfg, batch_size=batch, seed=0)
    rng = np.random.default_rng(0)
    lo, hi = cfg.ego.accel_bounds_mps2
    digest = hashlib.sha256()

    def drive(n: int) -> None:
        for _ in range(n):
            out = core.rollout(rng.uniform(lo, hi, size=batch))
            digest.update(out.ego_obs.tobytes())
            done = out.ego_outcome != OUTCOME_NONE
            if done.any():
                core.next_ego(done)

    drive(warmup)
    st = core.state
    v0, s0 = int(st.vehicle_steps.sum()), int(st.steps.sum())
    t0 = time.perf_counter()
    drive(calls)
    wall = time.perf_counter() - t0
    vs, ss = int(st.vehicle_steps.sum()) - v0, int(st.steps.sum()) - s0
    return {
        "vehicle_steps_per_s": vs / wall,
        "ns_per_world_step": wall / max(ss, 1) * 1e9,
        "vehicles_per_world": vs / max(ss, 1),
        "digest": digest.hexdigest()[:16],
    }


def measure(
    tree: Path, batch: int, flow: float, calls: int, warmup: int, threads: int | None = None
) -> dict:
    args = [sys.executable, __file__, "--worker", str(tree), str(batch), str(flow)]
    args += [str(calls), str(warmup)]
    env = None if threads is None else dict(os.environ, NUMBA_NUM_THREADS=str(threads))
    done = subprocess.run(args, capture_output=True, text=True, check=False, env=env)
    if done.returncode != 0:
        raise SystemExit(f"measurement in {tree} failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        tree, batch, flow, calls, warmup = sys.argv[2:7]
        row = worker(tree, int(batch), float(flow), int(calls), int(warmup))
        print(json.dumps(row))
        return
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--against", required=True, help="another checkout's root folder")
    p.add_argument("--batches", default="256,1024,4096", help="B at the default flow")
    p.add_argument("--flows", default="400,2000", help="veh/h/lane at B = 1024")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--calls", type=int, default=150, help="timed rollout calls per measurement")
    p.add_argument("--warmup", type=int, default=20)
    p.add_argument("--threads", type=int, default=None, help="kernel threads (NUMBA_NUM_THREADS)")
    args = p.parse_args()
    if args.threads is not None and args.threads < 1:
        raise SystemExit(f"--threads must be at least 1, got {args.threads}")
    other = Path(args.against).resolve()
    if not (other / "marlmerge" / "sim" / "core.py").is_file():
        raise SystemExit(f"--against {args.against}: not a marlmerge checkout (no marlmerge/sim)")
    from marlmerge.config import ScenarioConfig

    default_flow = ScenarioConfig().traffic.flow_vph_per_lane
    configs = [(int(b), default_flow) for b in args.batches.split(",") if b]
    configs += [(1024, float(f)) for f in args.flows.split(",") if f]
    trees = {"this": HERE, "against": other}
    rows: dict[tuple[int, float], dict[str, list[dict]]]
    rows = {c: {t: [] for t in trees} for c in configs}
    for _ in range(args.rounds):
        for c in configs:
            for name, tree in trees.items():
                # the work per call grows with B: fewer calls at large B, the same world-steps
                calls = max(args.calls * 1024 // c[0], 10)
                rows[c][name].append(measure(tree, c[0], c[1], calls, args.warmup, args.threads))
    out = {"against": str(other), "rounds": args.rounds, "threads": args.threads, "configs": []}
    for (batch, flow), by_tree in rows.items():
        med = {t: statistics.median(r["vehicle_steps_per_s"] for r in by_tree[t]) for t in trees}
        digests = {r["digest"] for t in trees for r in by_tree[t]}
        per_round = [
            a["vehicle_steps_per_s"] / b["vehicle_steps_per_s"]
            for a, b in zip(by_tree["this"], by_tree["against"], strict=True)
        ]
        out["configs"].append(
            {
                "batch": batch,
                "flow_vph_per_lane": flow,
                "vehicles_per_world": by_tree["this"][0]["vehicles_per_world"],
                "this_vehicle_steps_per_s": med["this"],
                "against_vehicle_steps_per_s": med["against"],
                "ratio": med["this"] / med["against"],
                "ratio_per_round": per_round,
                "ratio_paired_median": statistics.median(per_round),
                "identical": len(digests) == 1,
            }
        )
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
