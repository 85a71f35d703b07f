"""A plausible driver's envelope for learned highway agents (`CoTrainConfig.highway_envelope`).

A learned mainline driver may drive slowly, hang back or speed up into a gap: that is what
adversaries are for. It may not do what no careful driver does: drive so close to its leader
that it could not stop if the leader braked, or brake hard on a road that gives it no reason to.
`SafeEnvelope` limits each acceleration, decided on the observation at the start of an env step
and held for its `sim.action_repeat` simulator steps (tau s), to

    min(a, a_safe, a_fast)     no faster than it could still stop behind its leader, and no
                               faster than the fastest scripted driver wants to drive
    max(that, min(-b, a_safe)) no harder braking than the driver's comfortable b, unless a_safe
                               itself asks for it

where a_safe is the largest acceleration after which, with the leader braking at B from now and
the agent braking at B after tau, the agent still stops a jam gap s0 behind the leader (Gipps'
safe speed, 1981): with R = gap - s0 + v_lead^2 / (2 B) - v tau / 2 (m), the speed at the end of
the step may be at most v1 = B (-tau/2 + sqrt(tau^2/4 + 2 R / B)), so a_safe = (v1 - v) / tau.
B is the agents' braking bound (`sim.highway_agent_accel_bounds_mps2`), b the drivers'
comfortable braking (`driver.comfort_brake_mps2`). With no leader in sensing range
(`ego.sensing_range_m`) it must be able to stop within that range, as if a standing vehicle
were at its edge (150 m: about 35 m/s, 1.2 x the 65 mph limit): a driver racing on a free road
would otherwise arrive faster than it can stop behind the next vehicle it sees.
a_fast = (f v_limit - v) / tau keeps the speed at the end of the step within f times the limit
(as the agent observes it), f the larger of `driver.desired_speed_factor`'s upper end and
`driver.adversarial_speed_factor`. A leader that brakes harder than B (a scripted driver in an
emergency) is outside what the envelope promises.
"""

from __future__ import annotations

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.config.cotraining import HIGHWAY_ENVELOPES as ENVELOPES
from marlmerge.sim.observation import HIGHWAY_FEATURES, HIGHWAY_SCALE, feature_index

_SPEED = feature_index(HIGHWAY_FEATURES, "speed")
_GAP = feature_index(HIGHWAY_FEATURES, "leader_gap")
_V_LEAD = feature_index(HIGHWAY_FEATURES, "leader_speed")
_LIMIT = feature_index(HIGHWAY_FEATURES, "speed_limit")


class SafeEnvelope:
    """(highway observation [..., 12] scaled, acceleration [..., 1] m/s^2) -> the acceleration
    within a plausible driver's envelope, [..., 1] m/s^2 (all-zero, masked-out rows unchanged)."""

    def __init__(self, scenario: ScenarioConfig) -> None:
        self.low, self.high = scenario.sim.highway_agent_accel_bounds_mps2
        self.brake_mps2 = -self.low  # B
        self.comfort_mps2 = scenario.driver.comfort_brake_mps2  # b
        self.tau_s = scenario.sim.action_repeat * scenario.sim.dt_s
        self.s0_m = scenario.driver.min_gap_m
        self.sensing_m = scenario.ego.sensing_range_m
        d = scenario.driver
        self.fastest = max(d.desired_speed_factor[1], d.adversarial_speed_factor)  # f

    def safe_accel(
        self, v_mps: np.ndarray, gap_m: np.ndarray, v_lead_mps: np.ndarray
    ) -> np.ndarray:
        """a_safe [...] m/s^2 (no leader in sensing range: a standing one at its edge)."""
        B, tau = self.brake_mps2, self.tau_s
        free = gap_m >= self.sensing_m - 1e-6
        gap_m, v_lead_mps = np.where(free, self.sensing_m, gap_m), np.where(free, 0.0, v_lead_mps)
        room_m = gap_m - self.s0_m + v_lead_mps**2 / (2.0 * B) - v_mps * tau / 2.0
        v1 = B * (-tau / 2.0 + np.sqrt(tau**2 / 4.0 + 2.0 * np.maximum(room_m, 0.0) / B))
        return (v1 - v_mps) / tau

    def __call__(self, obs: np.ndarray, accel: np.ndarray) -> np.ndarray:
        raw = np.asarray(obs, dtype=np.float64) * HIGHWAY_SCALE  # [..., 12]
        v = raw[..., _SPEED]
        a_safe = self.safe_accel(v, raw[..., _GAP], raw[..., _V_LEAD])[..., None]
        a_fast = ((self.fastest * raw[..., _LIMIT] - v) / self.tau_s)[..., None]
        a = np.minimum(np.minimum(accel, a_safe), a_fast)
        a = np.maximum(a, np.minimum(-self.comfort_mps2, a_safe))
        a = np.clip(a, self.low, self.high)
        present = np.any(raw != 0.0, axis=-1, keepdims=True)
        return np.where(present, a, accel).astype(np.asarray(accel).dtype)


def make_envelope(name: str, scenario: ScenarioConfig) -> SafeEnvelope | None:
    """The envelope `name` of `ENVELOPES` for `scenario` (None: the agent bounds only)."""
    if name not in ENVELOPES:
        raise ValueError(f"unknown highway envelope {name!r} (known: {ENVELOPES})")
    return SafeEnvelope(scenario) if name == "safe" else None
