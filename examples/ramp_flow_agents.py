"""Every ramp vehicle an agent: ramp flow in PettingZoo, driven by gap acceptance.

Ramp vehicles arrive at 600 veh/h (`envs/ramp_flow.toml`); each becomes an agent `ramp_i` when it
enters the ramp and leaves when its merge ends. One policy (here the gap-acceptance rule on the
paper's observation) acts for all of them; the script counts how their merges end.

    PYTHONPATH=. python examples/ramp_flow_agents.py --seed 0 --cycles 1000
"""

from __future__ import annotations

import argparse
from collections import Counter

import numpy as np

import marlmerge
from marlmerge.policies.gap_acceptance import GapAcceptancePolicy
from marlmerge.sim import OUTCOME_NAMES


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cycles", type=int, default=1000, help="env steps of 0.4 s")
    args = parser.parse_args()

    env = marlmerge.ramp_flow_parallel_env("ramp_flow", max_cycles=args.cycles)
    policy = GapAcceptancePolicy(env.cfg)
    obs, _ = env.reset(seed=args.seed)
    ended: Counter[str] = Counter()
    most_at_once = 0
    while env.agents:
        most_at_once = max(most_at_once, len(env.agents))
        batch = np.stack([obs[a] for a in env.agents])  # [n, 7]: one policy for every agent
        actions = dict(zip(env.agents, policy(batch), strict=True))
        obs, rewards, terminated, truncated, infos = env.step(actions)
        for a in rewards:
            if terminated[a] or truncated[a]:  # "running": cut off at the episode's end
                ended[OUTCOME_NAMES[int(infos[a]["outcome"])]] += 1
    print(f"{sum(ended.values())} merges ended ({dict(ended)}); {most_at_once} agents at once")


if __name__ == "__main__":
    main()
