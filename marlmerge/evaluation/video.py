"""Videos of greedy episodes at the simulation rate: one frame per simulator step (0.1 s).

    marlmerge render runs/paper --episodes 3 --out episode.mp4      # or .gif, --view follow

Episode e is the first ramp vehicle of a fresh world seeded `seed + e`, as in the evaluation
(`marlmerge.evaluation.rollout`): with the default `seed` these are the first held-out episodes. The
policy acts every `sim.action_repeat` steps, as in training; the frames show every step in
between (`render.render_scene`: heads-up line, legend).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from marlmerge.config import ScenarioConfig, require_ego
from marlmerge.evaluation.registry import policy_for_evaluation
from marlmerge.sim import OUTCOME_NAMES, OUTCOME_NONE, TrafficCore
from marlmerge.views.render import render_scene, write_video

EgoPolicy = Callable[[torch.Tensor], torch.Tensor]
HighwayPolicy = Callable[[torch.Tensor], torch.Tensor]
HOLD_LAST_S = 1.5
"""The last frame of an episode is held this long."""


def _agents(roster) -> dict[str, int]:  # noqa: ANN001 - a Roster
    """The highway agents still taking part: name -> slot."""
    return {
        f"highway_{j}": int(roster.slots[0, j]) for j in range(roster.n_agents) if roster.mask[0, j]
    }


def record_episodes(
    policy: EgoPolicy,
    cfg: ScenarioConfig,
    episodes: int = 1,
    seed: int = 1_000_000,
    view: str = "merge",
    highway_policy: HighwayPolicy | None = None,
) -> tuple[list[np.ndarray], list[str]]:
    """Frames of `episodes` greedy episodes (every simulator step) and their outcomes."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    frames: list[np.ndarray] = []
    outcomes: list[str] = []
    k_hw = cfg.sim.n_highway_agents if highway_policy is not None else 0
    hold = int(round(HOLD_LAST_S / cfg.sim.dt_s))
    for e in range(episodes):
        core = TrafficCore(cfg, batch_size=1, seed=[seed + e])
        core.next_ego(np.ones(1, dtype=bool))  # as the evaluation's env reset does
        roster = core.make_roster(core.pick_roster(k_hw))
        caption = f"episode {e + 1}/{episodes}"
        frames.append(render_scene(core, 0, _agents(roster), view, caption))
        outcome = OUTCOME_NONE
        while outcome == OUTCOME_NONE:
            ego_obs, hw_obs = core.observe(roster)
            with torch.no_grad():
                act = policy(torch.as_tensor(ego_obs)).reshape(1, -1).double().numpy()
                a, join = act[:, 0], act[:, 1] if act.shape[1] > 1 else None
                cmd = None
                if highway_policy is not None:
                    hw = highway_policy(torch.as_tensor(hw_obs)).reshape(1, k_hw).double()
                    cmd = np.where(roster.mask, hw.numpy(), np.nan)
            for _ in range(cfg.sim.action_repeat):
                out = core.rollout(a, k=1, roster=roster, roster_accel=cmd, ego_join=join)
                frames.append(render_scene(core, 0, _agents(roster), view, caption))
                outcome = int(out.ego_outcome[0])
                if outcome != OUTCOME_NONE:
                    break
        outcomes.append(OUTCOME_NAMES[outcome])
        frames += [frames[-1]] * hold
    return frames, outcomes


def render_episodes(
    policy_spec: str,
    cfg: ScenarioConfig,
    out: str | Path,
    episodes: int = 1,
    seed: int = 1_000_000,
    view: str = "merge",
    highway: str | None = None,
) -> tuple[Path, int, list[str]]:
    """Record and write a video; returns (path, frames, outcomes). `policy_spec` as
    `evaluate` takes it (a rule, a run, or one policy in the grid's notation); a learned policy
    drives with its own ego-side settings in `cfg`'s traffic. Ramp flow (many merging agents,
    no ego) is refused before any work."""
    require_ego(cfg, f"render: scenario {cfg.name!r}")
    policy, cfg = policy_for_evaluation(policy_spec, cfg)
    highway_policy = None
    if highway is not None:
        from marlmerge.learners.highway import load_highway_policy

        highway_policy = load_highway_policy(highway, cfg)
    frames, outcomes = record_episodes(policy, cfg, episodes, seed, view, highway_policy)
    path = write_video(out, frames, fps=1.0 / cfg.sim.dt_s)
    return path, len(frames), outcomes
