"""Drive one episode with scripted agents and save a top-down frame from the merge zone.

The ramp vehicle (`ramp_0`) holds its speed and accelerates gently towards the speed limit;
every highway agent is a `ScriptedHighwayPolicy` of its own driver profile.

    PYTHONPATH=. python examples/drive_scripted.py --seed 0 --out runs/example_frame.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import marlmerge
from marlmerge.sim import OUTCOME_NAMES
from marlmerge.sim.observation import SPEED_SCALE_MPS
from marlmerge.views.pettingzoo_env import EGO_AGENT, reward_terms
from marlmerge.views.render import save_png


def ego_action(obs: np.ndarray, speed_limit_mps: float) -> np.ndarray:
    """Gentle rule: +1 m/s^2 below 90 % of the speed limit, else hold speed."""
    speed = float(obs[0]) * SPEED_SCALE_MPS  # EGO_FEATURES[0] is the ego's speed
    return np.array([1.0 if speed < 0.9 * speed_limit_mps else 0.0], dtype=np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("runs/example_frame.png"))
    args = parser.parse_args()

    env = marlmerge.parallel_env(render_mode="rgb_array", control="all")
    obs, _ = env.reset(seed=args.seed)
    core, cfg = env.core, env.cfg
    policies = {
        a: marlmerge.ScriptedHighwayPolicy(int(core.state.profile[0, s]), cfg)
        for a, s in env.agent_slots.items()
    }
    print("highway agents:", {a: p.profile.name.lower() for a, p in policies.items()})

    frame, frame_x, step = None, None, 0
    while env.agents:
        actions = {a: policies[a](obs[a]) for a in env.agents if a != EGO_AGENT}
        actions[EGO_AGENT] = ego_action(obs[EGO_AGENT], core.v_limit)
        obs, rewards, _, _, infos = env.step(actions)
        info = infos[EGO_AGENT]
        terms = " ".join(f"{k}={v:+.3f}" for k, v in reward_terms(info).items() if v)
        print(f"step {step:3d} x={info['ego_x_m']:7.1f} m  r={rewards[EGO_AGENT]:+.3f}  {terms}")
        # keep the frame taken closest to the middle of the merge zone
        x, mid = info["ego_x_m"], -0.5 * cfg.road.merge_zone_m
        if 2 * mid <= x <= 0.0 and (frame_x is None or abs(x - mid) < abs(frame_x - mid)):
            frame, frame_x = env.render(), x
        step += 1
    print(
        f"outcome: {OUTCOME_NAMES[info['outcome']]} after {info['ego_time_s']:.1f} s ({step} steps)"
    )

    if frame is None:  # the ego never reached the merge zone: save the last frame instead
        frame = env.render()
    save_png(args.out, frame)
    print(f"saved {frame.shape[1]}x{frame.shape[0]} frame to {args.out}")


if __name__ == "__main__":
    main()
