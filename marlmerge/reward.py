"""Reward as a dict of named terms, the paper's eqs. (3)-(7). Evaluation metrics live elsewhere.

Every function returns per-simulator-step terms; an env step sums them over its `action_repeat`
simulator steps. All terms are penalties (<= 0), as in the paper. See `RewardConfig` for the
formulas and default weights.
"""

from __future__ import annotations

import numpy as np

from marlmerge.config import InteractionConfig, RewardConfig
from marlmerge.core import EGO, OUTCOME_TRUNCATED, EgoGaps, StepEvents, TrafficCore

EGO_TERMS = ("acceleration", "gap_front", "gap_back", "speed", "collision")
"""Names of the ego's reward terms, in reporting order."""
HIGHWAY_TERMS = ("acceleration", "gap_front", "speed", "collision")


def proximity(gap_m: np.ndarray, safe_m: np.ndarray) -> np.ndarray:
    """g(d) = clip(1 - d / safe, 0, 1)^2: 0 beyond the safe distance, 1 when touching."""
    closeness = np.clip(1.0 - gap_m / np.maximum(safe_m, 1e-6), 0.0, 1.0)
    return closeness * closeness


def speed_polygon(v_mps: np.ndarray, speed_limit_mps: float, cfg: RewardConfig) -> np.ndarray:
    """Polygonal speed penalty shape: 1 at standstill, 0 in [v_low, v_limit], rising above it."""
    v_low = cfg.speed_low_fraction * speed_limit_mps
    too_slow = np.clip((v_low - v_mps) / v_low, 0.0, None)
    too_fast = np.clip((v_mps - speed_limit_mps) / cfg.speed_over_scale_mps, 0.0, None)
    return too_slow + too_fast


def ego_reward_terms(
    cfg: RewardConfig,
    accel_mps2: np.ndarray,
    v_mps: np.ndarray,
    x_m: np.ndarray,
    d_front_m: np.ndarray,
    d_back_m: np.ndarray,
    v_back_mps: np.ndarray,
    collided: np.ndarray,
    speed_limit_mps: float,
) -> dict[str, np.ndarray]:
    """One simulator step of the ego's reward terms, each [B]."""
    near = x_m >= cfg.distance_active_from_m
    safe_front = cfg.safe_min_gap_m + cfg.safe_headway_s * v_mps
    safe_back = cfg.safe_min_gap_m + cfg.safe_headway_s * v_back_mps
    return {
        "acceleration": -cfg.w_accel * np.abs(accel_mps2),
        "gap_front": -cfg.w_front * proximity(d_front_m, safe_front) * near,
        "gap_back": -cfg.w_back * proximity(d_back_m, safe_back) * near,
        "speed": -cfg.w_speed * speed_polygon(v_mps, speed_limit_mps, cfg),
        "collision": -cfg.collision_penalty * collided.astype(np.float64),
    }


def highway_reward_terms(
    cfg: RewardConfig,
    accel_mps2: np.ndarray,
    v_mps: np.ndarray,
    gap_m: np.ndarray,
    collided: np.ndarray,
    speed_limit_mps: float,
) -> dict[str, np.ndarray]:
    """One simulator step of a mainline driver's own driving reward: comfort, safety to its leader,
    speed, collision. The ego's shapes and weights, except the speed term (`w_highway_speed`:
    distance from the speed limit, no dead band below it)."""
    safe = cfg.safe_min_gap_m + cfg.safe_headway_s * v_mps
    return {
        "acceleration": -cfg.w_accel * np.abs(accel_mps2),
        "gap_front": -cfg.w_front * proximity(gap_m, safe),
        "speed": -cfg.w_highway_speed
        * (
            np.clip(speed_limit_mps - v_mps, 0.0, None) / speed_limit_mps
            + np.clip(v_mps - speed_limit_mps, 0.0, None) / cfg.speed_over_scale_mps
        ),
        "collision": -cfg.collision_penalty * collided.astype(np.float64),
    }


INTERACTION_TERMS = ("ego_collision", "ego_hard_brake", "ego_stall", "ego_unsafe_gap")
"""Names of a learned highway agent's interaction terms (see `InteractionConfig`)."""
LEARNED_HIGHWAY_TERMS = HIGHWAY_TERMS + INTERACTION_TERMS


