"""Reward as named terms, the paper's eqs. (3)-(7), written once as compiled scalar functions.

The simulator's kernel calls these after every simulator step for the ego and for the highway
agents, and sums them over an env step (`action_repeat` simulator steps); views only read the sums.
All terms are penalties (<= 0), as in the paper, except the interaction terms of a learned
adversary, which are signed by `interaction.sign`. Formulas and default weights: `RewardConfig`
and `InteractionConfig`. Evaluation metrics live elsewhere (`marlmerge.evaluation.metrics`).

`params` is the core's parameter vector (`marlmerge.sim.layout.pack_params`).
"""

from __future__ import annotations

import math

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.sim.jit import kernel
from marlmerge.sim.layout import (
    P_BACK_HW,
    P_BACK_TTC,
    P_COLLISION_PENALTY,
    P_DIST_ACTIVE,
    P_DT,
    P_I_GRACE,
    P_I_HARD_BRAKE,
    P_I_OWN_COLLISION,
    P_I_SIGN,
    P_I_W_COLLISION,
    P_I_W_HARD_BRAKE,
    P_I_W_STALL,
    P_I_W_UNSAFE,
    P_JOIN_CHOSEN,
    P_SAFE_HEADWAY,
    P_SAFE_MIN_GAP,
    P_SENSING,
    P_SPEED_LOW,
    P_SPEED_OVER,
    P_V_LIMIT,
    P_W_ACCEL,
    P_W_BACK,
    P_W_BACK_HW,
    P_W_BACK_TTC,
    P_W_FRONT,
    P_W_HW_SPEED,
    P_W_JERK,
    P_W_SPEED,
    pack_params,
)

EGO_TERMS = (
    "acceleration",
    "gap_front",
    "gap_back",
    "speed",
    "collision",
    "back_headway",
    "back_ttc",
    "jerk",
)
"""Names of the ego's reward terms, in reporting order (columns of the kernel's ego sums). The
last three, the follower's terms and the jerk term, are 0 unless weighted
(`RewardConfig.w_back_headway`, `w_back_ttc`, `w_jerk`)."""
HIGHWAY_TERMS = ("acceleration", "gap_front", "speed", "collision")
"""A mainline driver's own driving terms."""
INTERACTION_TERMS = ("ego_collision", "ego_hard_brake", "ego_stall", "ego_unsafe_gap")
"""Names of a learned highway agent's interaction terms (see `InteractionConfig`)."""
LEARNED_HIGHWAY_TERMS = HIGHWAY_TERMS + INTERACTION_TERMS
"""Columns of the kernel's highway-agent sums, in this order."""


@kernel
def proximity(gap_m: float, safe_m: float) -> float:
    """g(d) = clip(1 - d / safe, 0, 1)^2: 0 beyond the safe distance, 1 when touching."""
    closeness = min(max(1.0 - gap_m / max(safe_m, 1e-6), 0.0), 1.0)
    return closeness * closeness


@kernel
def speed_polygon(
    v_mps: float, speed_limit_mps: float, low_fraction: float, over_scale_mps: float
) -> float:
    """Polygonal speed penalty shape: 1 at standstill, 0 in [v_low, v_limit], rising above it."""
    v_low = low_fraction * speed_limit_mps
    too_slow = max((v_low - v_mps) / v_low, 0.0)
    too_fast = max((v_mps - speed_limit_mps) / over_scale_mps, 0.0)
    return too_slow + too_fast


@kernel
def ego_closeness(
    params, x_m: float, v_mps: float, d_front_m: float, d_back_m: float, v_back_mps: float
) -> tuple[float, float]:  # noqa: ANN001
    """The ego's gap closeness g to its gap-front and gap-back vehicles, 0 outside the merge
    area (upstream of `distance_active_from_m`). Safe distances: s0 + T_safe x own speed (front)
    and x the gap-back vehicle's speed (back)."""
    if x_m < params[P_DIST_ACTIVE]:
        return 0.0, 0.0
    s0, t = params[P_SAFE_MIN_GAP], params[P_SAFE_HEADWAY]
    return proximity(d_front_m, s0 + t * v_mps), proximity(d_back_m, s0 + t * v_back_mps)


