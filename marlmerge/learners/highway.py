"""Learned highway drivers: a neutral IDM driver plus a learned adjustment (the co-trained
highway group of `marlmerge.training.cotrain`), their snapshots and their policy files."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from marlmerge.config import ScenarioConfig, from_dict, to_dict
from marlmerge.io.policy_file import read_policy, weights_of, write_policy
from marlmerge.learners.ppo import greedy_offset, make_actor_net
from marlmerge.learners.quadq import QuadraticQNet
from marlmerge.policies.envelope import make_envelope
from marlmerge.policies.scripted import ScriptedHighwayPolicy
from marlmerge.sim.observation import HIGHWAY_FEATURES, HIGHWAY_SCALE, feature_index

HighwayPolicy = Callable[[Tensor], Tensor]
"""observation [..., K, 12] -> acceleration [..., K, 1] (m/s^2), greedy."""


OFFSET_BOUNDS_MPS2 = (-3.0, 3.0)
"""Range of the learned adjustment a highway agent adds to its own car-following acceleration."""
BASES = ("idm", "pace")
"""What a residual highway driver adds its adjustment to: a neutral IDM driver's acceleration,
or the pacing driver's (`pacing_accel`)."""
PACE_RANGE_M = 15.0
"""A pacing driver within this distance of the ramp vehicle's projection onto its lane steers to
stay beside it."""
PACE_GAINS = (0.5, 1.0)
"""(1/s^2, 1/s): the pacing driver's acceleration per m of the ramp vehicle ahead of it and per
m/s it is faster."""
COURTESY_SPEED_FACTOR = 0.7
"""A ramp vehicle on the ramp slower than this x the limit is waiting for a gap: the pacing
driver then drives as a neutral IDM driver and lets it find one."""
_COL = {f.name: feature_index(HIGHWAY_FEATURES, f.name) for f in HIGHWAY_FEATURES}


def pacing_accel(raw: np.ndarray, idm_mps2: np.ndarray) -> np.ndarray:
    """The pacing driver's acceleration [..., K] m/s^2 from unscaled highway observations
    [..., K, 12] and the neutral IDM driver's acceleration [..., K]: while the ramp vehicle is
    on the ramp, keep beside it (within `PACE_RANGE_M` of its projection: `PACE_GAINS` on the
    distance and the speed difference) and elsewhere close every gap (IDM + the top of the
    adjustment, as the edge driver), unless it waits for a gap (slower than
    `COURTESY_SPEED_FACTOR` x the limit): then IDM. Plausibility is the envelope's job."""
    c = _COL
    v, v_ramp, limit = raw[..., c["speed"]], raw[..., c["ego_speed"]], raw[..., c["speed_limit"]]
    dx_m = raw[..., c["ego_dx"]]  # the ramp vehicle's position minus own
    on_ramp = (raw[..., c["ego_present"]] > 0.5) & (raw[..., c["ego_in_lane"]] < 0.5)
    beside = on_ramp & (np.abs(dx_m) < PACE_RANGE_M)
    pace_mps2 = PACE_GAINS[0] * dx_m + PACE_GAINS[1] * (v_ramp - v)
    accel = np.where(beside, pace_mps2, idm_mps2 + OFFSET_BOUNDS_MPS2[1])
    return np.where(on_ramp & (v_ramp < COURTESY_SPEED_FACTOR * limit), idm_mps2, accel)


class ResidualHighwayPolicy:
    """A learned highway driver: the acceleration of a neutral IDM driver acting on the same
    observation (`ScriptedHighwayPolicy("neutral")`; `base = "pace"`: of the pacing driver,
    `pacing_accel`) plus a learned adjustment `offset(obs)`,
    clipped to `sim.highway_agent_accel_bounds_mps2` and, with `envelope = "safe"`, limited to
    a plausible driver's envelope (`marlmerge.policies.envelope`). [..., K, 12] -> [..., K, 1]
    m/s^2.

    The quadratic-Q network learns the adjustment (symmetric bounds, so an untrained network
    drives like IDM): learning starts from an ordinary driver and searches for the deviations that
    pay, instead of first having to learn to drive at all.
    """

    def __init__(
        self,
        offset: Callable[[Tensor], Tensor | dict[str, Tensor]],
        scenario: ScenarioConfig,
        envelope: str = "none",
        base: str = "idm",
    ) -> None:
        if base not in BASES:
            raise ValueError(f"unknown highway base {base!r} (one of {BASES})")
        self.offset = offset
        self.idm = ScriptedHighwayPolicy("neutral", scenario)
        self.low, self.high = scenario.sim.highway_agent_accel_bounds_mps2
        self.envelope = make_envelope(envelope, scenario)
        self.pacing = base == "pace"

    def base(self, obs: Tensor) -> Tensor:
        """The IDM part (or the pacing driver's), [..., 1] m/s^2; masked-out, all-zero
        observations get what IDM gives them (never applied)."""
        x = obs.numpy()
        a = np.nan_to_num(self.idm(x), nan=0.0, posinf=0.0, neginf=self.low)  # [..., 1]
        if self.pacing:
            paced = pacing_accel(x.astype(np.float64) * HIGHWAY_SCALE, a[..., 0])[..., None]
            a = np.where(np.any(x != 0, axis=-1, keepdims=True), paced, a).astype(a.dtype)
        return torch.as_tensor(a)

    @torch.no_grad()
    def __call__(self, obs: Tensor) -> Tensor | dict[str, Tensor]:
        """The acceleration [..., K, 1]; when `offset` returns a dict (a learner's `act`: the
        offset as `"action"` and what else it acted with), that dict with the acceleration as
        its `"action"`."""
        offset = self.offset(obs)
        if isinstance(offset, dict):
            return {**offset, "action": self._add(obs, offset["action"])}
        return self._add(obs, offset)

    def _add(self, obs: Tensor, offset: Tensor) -> Tensor:
        accel = (self.base(obs) + offset).clamp(self.low, self.high)
        return within(self.envelope, obs, accel)


