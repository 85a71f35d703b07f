"""Whether a seed trained in groups of different sizes stays its own run (docs/scale-out.md):
each check runs one part of `marlmerge train --seeds` for seed 3 alone, in a group of 2 (seeds
3-4) and in a group of 5 (seeds 0-4), and prints, as JSON, where they first differ (None: equal
bit for bit).

- `env`: `hardened_mix` (a new road after every ego) without level replay, the same commands,
  `--steps` env steps of `--worlds` worlds per seed, with each seed's worlds a draw group as
  training builds them (`marlmerge.training.seeds.make_seed_env`) and without (one group: how
  the env was built before; a reset in any world drew ahead in every world, and a world's new
  road discarded what it had drawn, so seed 3's roads depended on the other seeds' resets);
- `act`: the greedy command of seed 3's slice of the observations against a copy of it;
- `fused`: the compiled fused update from a run's trained state, `--calls` calls on the same
  minibatches (needs `RUN/seeds_checkpoint.pt` of a 5-seed run, e.g. `runs/hardened`; skipped
  without one).

    python benchmarks/seed_drift.py [--run runs/hardened] [--steps 600] [--worlds 4] [--calls 300]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from marlmerge.config.presets import load_train_config, run_scenario
from marlmerge.io import files
from marlmerge.learners.common import sample_uniform
from marlmerge.learners.quadq_fused import FusedQuadQUpdates
from marlmerge.training.loop import set_torch_threads
from marlmerge.training.train import make_ego_group
from marlmerge.views.torchrl_env import BatchedMergeEnv

B = 32  # worlds per seed (the hardened recipe's)


def seed_env(seeds: list[int], b: int, grouped: bool) -> BatchedMergeEnv:
    """The worlds of `seeds`, `b` per seed, seeded as `make_seed_env` seeds them; `grouped`:
    each seed's worlds a draw group, as `make_seed_env` builds them."""
    worlds = [np.random.SeedSequence(s, spawn_key=(i,)) for s in seeds for i in range(b)]
    groups = np.repeat(np.arange(len(seeds)), b) if grouped else None
    return BatchedMergeEnv(
        "hardened_mix", num_worlds=len(seeds) * b, seed=worlds, world_groups=groups
    )


def groups(ckpt: dict, seeds: list[int]) -> list:
    """The learning groups of `seeds` as the 5-seed run's checkpoint left them."""
    cfg = load_train_config("hardened")
    scen, out = run_scenario(cfg), []
    for s in seeds:
        group = make_ego_group(dataclasses.replace(cfg, seed=s), scen, ckpt["obs_dim"])
        group.load_state_dict(ckpt["runs"][s]["group"])
        out.append(group)
    return out


def check_env(steps: int, b: int, grouped: bool) -> dict:
    """Seed 3's worlds alone, among 2 seeds' and among 5 seeds', every world driving the same
    fixed commands: the first env step where either group's slice differs from seed 3 alone."""
    where = {1: 0, 2: 0, 5: 3}
    envs = {k: seed_env([[3], [3, 4], [0, 1, 2, 3, 4]][i], b, grouped) for i, k in enumerate(where)}
    tds = {k: e.reset() for k, e in envs.items()}
    for step in range(steps):
        for k, env in envs.items():
            wobble = torch.sin(torch.arange(float(b)) + 0.7 * step).repeat(k)
            tds[k]["action"] = (1.5 * wobble).unsqueeze(-1)
            _, tds[k] = env.step_and_maybe_reset(tds[k])
        alone = tds[1]["observation"]
        for k in (2, 5):
            if not torch.equal(alone, tds[k]["observation"][where[k] * b : (where[k] + 1) * b]):
                return {"first_difference": step, "group_size": k}
    return {"first_difference": None}


def check_act(net, steps: int) -> int:
    """Env steps (of 5 seeds' worlds) where the greedy command of seed 3's slice differs from
    the command of a copy of it."""
    env = seed_env([0, 1, 2, 3, 4], B, grouped=True)
    td, differs = env.reset(), 0
    for _ in range(steps):
        obs = td["observation"]  # [5 B, d]
        sl = obs[3 * B : 4 * B]
        differs += int(not torch.equal(net.greedy(sl), net.greedy(sl.clone())))
        td["action"] = net.greedy(obs)
        _, td = env.step_and_maybe_reset(td)
    return differs


def check_fused(ckpt: dict, calls: int) -> dict:
    """The compiled fused update of seeds 0-4 against seeds 3-4, on the same minibatches."""
    big, small = groups(ckpt, [0, 1, 2, 3, 4]), groups(ckpt, [3, 4])
    five = FusedQuadQUpdates([g.learner.fast for g in big], compile=True)
    two = FusedQuadQUpdates([g.learner.fast for g in small], compile=True)
    k = five.k
    for call in range(calls):
        rows = torch.stack([sample_uniform(g.replay, k * B).view(k, B, -1) for g in big])
        lf, lt = five.step(rows), two.step(rows[3:5].clone())
        if not (torch.equal(five.flat[3:5], two.flat) and torch.equal(lf[3:5], lt)):
            return {"fused_first_difference": call}
    return {"fused_first_difference": None}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--run", default="runs/hardened", help="a 5-seed run of the hardened recipe")
    p.add_argument("--steps", type=int, default=600)
    p.add_argument("--worlds", type=int, default=4, help="worlds per seed in the env check")
    p.add_argument("--calls", type=int, default=300)
    args = p.parse_args()
    set_torch_threads(1)
    result: dict = {"steps": args.steps, "worlds": args.worlds}
    with torch.no_grad():
        result["env_grouped"] = check_env(args.steps, args.worlds, grouped=True)
        result["env_ungrouped"] = check_env(args.steps, args.worlds, grouped=False)
    path = Path(args.run) / "seeds_checkpoint.pt"
    if path.exists():
        ckpt = files.load(path)
        if ckpt["seeds"] != [0, 1, 2, 3, 4]:
            raise SystemExit(f"--run {args.run}: needs a run of seeds 0-4, got {ckpt['seeds']}")
        weights = ckpt["runs"][3]["group"]["learner"]["loss"]
        ckpt["obs_dim"] = weights["value_network_params.hidden.weight"].shape[1]
        with torch.no_grad():
            result["act_differences"] = check_act(groups(ckpt, [3])[0].learner.net, 300)
        result["calls"] = args.calls
        result.update(check_fused(ckpt, args.calls))
    print(json.dumps(result))


if __name__ == "__main__":
    main()