@kernel(inline=True)
def merge_gaps(params, on_ramp: bool, d_front_m: float, d_back_m: float) -> tuple[float, float]:  # noqa: ANN001
    """The gaps (m) the distance terms see. With a chosen join (`ego.join = "chosen"`) a vehicle
    still on the ramp or the acceleration lane is beside its gap, not in it: no gap vehicle (the
    sensing range) until it joins, so the terms weigh the gap it joins, not the one it passes.
    Otherwise (the paper's forced join) the gaps as given."""
    if on_ramp and params[P_JOIN_CHOSEN] > 0.0:
        return params[P_SENSING], params[P_SENSING]
    return d_front_m, d_back_m


@kernel
def follower_closeness(
    params, x_m: float, v_mps: float, d_back_m: float, v_back_mps: float
) -> tuple[float, float]:  # noqa: ANN001
    """How far the gap-back vehicle is inside its headway and its time-to-collision thresholds,
    g = clip(1 - d / s, 0, 1)^2 with s = back_headway_s x its speed and s = back_ttc_s x its
    closing speed on the ego (0 when it is not closing in); 0 outside the merge area or without
    a gap-back vehicle within the sensing range (a virtual one is never closer than that)."""
    if x_m < params[P_DIST_ACTIVE] or d_back_m >= params[P_SENSING]:
        return 0.0, 0.0
    closing = max(v_back_mps - v_mps, 0.0)
    return (
        proximity(d_back_m, params[P_BACK_HW] * v_back_mps),
        proximity(d_back_m, params[P_BACK_TTC] * closing),
    )


@kernel(inline=True)
def add_ego_terms(
    params,
    out,
    b: int,
    accel_mps2: float,
    x_m: float,
    v_mps: float,
    d_front_m: float,
    d_back_m: float,
    v_back_mps: float,
    collided: bool,
    accel_change_mps2: float,
) -> None:  # noqa: ANN001
    """Add one simulator step of the ego's `EGO_TERMS` to out[b] ([B, 8]); accel is the applied
    one, accel_change its change since the previous step of the episode (0 on the first)."""
    close_f, close_b = ego_closeness(params, x_m, v_mps, d_front_m, d_back_m, v_back_mps)
    out[b, 0] += -params[P_W_ACCEL] * abs(accel_mps2)
    out[b, 1] += -params[P_W_FRONT] * close_f
    out[b, 2] += -params[P_W_BACK] * close_b
    out[b, 3] += -params[P_W_SPEED] * speed_polygon(
        v_mps, params[P_V_LIMIT], params[P_SPEED_LOW], params[P_SPEED_OVER]
    )
    out[b, 4] += -params[P_COLLISION_PENALTY] * collided
    close_hw, close_ttc = follower_closeness(params, x_m, v_mps, d_back_m, v_back_mps)
    out[b, 5] += -params[P_W_BACK_HW] * close_hw
    out[b, 6] += -params[P_W_BACK_TTC] * close_ttc
    out[b, 7] += -params[P_W_JERK] * accel_change_mps2 * accel_change_mps2


def total_reward(terms: np.ndarray) -> np.ndarray:
    """The reward: the named terms [..., T] summed left to right in `EGO_TERMS` order, so that a
    term left at 0 changes no bit of the total (a plain `sum` may pair the terms differently)."""
    # accumulate adds left to right (a `sum` reduces in blocks); + 0.0 as a sum from +0.0 ends
    return np.add.accumulate(terms, axis=-1)[..., -1] + 0.0


@kernel
def ego_to_blame(params, ego_rear: bool, ego_in_lane_s: float) -> bool:  # noqa: ANN001
    """In a collision of the ego with a highway vehicle, the rear vehicle is to blame, unless the
    front one is the ego and it cut in less than `cut_in_grace_s` before."""
    return ego_rear or ego_in_lane_s < params[P_I_GRACE]


