"""Where a seed trained in groups of different sizes could start to differ (docs/scale-out.md):
each check runs one part of `marlmerge train --seeds` for seed 3 in a group of 2 (seeds 3-4) and
in a group of 5 (seeds 0-4) and prints, as JSON, whether the two stay equal bit for bit.

- `env`: `hardened_mix` without level replay, the same commands, `--steps` env steps;
- `act`: the greedy command of seed 3's slice of the observations against a copy of it;
- `fused`: the compiled fused update from a run's trained state, `--calls` calls on the same
  minibatches (needs `RUN/seeds_checkpoint.pt` of a 5-seed run, e.g. `runs/hardened`).

    python benchmarks/seed_drift.py [--run runs/hardened] [--steps 3000] [--calls 300]
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


def seed_env(seeds: list[int]) -> BatchedMergeEnv:
    """The worlds of `seeds`, seeded as `marlmerge.training.seeds.make_seed_env` seeds them."""
    worlds = [np.random.SeedSequence(s, spawn_key=(i,)) for s in seeds for i in range(B)]
    return BatchedMergeEnv("hardened_mix", num_worlds=len(seeds) * B, seed=worlds)


def groups(ckpt: dict, seeds: list[int]) -> list:
    """The learning groups of `seeds` as the 5-seed run's checkpoint left them."""
    cfg = load_train_config("hardened")
    scen, out = run_scenario(cfg), []
    for s in seeds:
        group = make_ego_group(dataclasses.replace(cfg, seed=s), scen, ckpt["obs_dim"])
        group.load_state_dict(ckpt["runs"][s]["group"])
        out.append(group)
    return out


def check_env_and_act(net, steps: int) -> dict:
    """Seed 3's worlds among 2 seeds' and among 5 seeds', driven by `net` (+ a fixed wobble)."""
    envs, where = {2: seed_env([3, 4]), 5: seed_env([0, 1, 2, 3, 4])}, {2: 0, 5: 3}
    tds = {k: e.reset() for k, e in envs.items()}
    act_differs = 0
    for step in range(steps):
        for k, env in envs.items():
            obs = tds[k]["observation"]  # [k * B, d]
            wobble = 0.3 * torch.sin(torch.arange(float(B)) + step).unsqueeze(-1)
            acts = [net.greedy(obs[j * B : (j + 1) * B]) + wobble for j in range(k)]
            sl = obs[where[k] * B : (where[k] + 1) * B]
            act_differs += int(not torch.equal(net.greedy(sl), net.greedy(sl.clone())))
            tds[k]["action"] = torch.cat(acts)
            tds[k] = env.step(tds[k])["next"]
        if not torch.equal(tds[2]["observation"][:B], tds[5]["observation"][3 * B : 4 * B]):
            return {"env_first_difference": step, "act_differences": act_differs}
    return {"env_first_difference": None, "act_differences": act_differs}


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
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--calls", type=int, default=300)
    args = p.parse_args()
    set_torch_threads(1)
    ckpt = files.load(Path(args.run) / "seeds_checkpoint.pt")
    if ckpt["seeds"] != [0, 1, 2, 3, 4]:
        raise SystemExit(f"--run {args.run}: needs a run of seeds 0-4, got {ckpt['seeds']}")
    weights = ckpt["runs"][3]["group"]["learner"]["loss"]
    ckpt["obs_dim"] = weights["value_network_params.hidden.weight"].shape[1]
    net = groups(ckpt, [3])[0].learner.net
    result = {"steps": args.steps, "calls": args.calls}
    with torch.no_grad():
        result.update(check_env_and_act(net, args.steps))
    result.update(check_fused(ckpt, args.calls))
    print(json.dumps(result))


if __name__ == "__main__":
    main()
