"""How plausible learned highway drivers are: measured per episode, never assumed.

An adversary that makes the ego fail by driving as no one drives (ramming, stopping dead on a
highway, tailgating at a few metres) finds nothing worth fixing. While an evaluation runs a
highway policy (`rollout_first_egos(..., highway_policy=...)`), `HighwayTally` counts, over
the acting highway agents of every episode:

    highway_agent_steps          agent env steps (an agent acting for one env step = 1)
    highway_own_fault_collisions collisions an agent is in that the blame rule does not put on
                                 the ego (`marlmerge.sim.reward.ego_to_blame`): with a mainline
                                 vehicle, or with an ego it ran into
    highway_hard_brake_steps     agent steps at an applied acceleration <= -hard_brake_mps2
                                 (`interaction.hard_brake_mps2`, 3 m/s^2 by default)
    highway_slow_steps           agent steps below half the speed limit
    highway_short_headway_steps  agent steps at a time headway to the own-lane leader < 1 s
    highway_min_headway_s        the smallest such headway of the episode (s; inf: none; the
                                 summary reports the median over episodes)

`summarize_highway` turns them into the rates the evaluation reports, and `fairness` pairs an
ego's outcomes with gap acceptance's on the same roads. The own-fault count reads
the agent's own `collision` reward term (-own_collision_penalty for exactly those collisions), so
it needs `interaction.own_collision_penalty > 0` (the default, 100); with 0 it is NaN.
"""

from __future__ import annotations

import numpy as np
from tensordict import TensorDictBase

from marlmerge.config import ScenarioConfig
from marlmerge.sim import OUTCOME_SUCCESS
from marlmerge.sim.observation import HIGHWAY_FEATURES, HIGHWAY_SCALE, feature_index
from marlmerge.views.torchrl_groups import GROUP

SHORT_HEADWAY_S = 1.0
"""A time headway under this is counted as short (about half the usual 2 s rule)."""
FIELDS = (
    "highway_agent_steps",
    "highway_own_fault_collisions",
    "highway_hard_brake_steps",
    "highway_slow_steps",
    "highway_short_headway_steps",
    "highway_min_headway_s",
)

_SPEED = feature_index(HIGHWAY_FEATURES, "speed")
_GAP = feature_index(HIGHWAY_FEATURES, "leader_gap")
_LIMIT = feature_index(HIGHWAY_FEATURES, "speed_limit")


class HighwayTally:
    """Per-episode plausibility counts of the highway agents of `worlds` episodes (see the
    module docstring); `add` once per env step, `records` at the end."""

    def __init__(self, scenario: ScenarioConfig, worlds: int) -> None:
        self.hard_brake_mps2 = scenario.interaction.hard_brake_mps2
        self.low, self.high = scenario.sim.highway_agent_accel_bounds_mps2
        self.blames_known = scenario.interaction.own_collision_penalty > 0
        self.counts = {f: np.zeros(worlds) for f in FIELDS}
        self.counts["highway_min_headway_s"][:] = np.inf

    def add(self, td: TensorDictBase, nxt: TensorDictBase, running: np.ndarray) -> None:
        """One env step: `td` holds the group's observation, mask and action before it, `nxt`
        the step's outputs; `running` [B] marks the episodes still counting."""
        acting = td.get((GROUP, "mask")).numpy() & running[:, None]  # [B, K]
        obs = td.get((GROUP, "observation")).numpy().astype(np.float64) * HIGHWAY_SCALE
        accel = np.clip(td.get((GROUP, "action")).numpy()[..., 0], self.low, self.high)
        speed, gap, limit = obs[..., _SPEED], obs[..., _GAP], obs[..., _LIMIT]  # [B, K]
        moving = acting & (speed > 1.0)
        headway = np.where(moving, gap / np.maximum(speed, 1.0), np.inf)
        own = nxt.get((GROUP, "reward_terms", "collision")).numpy()[..., 0] < 0  # [B, K]
        c = self.counts
        c["highway_agent_steps"] += acting.sum(1)
        c["highway_own_fault_collisions"] += (own & acting).sum(1)
        c["highway_hard_brake_steps"] += (acting & (accel <= -self.hard_brake_mps2)).sum(1)
        c["highway_slow_steps"] += (acting & (speed < 0.5 * limit)).sum(1)
        c["highway_short_headway_steps"] += (headway < SHORT_HEADWAY_S).sum(1)
        c["highway_min_headway_s"] = np.minimum(c["highway_min_headway_s"], headway.min(1))

    def records(self) -> dict[str, np.ndarray]:
        out = {k: v.copy() for k, v in self.counts.items()}
        if not self.blames_known:
            out["highway_own_fault_collisions"][:] = np.nan
        return out


def summarize_highway(rec: dict[str, np.ndarray]) -> dict[str, float]:
    """The rates the evaluation reports (empty without highway records)."""
    if "highway_agent_steps" not in rec:
        return {}
    steps = max(float(rec["highway_agent_steps"].sum()), 1.0)
    own = rec["highway_own_fault_collisions"]
    return {
        "highway_own_fault_collision_rate": float(np.mean(own > 0))
        if np.isfinite(own).all()
        else float("nan"),  # fmt: skip
        "highway_hard_brake_share": float(rec["highway_hard_brake_steps"].sum() / steps),
        "highway_slow_share": float(rec["highway_slow_steps"].sum() / steps),
        "highway_short_headway_share": float(rec["highway_short_headway_steps"].sum() / steps),
        "highway_min_headway_s_median": float(np.median(rec["highway_min_headway_s"])),
    }


def fairness(ego: np.ndarray, rule: np.ndarray) -> dict[str, float]:
    """Pair the outcomes of an ego and of gap acceptance on the same roads against the same
    highway policy ([episodes] outcome codes each): a failure the careful rule driver suffers
    too counts against the highway policy, not the ego.

    ego_failure_rate    the ego's collisions and truncations
    rule_failure_rate   gap acceptance's
    fair_failure_rate   the ego's failures on roads where gap acceptance succeeds: what the
                        highway policy found in the ego, not in the traffic
    """
    ego_fail, rule_fail = ego != OUTCOME_SUCCESS, rule != OUTCOME_SUCCESS
    return {
        "ego_failure_rate": float(ego_fail.mean()),
        "rule_failure_rate": float(rule_fail.mean()),
        "fair_failure_rate": float((ego_fail & ~rule_fail).mean()),
    }