@kernel
def add_highway_terms(
    params,
    out,
    b: int,
    j: int,
    a_mps2: float,
    v_mps: float,
    gap_m: float,
    collided: bool,
    hit_ego: bool,
    ego_blamed: bool,
    is_front: bool,
    is_back: bool,
    ego_a_mps2: float,
    ego_truncated: bool,
    close_front: float,
    close_back: float,
) -> None:  # noqa: ANN001
    """Add one simulator step of a highway agent's `LEARNED_HIGHWAY_TERMS` to out[b, j] ([B, K, 8]).

    Own driving terms: comfort (|realised acceleration|), safety to its own leader, speed (the
    distance from the limit, no dead band), and -own_collision_penalty for every collision it is
    in except one the ego is to blame for. Interaction terms, signed by `interaction.sign`, only
    for ego failures it contributed to: the ego ran into it (or cut in just before being hit),
    the ego brakes hard behind it (it is the gap-front vehicle), the ego is truncated with it as
    a gap vehicle, or it holds the ego at an unsafe gap (closeness g of the ego's gap terms).
    hit_ego: this vehicle is the ego's collision partner of this step; ego_blamed: the ego is to
    blame for that collision.
    """
    v_limit = params[P_V_LIMIT]
    safe = params[P_SAFE_MIN_GAP] + params[P_SAFE_HEADWAY] * v_mps
    out[b, j, 0] += -params[P_W_ACCEL] * abs(a_mps2)
    out[b, j, 1] += -params[P_W_FRONT] * proximity(gap_m, safe)
    out[b, j, 2] += -params[P_W_HW_SPEED] * (
        max(v_limit - v_mps, 0.0) / v_limit + max(v_mps - v_limit, 0.0) / params[P_SPEED_OVER]
    )
    blamed_on_ego = hit_ego and ego_blamed
    out[b, j, 3] += -params[P_I_OWN_COLLISION] * (collided and not blamed_on_ego)
    sign, dt = params[P_I_SIGN], params[P_DT]
    out[b, j, 4] += sign * params[P_I_W_COLLISION] * blamed_on_ego
    hard = ego_a_mps2 <= -params[P_I_HARD_BRAKE]
    out[b, j, 5] += sign * params[P_I_W_HARD_BRAKE] * dt * (hard and is_front)
    out[b, j, 6] += sign * params[P_I_W_STALL] * (ego_truncated and (is_front or is_back))
    out[b, j, 7] += (
        sign * params[P_I_W_UNSAFE] * dt * (is_front * close_front + is_back * close_back)
    )


# ----------------------------------------------------------------------------------------------
# One step of the terms from Python, by name (documentation, tests, analysis)
# ----------------------------------------------------------------------------------------------


def ego_step_terms(
    cfg: ScenarioConfig,
    accel_mps2: float,
    x_m: float,
    v_mps: float,
    d_front_m: float,
    d_back_m: float,
    v_back_mps: float,
    collided: bool = False,
    accel_change_mps2: float = 0.0,
) -> dict[str, float]:
    """The ego's `EGO_TERMS` for one simulator step, by the kernel's own function."""
    out = np.zeros((1, len(EGO_TERMS)))
    add_ego_terms(
        pack_params(cfg), out, 0, accel_mps2, x_m, v_mps, d_front_m, d_back_m, v_back_mps, collided,
        accel_change_mps2,
    )  # fmt: skip
    return dict(zip(EGO_TERMS, out[0].tolist(), strict=True))


def highway_step_terms(
    cfg: ScenarioConfig,
    a_mps2: float = 0.0,
    v_mps: float | None = None,
    gap_m: float = math.inf,
    collided: bool = False,
    hit_ego: bool = False,
    ego_rear: bool = False,
    ego_in_lane_s: float = 5.0,
    is_front: bool = False,
    is_back: bool = False,
    ego_a_mps2: float = 0.0,
    ego_truncated: bool = False,
    close_front: float = 0.0,
    close_back: float = 0.0,
) -> dict[str, float]:
    """A highway agent's `LEARNED_HIGHWAY_TERMS` for one simulator step, by the kernel's own
    function. v_mps defaults to the speed limit; blame follows `ego_to_blame`."""
    p = pack_params(cfg)
    v = cfg.road.speed_limit_mps if v_mps is None else v_mps
    out = np.zeros((1, 1, len(LEARNED_HIGHWAY_TERMS)))
    blamed = ego_to_blame(p, ego_rear, ego_in_lane_s)
    add_highway_terms(
        p, out, 0, 0, a_mps2, v, gap_m, collided, hit_ego, blamed, is_front, is_back,
        ego_a_mps2, ego_truncated, close_front, close_back,
    )  # fmt: skip
    return dict(zip(LEARNED_HIGHWAY_TERMS, out[0, 0].tolist(), strict=True))
