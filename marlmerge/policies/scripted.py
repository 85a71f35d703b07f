"""Scripted policies that act through the agent interface (observation in, acceleration out).

`ScriptedHighwayPolicy` drives a highway agent from its observation alone with the same driver
functions the simulator core uses (`marlmerge.sim.drivers`), so a scripted and a learned policy are
interchangeable. Inside the core each background vehicle has its own drawn parameters; a policy that
sees only the observation uses the mean parameters of the `DriverConfig` and treats a leader at the
edge of the sensing range as free road.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.sim.drivers import InteractionView, Profile, idm_accel, profile_accel_array
from marlmerge.sim.observation import (
    EGO_FEATURES,
    EGO_SCALE,
    HIGHWAY_FEATURES,
    HIGHWAY_SCALE,
    feature_index,
)

_I = {f.name: feature_index(HIGHWAY_FEATURES, f.name) for f in HIGHWAY_FEATURES}
_E = {f.name: feature_index(EGO_FEATURES, f.name) for f in EGO_FEATURES}


class ScriptedHighwayPolicy:
    """A cooperative, neutral or adversarial mainline driver acting on highway observations."""

    def __init__(self, profile: Profile | int | str, cfg: ScenarioConfig | None = None):
        if isinstance(profile, str):
            try:
                profile = Profile[profile.upper()]
            except KeyError:
                raise ValueError(
                    f"unknown driver profile {profile!r} "
                    f"(known: {[p.name.lower() for p in Profile]})"
                ) from None
        self.profile = Profile(profile)
        self.cfg = cfg or ScenarioConfig()
        d = self.cfg.driver
        self.v0_mps = float(np.mean(d.desired_speed_factor)) * self.cfg.road.speed_limit_mps
        self.headway_s = float(np.mean(d.time_headway_s))

    def __call__(self, obs: np.ndarray, v0_mps: np.ndarray | None = None) -> np.ndarray:
        """obs: [..., 12] scaled highway observation -> [..., 1] acceleration in m/s^2;
        `v0_mps` [...] replaces the profile's desired speed (a learned driver's choice)."""
        raw = np.asarray(obs, dtype=np.float64) * HIGHWAY_SCALE
        cfg = self.cfg
        col = {k: raw[..., i] for k, i in _I.items()}
        sensing = cfg.ego.sensing_range_m
        gap = np.where(col["leader_gap"] >= sensing - 1e-6, np.inf, col["leader_gap"])
        view = InteractionView(
            ego_dx_m=col["ego_dx"],
            ego_v_mps=col["ego_speed"],
            ego_to_overlap_m=col["ego_to_merge"] + cfg.x_overlap_m,
            ego_pending=(col["ego_present"] > 0.5) & (col["ego_in_lane"] < 0.5),
        )
        accel, _ = profile_accel_array(
            np.full(gap.shape, int(self.profile)),
            col["speed"],
            gap,
            col["leader_speed"],
            self.v0_mps if v0_mps is None else v0_mps,
            self.headway_s,
            np.rint(col["lane"]) == 0,
            view,
            cfg.driver,
            cfg.vehicle,
            cfg.road.speed_limit_mps,
        )
        accel = np.clip(accel, -cfg.vehicle.max_brake_mps2, cfg.vehicle.max_accel_mps2)
        return accel[..., None].astype(np.float32)


def constant_speed_action(obs: np.ndarray) -> np.ndarray:
    """The ramp vehicle that simply holds its speed: zero acceleration."""
    return np.zeros(np.asarray(obs).shape[:-1] + (1,), dtype=np.float32)


class IdmEgoPolicy:
    """A ramp vehicle that ignores the merge: free-road IDM on the ramp, IDM behind its gap-front
    vehicle once it is in the right lane. The lower-bound baseline."""

    def __init__(self, cfg: ScenarioConfig | None = None):
        self.cfg = cfg or ScenarioConfig()
        self.headway_s = float(np.mean(self.cfg.driver.time_headway_s))

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """obs: [..., F] scaled ego observation (any layout: it reads the paper's features, the
        first 7) -> [..., 1] acceleration in m/s^2."""
        cfg = self.cfg
        raw = np.asarray(obs, dtype=np.float64)[..., : len(EGO_FEATURES)] * EGO_SCALE
        v, x = raw[..., _E["ego_speed"]], raw[..., _E["ego_position"]]
        x_f, v_f = raw[..., _E["front_position"]], raw[..., _E["front_speed"]]
        seen = x_f - x < cfg.ego.sensing_range_m - 1e-6
        in_lane = joined(obs, cfg)
        gap = np.where(seen & in_lane, x_f - x - cfg.vehicle.length_m, np.inf)
        d = cfg.driver
        accel = idm_accel(
            v,
            gap,
            v_f,
            cfg.road.speed_limit_mps,
            self.headway_s,
            d.accel_mps2,
            d.comfort_brake_mps2,
            d.min_gap_m,
            d.delta,
        )
        lo, hi = cfg.ego.accel_bounds_mps2
        return np.clip(accel, lo, hi)[..., None].astype(np.float32)


def past_overlap(obs: np.ndarray, cfg: ScenarioConfig) -> np.ndarray:
    """[...] whether the ramp vehicle of each observation [..., F] is at or past the overlap
    point, where the paper's ego is joined by force."""
    x_m = np.asarray(obs, dtype=np.float64)[..., _E["ego_position"]] * EGO_SCALE[_E["ego_position"]]
    return x_m >= cfg.x_overlap_m


def joined(obs: np.ndarray, cfg: ScenarioConfig) -> np.ndarray:
    """[...] whether the ramp vehicle of each observation [..., F] is in the right lane: past
    the overlap point, or, when it chooses its join (`ego.join = "chosen"`), as its last
    feature `on_ramp` says."""
    if cfg.ego.chooses_join:
        return np.asarray(obs)[..., -1] < 0.5
    return past_overlap(obs, cfg)


def with_join_at_overlap(
    rule: Callable[[np.ndarray], np.ndarray], cfg: ScenarioConfig
) -> Callable[[np.ndarray], np.ndarray]:
    """A rule that only sets the acceleration ([..., 1]) as a ramp vehicle choosing its join
    (`ego.join = "chosen"`): it joins where the paper's ego is joined by force, once it overlaps
    the right lane (join = +1 from there on, -1 before). Without a join choice: `rule` itself."""
    if not cfg.ego.chooses_join:
        return rule

    def act(obs: np.ndarray) -> np.ndarray:
        accel = np.asarray(rule(obs), dtype=np.float32)
        join = np.where(past_overlap(obs, cfg), 1.0, -1.0).astype(np.float32)
        return np.concatenate([accel, join[..., None]], axis=-1)

    return act