def ego_collision_blame(
    cfg: InteractionConfig,
    slots: np.ndarray,
    ego_partner: np.ndarray,
    ego_rear: np.ndarray,
    ego_in_lane_s: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Who is to blame for a collision between the ego and the vehicles in `slots` ([B, K]).

    ego_partner [B]: slot the ego hit this step (-1 none); ego_rear [B]: the ego was the rear
    vehicle; ego_in_lane_s [B]: how long the ego had been in the right lane. The rear vehicle is
    to blame, unless the front one is the ego and it cut in less than `cut_in_grace_s` ago.
    Returns (ego_to_blame, agent_to_blame), each [B, K] bool.
    """
    hit = (slots >= 0) & (slots == ego_partner[:, None])
    ego_blamed = (ego_rear | (ego_in_lane_s < cfg.cut_in_grace_s))[:, None]
    return hit & ego_blamed, hit & ~ego_blamed


def interaction_terms(
    cfg: InteractionConfig,
    slots: np.ndarray,
    dt_s: float,
    ego_accel_mps2: np.ndarray,
    ego_partner: np.ndarray,
    ego_rear: np.ndarray,
    ego_in_lane_s: np.ndarray,
    ego_truncated: np.ndarray,
    gap_front: np.ndarray,
    gap_back: np.ndarray,
    closeness_front: np.ndarray | None = None,
    closeness_back: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """One simulator step of the interaction terms of the highway agents in `slots` ([B, K] int,
    -1 for none), each [B, K], signed by `cfg.sign`.

    Only ego failures the agent contributed to count: the ego ran into it (or cut in front of it
    and was hit at once), the ego brakes hard behind it (it is the gap-front vehicle), or the ego
    was truncated with it as a gap vehicle, or it holds the ego at an unsafe gap. Ego failures
    involving other vehicles give 0. ego_accel_mps2, ego_partner, ego_rear, ego_in_lane_s,
    ego_truncated (bool), gap_front and gap_back (slots of the ego's gap vehicles after the step,
    -1 none), closeness_front and closeness_back (the ego's gap closeness g in [0, 1], 0 outside
    the merge area; zeros if None) are [B] each.
    """
    present = slots >= 0
    ego_blamed, _ = ego_collision_blame(cfg, slots, ego_partner, ego_rear, ego_in_lane_s)
    is_front = present & (slots == gap_front[:, None])
    is_back = present & (slots == gap_back[:, None])
    hard = (ego_accel_mps2 <= -cfg.hard_brake_mps2)[:, None]
    return {
        "ego_collision": cfg.sign * cfg.w_ego_collision * ego_blamed,
        "ego_hard_brake": cfg.sign * cfg.w_ego_hard_brake_per_s * dt_s * (hard & is_front),
        "ego_stall": cfg.sign * cfg.w_ego_stall * (ego_truncated[:, None] & (is_front | is_back)),
        "ego_unsafe_gap": cfg.sign
        * cfg.w_ego_unsafe_gap_per_s
        * dt_s
        * (
            is_front * (0.0 if closeness_front is None else closeness_front[:, None])
            + is_back * (0.0 if closeness_back is None else closeness_back[:, None])
        ),
    }


def highway_agent_step_terms(
    core: TrafficCore,
    ev: StepEvents,
    gaps: EgoGaps,
    slots: np.ndarray,
    ego_in_lane_s: np.ndarray,
) -> dict[str, np.ndarray]:
    """One simulator step of a highway agent's reward, every `LEARNED_HIGHWAY_TERMS` entry, for
    the vehicles in `slots` ([B, K] int, -1 = no agent: 0 there), right after `core.step`.

    Own driving terms as `highway_reward_terms`, with the collision term of `InteractionConfig`
    (every collision except one the ego is to blame for), plus the interaction terms signed by
    `interaction.sign`. ego_in_lane_s [B]: how long the ego has been in the right lane.
    """
    cfg = core.cfg
    st = core.state
    s = np.maximum(slots, 0)
    on = slots >= 0

    def take(a: np.ndarray) -> np.ndarray:
        return np.take_along_axis(a, s, axis=1)

    ego_blamed, _ = ego_collision_blame(
        cfg.interaction, slots, ev.ego_partner, ev.ego_rear, ego_in_lane_s
    )
    own = highway_reward_terms(
        cfg.reward,
        take(st.a_mps2),
        take(st.v_mps),
        take(core.nb.gap_m),
        np.zeros(slots.shape, dtype=bool),
        core.v_limit,
    )
    own["collision"] = -cfg.interaction.own_collision_penalty * (take(ev.collided) & ~ego_blamed)
    rc = cfg.reward
    near = st.x_m[:, EGO] >= rc.distance_active_from_m
    close_f = proximity(gaps.d_front_m, rc.safe_min_gap_m + rc.safe_headway_s * st.v_mps[:, EGO])
    close_b = proximity(gaps.d_back_m, rc.safe_min_gap_m + rc.safe_headway_s * gaps.v_back_mps)
    inter = interaction_terms(
        cfg.interaction,
        slots,
        cfg.sim.dt_s,
        st.a_mps2[:, EGO],
        ev.ego_partner,
        ev.ego_rear,
        ego_in_lane_s,
        ev.ego_outcome == OUTCOME_TRUNCATED,
        gaps.front,
        gaps.back,
        close_f * near,
        close_b * near,
    )
    return {t: np.where(on, v, 0.0) for t, v in (own | inter).items()}