def within(envelope: Callable | None, obs: Tensor, accel: Tensor) -> Tensor:
    """`accel` [..., K, 1] limited to `envelope` (None: unchanged)."""
    if envelope is None:
        return accel
    return torch.as_tensor(envelope(obs.numpy(), accel.numpy()))


class DesiredSpeedHighwayPolicy:
    """A learned highway driver that chooses how fast it wants to go: a neutral IDM driver whose
    desired speed is `factor(obs)` x the speed limit ([..., K, 1], the learner's action in
    `CoTrainConfig.highway_speed_factor_bounds`), clipped to
    `sim.highway_agent_accel_bounds_mps2` and limited to `envelope` as `ResidualHighwayPolicy`.
    [..., K, 12] -> [..., K, 1] m/s^2.

    Every acceleration it produces is a car-following driver's: it can drive slowly, speed up
    into a gap or hang back, but never stop dead or brake with a free road ahead. IDM smooths the
    choice over time, so per-step sampling noise explores sustained speeds, not jitter.
    """

    def __init__(
        self,
        factor: Callable[[Tensor], Tensor | dict[str, Tensor]],
        scenario: ScenarioConfig,
        envelope: str = "none",
    ) -> None:
        self.factor = factor
        self.idm = ScriptedHighwayPolicy("neutral", scenario)
        self.limit_mps = scenario.road.speed_limit_mps
        self.low, self.high = scenario.sim.highway_agent_accel_bounds_mps2
        self.envelope = make_envelope(envelope, scenario)

    @torch.no_grad()
    def __call__(self, obs: Tensor) -> Tensor | dict[str, Tensor]:
        """The acceleration [..., K, 1]; when `factor` returns a dict (a learner's `act`), that
        dict with the acceleration as its `"action"`."""
        out = self.factor(obs)
        factor = out["action"] if isinstance(out, dict) else out
        v0 = factor.squeeze(-1).numpy().astype(np.float64) * self.limit_mps  # [..., K] m/s
        a = np.nan_to_num(self.idm(obs.numpy(), v0), nan=0.0, posinf=0.0, neginf=self.low)
        accel = within(self.envelope, obs, torch.as_tensor(a).clamp(self.low, self.high))
        return {**out, "action": accel} if isinstance(out, dict) else accel


def make_driver(
    action: str,
    choice: Callable[[Tensor], Tensor | dict[str, Tensor]],
    scenario: ScenarioConfig,
    envelope: str = "none",
) -> ResidualHighwayPolicy | DesiredSpeedHighwayPolicy:
    """The learned driver of `CoTrainConfig.highway_action` around the learner's `choice`,
    within `CoTrainConfig.highway_envelope`."""
    if action == "desired_speed":
        return DesiredSpeedHighwayPolicy(choice, scenario, envelope)
    if action not in FILE_KINDS:
        raise ValueError(f"unknown highway action {action!r} (one of {tuple(FILE_KINDS)})")
    base = "pace" if action == "pace_offset" else "idm"
    return ResidualHighwayPolicy(choice, scenario, envelope, base)


FILE_KINDS = {"accel_offset": "residual", "desired_speed": "speed", "pace_offset": "pace"}
"""A highway policy file's algorithm is the learner's name, "-", the kind of its action."""


def frozen_net(
    state: dict[str, Tensor], obs_dim: int, hidden: int, bounds: tuple[float, float]
) -> QuadraticQNet:
    net = QuadraticQNet(obs_dim, hidden, action_low=bounds[0], action_high=bounds[1])
    net.load_state_dict(state)
    net.eval()
    return net


def greedy_adjustment(
    algorithm: str, state: dict[str, Tensor], hidden: int, bounds: tuple[float, float]
) -> Callable[[Tensor], Tensor]:
    """The greedy learned adjustment obs [..., 12] -> [..., 1] m/s^2 in `bounds`, from the
    weights of a "quadq" (quadratic-Q network) or "ppo" (PPO actor) highway learner."""
    if algorithm == "quadq":
        return frozen_net(state, len(HIGHWAY_FEATURES), hidden, bounds).greedy
    if algorithm != "ppo":
        raise ValueError(f"unknown highway algorithm {algorithm!r} (one of 'quadq', 'ppo')")
    net = make_actor_net(len(HIGHWAY_FEATURES), hidden, 1.0)
    net.load_state_dict(state)
    net.eval()
    return torch.no_grad()(lambda obs: greedy_offset(net, obs, *bounds))


