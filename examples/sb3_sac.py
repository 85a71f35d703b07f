"""Train Stable-Baselines3's SAC on the ramp vehicle and evaluate it with this project's metrics.

    pip install -c constraints.txt -e ".[sb3]"
    python examples/sb3_sac.py --timesteps 200000 --out runs/sb3_sac

SAC learns on `MergeVecEnv` (the batched core as an SB3 VecEnv: the paper's state, reward and
episode, scripted mixed traffic). Every `--eval-every` timesteps and at the end, the
deterministic policy is evaluated on the same held-out roads as `marlmerge train` evaluates its
learners (`--eval-episodes` from seed 1,000,000) and the success rate is printed; the final
evaluation and the learning curve go to `OUT/evaluation.json`, the model to `OUT/model.zip`.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from stable_baselines3 import SAC
from stable_baselines3.common.callbacks import BaseCallback

from marlmerge.evaluation.rollout import evaluate_policy
from marlmerge.views.pettingzoo_env import resolve_config
from marlmerge.views.sb3_env import MergeVecEnv


def greedy(model: SAC):
    """obs [B, 7] -> acceleration [B, 1], as marlmerge's evaluation expects."""

    def policy(obs: torch.Tensor) -> torch.Tensor:
        action, _ = model.predict(obs.numpy(), deterministic=True)
        return torch.as_tensor(np.asarray(action, dtype=np.float32))

    return policy


class EvalEvery(BaseCallback):
    """Evaluate on the held-out roads every `every` timesteps."""

    def __init__(self, every: int, episodes: int, scenario, curve: list):
        super().__init__()
        self.every, self.episodes, self.scenario, self.curve = every, episodes, scenario, curve
        self.next_at = every

    def _on_step(self) -> bool:
        if self.num_timesteps >= self.next_at:
            self.next_at += self.every
            ev = evaluate_policy(greedy(self.model), self.scenario, self.episodes)
            self.curve.append({"timesteps": self.num_timesteps, **ev})
            print(
                f"{self.num_timesteps:>9,} timesteps: success {ev['success_rate']:.1%}, "
                f"collision {ev['collision_rate']:.1%}",
                flush=True,
            )
        return True


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--timesteps", type=int, default=200_000, help="env steps, all worlds summed")
    p.add_argument("--envs", type=int, default=8, help="worlds stepped together")
    p.add_argument("--scenario", default="default")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eval-episodes", type=int, default=200)
    p.add_argument("--eval-every", type=int, default=50_000)
    p.add_argument("--out", default="runs/sb3_sac")
    args = p.parse_args()
    torch.set_num_threads(1)
    scenario = resolve_config(args.scenario)
    env = MergeVecEnv(num_envs=args.envs, config=scenario, seed=args.seed)
    model = SAC(
        "MlpPolicy",
        env,
        learning_starts=1_000,
        batch_size=256,
        gamma=0.95,  # the paper's discount
        seed=args.seed,
        device="cpu",
        verbose=0,
    )
    curve: list[dict] = []
    t0 = time.perf_counter()
    model.learn(
        args.timesteps, callback=EvalEvery(args.eval_every, args.eval_episodes, scenario, curve)
    )
    wall = time.perf_counter() - t0
    final = evaluate_policy(greedy(model), scenario, args.eval_episodes)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    model.save(out / "model.zip")
    result = {
        "timesteps": args.timesteps,
        "simulator_steps": args.timesteps * scenario.sim.action_repeat,
        "envs": args.envs,
        "seed": args.seed,
        "wall_s": wall,
        "final": final,
        "curve": curve,
    }
    (out / "evaluation.json").write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k != "curve"}, indent=1))


if __name__ == "__main__":
    main()
