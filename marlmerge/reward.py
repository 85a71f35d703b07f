"""Reward as a dict of named terms, the paper's eqs. (3)-(7). Evaluation metrics live elsewhere.

Every function returns per-simulator-step terms; an env step sums them over its `action_repeat`
simulator steps. All terms are penalties (<= 0), as in the paper. See `RewardConfig` for the
formulas and default weights.
"""

from __future__ import annotations

import numpy as np

from marlmerge.config import RewardConfig

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
    speed, collision. The same shapes and weights as the ego's terms."""
    safe = cfg.safe_min_gap_m + cfg.safe_headway_s * v_mps
    return {
        "acceleration": -cfg.w_accel * np.abs(accel_mps2),
        "gap_front": -cfg.w_front * proximity(gap_m, safe),
        "speed": -cfg.w_speed * speed_polygon(v_mps, speed_limit_mps, cfg),
        "collision": -cfg.collision_penalty * collided.astype(np.float64),
    }