def snapshot_policy(
    state: dict[str, Tensor],
    hidden: int,
    scen: ScenarioConfig,
    bounds: tuple[float, float] = OFFSET_BOUNDS_MPS2,
    algorithm: str = "quadq",
    action: str = "accel_offset",
    envelope: str = "none",
) -> HighwayPolicy:
    """The greedy highway policy of a pool snapshot: weights of the learned choice (of
    `algorithm`'s network: an adjustment in m/s^2 or a desired-speed factor, per `action`),
    squashed into `bounds`, within `envelope`."""
    choice = greedy_adjustment(algorithm, state, hidden, bounds)
    return make_driver(action, choice, scen, envelope)


def save_highway_policy(
    path: Path,
    state: dict[str, Tensor],
    cfg: Any,
    scen: ScenarioConfig,
    bounds: tuple[float, float] = OFFSET_BOUNDS_MPS2,
) -> None:
    """A highway group's policy: the network's weights and the `bounds` its greedy action is
    squashed into (stored, so the file reloads as it was trained); the file's algorithm is
    `cfg.highway_algorithm` + "-residual" (an adjustment) or "-speed" (a desired speed); its
    envelope (`cfg.highway_envelope`) is stored too, so the driver reloads within it."""
    state = {"net": state, "hidden": cfg.hidden, "profile": cfg.profile}
    if getattr(cfg, "highway_envelope", "none") != "none":  # files without one: "none"
        state["envelope"] = cfg.highway_envelope
    kind = FILE_KINDS[getattr(cfg, "highway_action", "accel_offset")]
    algorithm = f"{getattr(cfg, 'highway_algorithm', 'quadq')}-{kind}"
    write_policy(path, "highway", algorithm, bounds, state, to_dict(cfg), to_dict(scen))


EDGE_DRIVER = "edge"
"""The name, in place of a run folder, of the scripted driver at a plausible envelope's edge."""


def edge_driver(scenario: ScenarioConfig) -> ResidualHighwayPolicy:
    """The scripted driver at the edge of the plausible envelope (`highway_envelope = "safe"`):
    it always asks for IDM + 3 m/s^2 (the top of a learned adjustment), so it drives as fast as
    it safely can, up to the fastest scripted driver's speed, closing every gap it may. What
    learned adversaries within the envelope converge to (docs/cotraining.md); no learning, so it
    is the same on every machine."""
    high = OFFSET_BOUNDS_MPS2[1]
    return ResidualHighwayPolicy(
        lambda obs: torch.full((*obs.shape[:-1], 1), high), scenario, "safe"
    )


PACE_DRIVER = "pace"
"""The name, in place of a run folder, of the scripted pacing driver."""


def pace_driver(scenario: ScenarioConfig) -> ResidualHighwayPolicy:
    """The scripted pacing driver within the plausible envelope: it keeps beside the ramp vehicle
    while that is on the ramp, so that the place it would merge into stays taken, closes every
    other gap as the edge driver does, and lets a ramp vehicle that waits for a gap find one
    (`pacing_accel`). No learning: the same on every machine (docs/cotraining.md)."""
    return ResidualHighwayPolicy(
        lambda obs: torch.zeros((*obs.shape[:-1], 1)), scenario, "safe", base="pace"
    )


SCRIPTED_DRIVERS = {EDGE_DRIVER: edge_driver, PACE_DRIVER: pace_driver}
"""The scripted highway drivers a `--highway` / `+highway:` may name in place of a run."""
SCRIPTED_LABELS = {EDGE_DRIVER: "edge drivers", PACE_DRIVER: "pacing drivers"}
"""How a grid condition with a scripted driver of `SCRIPTED_DRIVERS` names it."""


def load_highway_policy(path: str | Path, scenario: ScenarioConfig | None = None) -> HighwayPolicy:
    """The greedy shared policy of a saved highway group (`highway_policy.pt` or its folder),
    or, for a name of `SCRIPTED_DRIVERS`, that driver on `scenario` (the one it drives in)."""
    if str(path) in SCRIPTED_DRIVERS:
        if scenario is None:
            raise ValueError(f"highway policy {str(path)!r} needs the scenario it drives in")
        return SCRIPTED_DRIVERS[str(path)](scenario)
    saved = read_policy(path, "highway")
    scen = from_dict(ScenarioConfig, saved["scenario"])
    low, high = saved["action_bounds_mps2"]
    state = saved["policy_state"]
    algorithm, kind = saved["algorithm"].split("-")
    action = {k: a for a, k in FILE_KINDS.items()}[kind]
    envelope = state.get("envelope", "none")
    with weights_of(path):
        return snapshot_policy(
            state["net"], state["hidden"], scen, (low, high), algorithm, action, envelope
        )
