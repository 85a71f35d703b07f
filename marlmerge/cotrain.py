"""Co-training of learned highway agents and the ego: alternating phases on `MultiAgentMergeEnv`.

Two agent groups learn with the paper's quadratic-Q learner, each with its own network, loss
(`QuadraticQLoss`), optimiser and target (`FastQuadQUpdater`), torchrl `ReplayBuffer` and seeded
generators (`GroupLearner`):

- `"ego"`: the ramp vehicle (observation [B, 7], acceleration in the ego bounds);
- `"highway"`: one policy shared by the K highway agents of every world (observation [B, K, 12],
  acceleration in the vehicle limits); only agents that act (mask) give transitions, an agent that
  leaves the road ends its own episode (terminal), the end of the merge truncates it.

The schedule (`CoTrainConfig.phases()`), one torchrl `Collector` per phase:

    pretrain   the ego learns against scripted traffic (skipped when `ego_init` names a policy)
    adversary  the highway group learns against the frozen greedy ego; every world's K agents are
               the learning policy (with exploration noise). At the end its weights join the pool.
    ego        the ego learns against frozen opponents: each ego meets scripted traffic with
               probability `scripted_fraction`, else a snapshot drawn uniformly from the pool,
               so it does not forget ordinary traffic.
    (adversary, ego) x rounds

The highway reward is its own driving reward plus the interaction term of `InteractionConfig`
(`profile = "adversarial"`: +, `"cooperative"`: -). Everything is checkpointed (both groups'
weights, targets, optimisers and replays, the pool, the worlds and every generator) at
`checkpoint_every_sim_steps` and at every phase end; `resume=True` continues from there.

The quadratic-Q ego does not improve monotonically from phase to phase (one ego phase can leave
it weaker against some opponents than the one before). At the end every ego of the run (the
starting ego and the ego after each ego phase) is scored on greedy episodes against scripted
traffic and against every snapshot of the run's own pool (`select_episodes`), and the one with the
fewest failures becomes `policy.pt`: model selection on the training opponents, never on held-out
ones.

Outputs in the run folder: `policy.pt` (the selected ego, loadable by `load_policy` and the grid),
`policy_last.pt` (the ego at the end of the schedule), `policy_pretrained.pt` (the ego before any
co-training, when pretrained here), `highway_policy.pt` (the latest highway policy;
`load_highway_policy`), `pool/adversary_<i>.pt`, `pool/ego_start.pt` and `pool/ego_<i>.pt`
(the ego at the start and after each ego phase), `egos.csv`, `highway.csv`, `loss.csv`,
`checkpoint.pt`, `evaluation.json` (the selection's scores, then the selected ego against
scripted traffic and the latest highway policy).
"""

from __future__ import annotations

import functools
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from tensordict import TensorDictBase
from torch import Tensor
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer

from marlmerge import files
from marlmerge.config import ScenarioConfig, check_values, from_dict, to_dict
from marlmerge.learners.quadq import (
    PAPER_GAMMA,
    FastQuadQUpdater,
    GaussianExploration,
    QuadraticQLoss,
    QuadraticQNet,
    noisy_greedy_action,
)
from marlmerge.marl_env import GROUP, MultiAgentMergeEnv
from marlmerge.policies import ScriptedHighwayPolicy
from marlmerge.policy_file import read_policy, write_policy
from marlmerge.sim import OUTCOME_NAMES
from marlmerge.spec.observation import EGO_FEATURES, HIGHWAY_FEATURES
from marlmerge.spec.reward import INTERACTION_TERMS, LEARNED_HIGHWAY_TERMS
from marlmerge.train import (
    CsvLog,
    _progress,
    load_preset,
    save_checkpoint,
)

PROFILES = {"adversarial": 1.0, "cooperative": -1.0}
PHASES = ("pretrain", "adversary", "ego")


COTRAIN_RULES = {
    **dict.fromkeys(
        [
            "num_worlds", "env_steps_per_batch", "pool_size", "batch_size",
            "target_update_period", "hidden", "replay_capacity", "updates_per_call", "threads",
            "loss_log_every", "checkpoint_every_sim_steps", "eval_worlds",
        ],
        ">=1",
    ),
    **dict.fromkeys(
        [
            "seed", "ego_pretrain_sim_steps", "rounds", "adversary_sim_steps", "ego_sim_steps",
            "learning_starts", "ego_updates_per_sim_step", "highway_updates_per_sim_step",
            "ego_sigma_start", "ego_sigma_end", "ego_sigma_cotrain", "highway_sigma_start",
            "highway_sigma_end", "eval_episodes", "eval_seed", "select_episodes", "select_seed",
        ],
        ">=0",
    ),
    "lr": ">0",
    "scripted_fraction": "[0,1]",
}  # fmt: skip
"""Signs and ranges of the co-training numbers (`marlmerge.config.check_values`)."""


@dataclass(frozen=True)
class CoTrainConfig:
    """One co-training run. Learner settings follow the paper's recipe for both groups."""

    KIND: ClassVar[str] = "cotrain"
    """The `kind` a preset of this schema names."""

    name: str = "cotrain"
    """Run name; outputs go to `runs/<name>` unless `--out` says otherwise."""
    scenario: str = "default"
    """Scenario preset in `envs/` (or a path): the background traffic of every phase."""
    seed: int = 0
    """Seeds traffic, both networks, exploration noise, replay sampling and the opponent draws."""
    profile: str = "adversarial"
    """"adversarial" or "cooperative": the sign of the highway agents' interaction term."""
    num_worlds: int = 32
    env_steps_per_batch: int = 4
    ego_init: str = ""
    """A trained quadratic-Q ego (`policy.pt` or run folder) to start from; "" = pretrain here."""
    ego_pretrain_sim_steps: int = 1_600_000
    """Pretrain phase (skipped with `ego_init`): the paper's recipe against scripted traffic."""
    rounds: int = 5
    """(adversary, ego) phase pairs after pretraining."""
    adversary_sim_steps: int = 400_000
    """Simulator steps (summed over worlds) of each adversary phase; 0 skips them."""
    ego_sim_steps: int = 400_000
    """Simulator steps of each ego phase; 0 skips them (e.g. adversaries for a fixed ego)."""
    scripted_fraction: float = 0.5
    """Ego phases: share of egos that meet scripted traffic rather than a pool snapshot."""
    pool_size: int = 10
    """Adversary snapshots kept (oldest dropped first)."""
    gamma: float = PAPER_GAMMA
    lr: float = 1.0e-3
    batch_size: int = 32
    target_update_period: int = 500
    hidden: int = 64
    replay_capacity: int = 200_000
    learning_starts: int = 1_000
    ego_updates_per_sim_step: float = 1.0
    """Ego updates per simulator step of ego experience (paper: 1)."""
    highway_updates_per_sim_step: float = 0.5
    """Highway updates per simulator step of world experience (each step holds up to K agent
    transitions, so ~0.5 updates per stored agent transition)."""
    ego_sigma_start: float = 1.0
    ego_sigma_end: float = 0.1
    """Pretrain exploration, decaying linearly over the first half of the phase (paper)."""
    ego_sigma_cotrain: float = 0.2
    """Exploration noise of the ego in the ego phases (constant), m/s^2."""
    highway_sigma_start: float = 0.8
    highway_sigma_end: float = 0.1
    """Adversary phases: exploration noise decaying linearly over each phase's first half."""
    update_path: str = "compiled"
    """"compiled" (torch.compile of the fast update) or "fast" (the same, eager)."""
    updates_per_call: int = 10
    threads: int = 1
    loss_log_every: int = 50
    checkpoint_every_sim_steps: int = 400_000
    eval_episodes: int = 200
    """After training: the final ego on this many held-out episodes, against scripted traffic
    and against the latest highway policy ..."""
    eval_seed: int = 1_000_000
    eval_worlds: int = 50
    select_episodes: int = 200
    """After training, every ego of the run (the starting ego and the ego after each ego phase)
    meets scripted traffic and each of the run's own pool snapshots for this many greedy
    episodes; `policy.pt` is the ego with the fewest failures (collisions + truncations), the
    latest on ties. 0 keeps the last ego. The run's own adversaries only: held-out adversaries
    never take part."""
    select_seed: int = 3_000_000
    """First seed of the selection episodes (apart from `eval_seed` and the grid's seeds)."""

    def __post_init__(self) -> None:
        check_values(self, COTRAIN_RULES)
        checks = [
            (
                self.replay_capacity >= self.batch_size,
                f"replay_capacity ({self.replay_capacity}) must be >= batch_size "
                f"({self.batch_size})",
            ),
            (
                self.profile in PROFILES,
                f"profile must be one of {tuple(PROFILES)}, got {self.profile!r}",
            ),
            (self.update_path in ("compiled", "fast"), "update_path must be 'compiled' or 'fast'"),
            (0.0 < self.gamma < 1.0, f"gamma must lie in (0, 1), got {self.gamma}"),
            (
                self.target_update_period % self.updates_per_call == 0,
                "updates_per_call must divide target_update_period",
            ),
        ]
        for ok, msg in checks:
            if not ok:
                raise ValueError(msg)
        if not self.phases():
            raise ValueError("the schedule is empty: every phase has 0 simulator steps")
        if not self.ego_init and self.ego_pretrain_sim_steps == 0 and self.adversary_sim_steps:
            raise ValueError("adversaries need a trained ego: set ego_init or pretrain")

    def phases(self) -> list[tuple[str, int]]:
        """The schedule: (phase kind, simulator steps) in order."""
        out: list[tuple[str, int]] = []
        if not self.ego_init and self.ego_pretrain_sim_steps > 0:
            out.append(("pretrain", self.ego_pretrain_sim_steps))
        for _ in range(self.rounds):
            if self.adversary_sim_steps > 0:
                out.append(("adversary", self.adversary_sim_steps))
            if self.ego_sim_steps > 0:
                out.append(("ego", self.ego_sim_steps))
        return out


def load_cotrain_config(path: str | Path, **overrides: Any) -> CoTrainConfig:
    """A co-training preset (TOML in `trainers/` or a path), loaded strictly, with overrides."""
    return load_preset(CoTrainConfig, path, **overrides)


# ----------------------------------------------------------------------------------------------
# One learning group
# ----------------------------------------------------------------------------------------------


@dataclass
class PhaseNoise:
    """Exploration std (m/s^2) falling linearly from `start` to `end` over `decay_steps`
    simulator steps of the current phase (`step`, set by the loop), then constant."""

    start: float
    end: float
    decay_steps: int
    step: int = 0

    def sigma(self) -> float:
        return GaussianExploration(self.start, self.end, max(self.decay_steps, 1)).sigma(self.step)


class GroupLearner:
    """Network, loss, optimiser + target (fast path), replay and generators of one agent group."""

    def __init__(
        self,
        cfg: CoTrainConfig,
        obs_dim: int,
        bounds: tuple[float, float],
        seed: int,
        init_state: dict[str, Tensor] | None = None,
    ) -> None:
        self.obs_dim = obs_dim
        self.low, self.high = bounds
        self.net = QuadraticQNet(
            obs_dim,
            cfg.hidden,
            action_low=self.low,
            action_high=self.high,
            generator=torch.Generator().manual_seed(seed),
        )
        if init_state is not None:
            self.net.load_state_dict(init_state)
        self.loss = QuadraticQLoss(self.net, gamma=cfg.gamma)
        self.noise_gen = torch.Generator().manual_seed(seed + 1)
        self.sample_gen = torch.Generator().manual_seed(seed + 2)
        self.replay = ReplayBuffer(
            storage=LazyTensorStorage(cfg.replay_capacity), generator=self.sample_gen
        )
        self.cfg = cfg
        self.updater: FastQuadQUpdater | None = None
        self.experience_sim_steps = 0  # simulator steps of experience this group learned from
        self.updates = 0

    def start_updates(self) -> None:
        """Alias the weights into the fast path (after any weights were loaded)."""
        if self.updater is None:
            cfg = self.cfg
            self.updater = FastQuadQUpdater(
                self.loss,
                None,
                generator=self.sample_gen,
                lr=cfg.lr,
                batch_size=cfg.batch_size,
                updates_per_call=cfg.updates_per_call,
                target_update_period=cfg.target_update_period,
                compile=cfg.update_path == "compiled",
            )

    @torch.no_grad()
    def act(self, obs: Tensor, noise: PhaseNoise) -> Tensor:
        """obs [..., d] -> greedy action plus N(0, sigma^2) noise, clipped, [..., 1]."""
        greedy = self.net.greedy(obs)
        sigma = noise.sigma()
        if sigma <= 0.0:
            return greedy
        return noisy_greedy_action(greedy, sigma, self.noise_gen, low=self.low, high=self.high)

    def store(self, rows: Tensor, sim_steps: int) -> None:
        if rows.shape[0]:
            self.replay.extend(rows)
        self.experience_sim_steps += sim_steps

    def update(self, rate: float) -> list[tuple[int, float]]:
        """Run the updates owed to the experience so far; returns (update index, loss) pairs."""
        owed = int(self.experience_sim_steps * rate) - self.updates
        cfg = self.cfg
        if len(self.replay) < cfg.learning_starts:
            self.updates += max(owed, 0)  # skipped: too little data yet
            return []
        self.start_updates()
        assert self.updater is not None
        k = self.updater.k
        out = []
        for _ in range(max(owed, 0) // k):
            mb = self.replay.sample(k * cfg.batch_size).view(k, cfg.batch_size, -1)
            losses = self.updater.step(mb)
            out.append((self.updates + k, float(losses[-1])))
            self.updates += k
        return out

    def snapshot(self) -> dict[str, Tensor]:
        return {k: v.detach().clone() for k, v in self.net.state_dict().items()}

    def state_dict(self) -> dict[str, Any]:
        return {
            "loss": self.loss.state_dict(),
            "optimizer": None if self.updater is None else self.updater.state_dict(),
            "replay": self.replay.state_dict(),
            "noise_gen": self.noise_gen.get_state(),
            "sample_gen": self.sample_gen.get_state(),
            "experience_sim_steps": self.experience_sim_steps,
            "updates": self.updates,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore; call before `start_updates` (the fast path aliases the loaded weights)."""
        self.loss.load_state_dict(state["loss"])
        if state["optimizer"] is not None:
            self.start_updates()
            assert self.updater is not None
            self.updater.load_state_dict(state["optimizer"])
        self.replay.load_state_dict(state["replay"])
        self.noise_gen.set_state(state["noise_gen"])
        self.sample_gen.set_state(state["sample_gen"])
        self.experience_sim_steps = state["experience_sim_steps"]
        self.updates = state["updates"]


OFFSET_BOUNDS_MPS2 = (-3.0, 3.0)
"""Range of the learned adjustment a highway agent adds to its own car-following acceleration."""


class ResidualHighwayPolicy:
    """A learned highway driver: the acceleration of a neutral IDM driver acting on the same
    observation (`ScriptedHighwayPolicy("neutral")`) plus a learned adjustment `offset(obs)`,
    clipped to `sim.highway_agent_accel_bounds_mps2`. [..., K, 12] -> [..., K, 1] m/s^2.

    The quadratic-Q network learns the adjustment (symmetric bounds, so an untrained network
    drives like IDM): learning starts from an ordinary driver and searches for the deviations that
    pay, instead of first having to learn to drive at all.
    """

    def __init__(self, offset: Callable[[Tensor], Tensor], scenario: ScenarioConfig) -> None:
        self.offset = offset
        self.idm = ScriptedHighwayPolicy("neutral", scenario)
        self.low, self.high = scenario.sim.highway_agent_accel_bounds_mps2

    def base(self, obs: Tensor) -> Tensor:
        """The IDM part, [..., 1] m/s^2 (0 for masked-out, all-zero observations)."""
        a = self.idm(obs.numpy())
        return torch.as_tensor(np.nan_to_num(a, nan=0.0, posinf=0.0, neginf=self.low))

    @torch.no_grad()
    def __call__(self, obs: Tensor) -> Tensor:
        return (self.base(obs) + self.offset(obs)).clamp(self.low, self.high)


def frozen_net(
    state: dict[str, Tensor], obs_dim: int, hidden: int, bounds: tuple[float, float]
) -> QuadraticQNet:
    net = QuadraticQNet(obs_dim, hidden, action_low=bounds[0], action_high=bounds[1])
    net.load_state_dict(state)
    net.eval()
    return net


def snapshot_policy(
    state: dict[str, Tensor],
    hidden: int,
    scen: ScenarioConfig,
    bounds: tuple[float, float] = OFFSET_BOUNDS_MPS2,
) -> HighwayPolicy:
    """The greedy highway policy of a pool snapshot: weights of the learned adjustment, whose
    network squashes its greedy action into `bounds` (m/s^2)."""
    net = frozen_net(state, len(HIGHWAY_FEATURES), hidden, bounds)
    return ResidualHighwayPolicy(net.greedy, scen)


# ----------------------------------------------------------------------------------------------
# Collector policy: both groups at once
# ----------------------------------------------------------------------------------------------


class JointPolicy:
    """Sets the ego's `"action"` and the highway group's `("highway", "action")`.

    ego(obs [B, 7]) -> [B, 1]; highway[o](obs [n, K, 12]) -> [n, K, 1] for the worlds whose
    `"opponent"` is o (worlds with -1 are scripted: their actions are ignored, zeros are sent).
    """

    def __init__(
        self, ego: Callable[[Tensor], Tensor], highway: list[Callable[[Tensor], Tensor]]
    ) -> None:
        self.ego = ego
        self.highway = highway

    @torch.no_grad()
    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        td.set("action", self.ego(td.get("observation")))
        obs = td.get((GROUP, "observation"))  # [B, K, 12]
        opp = td.get("opponent").reshape(-1)  # [B]
        act = torch.zeros(*obs.shape[:-1], 1)
        for o in torch.unique(opp).tolist():
            if o >= 0:
                sel = opp == o
                act[sel] = self.highway[o](obs[sel])
        td.set((GROUP, "action"), act)
        return td


# ----------------------------------------------------------------------------------------------
# Saving and loading policies
# ----------------------------------------------------------------------------------------------


def save_ego_policy(path: Path, net: QuadraticQNet, cfg: CoTrainConfig, scen: ScenarioConfig):
    """The ego in the `policy.pt` format of `train.py` (readable by `load_policy`, the grid)."""
    write_policy(
        path,
        "ego",
        "quadq",
        (net.action_low, net.action_high),
        {"net": net.state_dict(), "hidden": cfg.hidden},
        to_dict(cfg),
        to_dict(scen),
    )


def save_highway_policy(
    path: Path,
    state: dict[str, Tensor],
    cfg: CoTrainConfig,
    scen: ScenarioConfig,
    bounds: tuple[float, float] = OFFSET_BOUNDS_MPS2,
) -> None:
    """A highway group's policy: the adjustment network's weights and the `bounds` its greedy
    action is squashed into (stored, so the file reloads as it was trained)."""
    state = {"net": state, "hidden": cfg.hidden, "profile": cfg.profile}
    write_policy(path, "highway", "quadq-residual", bounds, state, to_dict(cfg), to_dict(scen))


HighwayPolicy = Callable[[Tensor], Tensor]
"""observation [..., K, 12] -> acceleration [..., K, 1] (m/s^2), greedy."""


def load_highway_policy(path: str | Path) -> HighwayPolicy:
    """The greedy shared policy of a saved highway group (`highway_policy.pt` or its folder)."""
    saved = read_policy(path, "highway")
    scen = from_dict(ScenarioConfig, saved["scenario"])
    low, high = saved["action_bounds_mps2"]
    state = saved["policy_state"]
    return snapshot_policy(state["net"], state["hidden"], scen, (low, high))


# ----------------------------------------------------------------------------------------------
# The loop
# ----------------------------------------------------------------------------------------------

EGO_LOG_FIELDS = (
    "ego",
    "phase_index",
    "phase",
    "sim_step",
    "world",
    "opponent",
    "outcome",
    "time_s",
    "total_reward",
)
HIGHWAY_LOG_FIELDS = (
    "phase_index",
    "phase",
    "sim_step",
    "agent_steps",
    "reward_per_agent_step",
    *(f"{t}_sum" for t in LEARNED_HIGHWAY_TERMS),
    "background_collisions",
)
LOSS_LOG_FIELDS = ("group", "update", "sim_step", "loss")


@dataclass
class CoTrainResult:
    out_dir: Path
    sim_steps: int
    egos: int
    wall_s: float
    pool_size: int
    evaluation: dict[str, Any] | None


def cotrain(
    cfg: CoTrainConfig,
    out_dir: str | Path,
    resume: bool = False,
    progress: bool = True,
    stop_after_sim_steps: int | None = None,
) -> CoTrainResult:
    """Run (or resume) the co-training schedule of `cfg`; see the module docstring.

    `stop_after_sim_steps` ends the run abruptly at that total step count, as a kill would.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "pool").mkdir(exist_ok=True)
    ckpt_path = out / "checkpoint.pt"
    ckpt = None
    if resume:
        if not ckpt_path.exists():
            raise ValueError(f"--resume: no checkpoint at {ckpt_path}")
        ckpt = files.load(ckpt_path, "checkpoint")
        cfg = from_dict(CoTrainConfig, ckpt["config"])  # a resumed run continues that run
    (out / "config.json").write_text(json.dumps(to_dict(cfg), indent=1))
    torch.set_num_threads(cfg.threads)

    env = MultiAgentMergeEnv(
        cfg.scenario,
        num_worlds=cfg.num_worlds,
        seed=cfg.seed,
        overrides={"interaction.sign": PROFILES[cfg.profile]},
    )
    scen = env.cfg
    k_rep = scen.sim.action_repeat
    ego_bounds = scen.ego.accel_bounds_mps2
    hw_bounds = OFFSET_BOUNDS_MPS2  # the highway network learns an adjustment to IDM
    ego_init = None
    if cfg.ego_init:
        saved = read_policy(cfg.ego_init, "ego")
        if saved["algorithm"] != "quadq":
            raise ValueError(f"ego_init {cfg.ego_init!r} is not a quadratic-Q policy")
        hidden = saved["policy_state"]["hidden"]
        if hidden != cfg.hidden:
            raise ValueError(f"ego_init {cfg.ego_init!r} has hidden={hidden}, not {cfg.hidden}")
        if tuple(saved["action_bounds_mps2"]) != tuple(ego_bounds):
            raise ValueError(
                f"ego_init {cfg.ego_init!r} acts in {saved['action_bounds_mps2']} m/s^2, the "
                f"scenario's ego in {ego_bounds}"
            )
        ego_init = saved["policy_state"]["net"]
    ego = GroupLearner(cfg, len(EGO_FEATURES), ego_bounds, cfg.seed * 1000 + 10, ego_init)
    hw = GroupLearner(cfg, len(HIGHWAY_FEATURES), hw_bounds, cfg.seed * 1000 + 20)
    pool: list[dict[str, Tensor]] = []
    egos_kept: list[tuple[int, dict[str, Tensor]]] = []  # (phase index, weights): candidates
    phases = cfg.phases()
    phase_index, phase_done, total = 0, 0, 0
    egos = 0
    if ckpt is not None:
        ego.load_state_dict(ckpt["ego"])
        hw.load_state_dict(ckpt["highway"])
        pool = ckpt["pool"]
        egos_kept = ckpt.get("egos_kept", [])  # absent in checkpoints of older versions
        phase_index, phase_done, total = ckpt["phase_index"], ckpt["phase_done"], ckpt["total"]
        egos = ckpt["egos"]
        env.load_sim_state(ckpt["env"])

    ego_log = CsvLog(out / "egos.csv", EGO_LOG_FIELDS, ckpt["ego_rows"] if ckpt else None)
    hw_log = CsvLog(out / "highway.csv", HIGHWAY_LOG_FIELDS, ckpt["hw_rows"] if ckpt else None)
    loss_log = CsvLog(out / "loss.csv", LOSS_LOG_FIELDS, ckpt["loss_rows"] if ckpt else None)
    grand_total = sum(n for _, n in phases)
    bar = _progress(grand_total, total, progress)
    t0 = time.perf_counter()
    ep_sum = np.zeros(cfg.num_worlds)  # [B] running ego reward of the current egos
    ep_steps = np.zeros(cfg.num_worlds, dtype=np.int64)
    if ckpt is not None:
        ep_sum[:] = ckpt["ep_sum"]
        ep_steps[:] = ckpt["ep_steps"]
    next_ckpt = (total // cfg.checkpoint_every_sim_steps + 1) * cfg.checkpoint_every_sim_steps

    def checkpoint() -> None:
        for log in (ego_log, hw_log, loss_log):
            log.flush()
        save_checkpoint(
            ckpt_path,
            {
                "config": to_dict(cfg),
                "ego": ego.state_dict(),
                "highway": hw.state_dict(),
                "pool": pool,
                "egos_kept": egos_kept,
                "phase_index": phase_index,
                "phase_done": phase_done,
                "total": total,
                "egos": egos,
                "env": env.sim_state(),
                "ep_sum": ep_sum.copy(),
                "ep_steps": ep_steps.copy(),
                "ego_rows": ego_log.rows,
                "hw_rows": hw_log.rows,
                "loss_rows": loss_log.rows,
            },
        )

    def keep_ego(index: int) -> None:
        egos_kept.append((index, ego.snapshot()))
        name = f"ego_{index}.pt" if index >= 0 else "ego_start.pt"
        save_ego_policy(out / "pool" / name, ego.net, cfg, scen)

    if ego_init is not None and ckpt is None:
        keep_ego(-1)  # the starting ego is a candidate too
    killed = False
    while phase_index < len(phases) and not killed:
        kind, length = phases[phase_index]
        resumed_mid_phase = ckpt is not None and phase_done > 0
        ego_noise = PhaseNoise(0.0, 0.0, 1)  # frozen groups act greedily
        hw_noise = PhaseNoise(0.0, 0.0, 1)
        ego_noise.step = hw_noise.step = phase_done
        opponents: list[Callable[[Tensor], Tensor]] = []
        if kind == "adversary":
            env.set_opponent_mix(1, 0.0)
            hw_noise = PhaseNoise(cfg.highway_sigma_start, cfg.highway_sigma_end, length // 2)
            opponents = [ResidualHighwayPolicy(functools.partial(hw.act, noise=hw_noise), scen)]
        elif kind == "pretrain":
            env.set_opponent_mix(0, 1.0)
            ego_noise = PhaseNoise(cfg.ego_sigma_start, cfg.ego_sigma_end, length // 2)
        else:
            env.set_opponent_mix(len(pool), cfg.scripted_fraction if pool else 1.0)
            ego_noise = PhaseNoise(cfg.ego_sigma_cotrain, cfg.ego_sigma_cotrain, 1)
            opponents = [snapshot_policy(s, cfg.hidden, scen) for s in pool]
        ego_noise.step = hw_noise.step = phase_done
        policy = JointPolicy(functools.partial(ego.act, noise=ego_noise), opponents)
        if resumed_mid_phase:
            env.resume_without_reset()
        frames_per_batch = cfg.num_worlds * cfg.env_steps_per_batch
        remaining = math.ceil((length - phase_done) / k_rep)
        remaining = max(
            frames_per_batch, math.ceil(remaining / frames_per_batch) * frames_per_batch
        )
        collector = Collector(
            env,
            policy,
            frames_per_batch=frames_per_batch,
            total_frames=remaining,
            auto_register_policy_transforms=False,
        )
        if resumed_mid_phase:  # the collector ran the policy once while setting up
            ego.noise_gen.set_state(ckpt["ego"]["noise_gen"])
            hw.noise_gen.set_state(ckpt["highway"]["noise_gen"])
        ckpt = None
        bg_before = env.core.state.background_collisions.sum()
        for batch in collector:
            n_sim = batch.numel() * k_rep
            phase_done += n_sim
            total += n_sim
            ego_noise.step = hw_noise.step = phase_done
            nxt = batch.get("next")
            if kind in ("pretrain", "ego"):
                flat = batch.reshape(-1)
                fn = flat.get("next")
                rows = torch.cat(
                    [
                        flat.get("observation"),
                        flat.get("action"),
                        fn.get("reward"),
                        fn.get("terminated").float(),
                        fn.get("observation"),
                    ],
                    -1,
                )
                ego.store(rows, n_sim)
                for upd, loss in ego.update(cfg.ego_updates_per_sim_step):
                    if upd % cfg.loss_log_every < cfg.updates_per_call:
                        loss_log.write(["ego", upd, total, loss])
            valid = batch.get((GROUP, "mask")) & (batch.get("opponent") >= 0)  # [B, T, K]
            hw_reward = nxt.get((GROUP, "reward")).squeeze(-1)  # [B, T, K]
            if kind == "adversary":
                # leaving downstream is no outcome: drop it (an absorbing 0 would pay agents to
                # race off the road); a collision is terminal, with its penalty
                keep = valid & ~nxt.get((GROUP, "exited"))
                obs_kept = batch.get((GROUP, "observation"))[keep]
                offset = batch.get((GROUP, "action"))[keep] - opponents[0].base(obs_kept)
                rows = torch.cat(
                    [
                        obs_kept,
                        offset,  # the adjustment applied (after clipping), what the net learns
                        nxt.get((GROUP, "reward"))[keep],
                        nxt.get((GROUP, "left_road"))[keep].float().unsqueeze(-1),
                        nxt.get((GROUP, "observation"))[keep],
                    ],
                    -1,
                )
                hw.store(rows, n_sim)
                for upd, loss in hw.update(cfg.highway_updates_per_sim_step):
                    if upd % cfg.loss_log_every < cfg.updates_per_call:
                        loss_log.write([GROUP, upd, total, loss])
            terms = nxt.get((GROUP, "reward_terms"))
            n_valid = int(valid.sum())
            bg_now = env.core.state.background_collisions.sum()
            hw_log.write(
                [
                    phase_index,
                    kind,
                    total,
                    n_valid,
                    float(hw_reward[valid].mean()) if n_valid else 0.0,
                    *(float(terms.get(t).squeeze(-1)[valid].sum()) for t in LEARNED_HIGHWAY_TERMS),
                    int(bg_now - bg_before),
                ]
            )
            bg_before = bg_now
            # ---- ego log
            rew = nxt.get("reward").reshape(batch.batch_size).numpy()  # [B, T]
            done = nxt.get("done").reshape(batch.batch_size).numpy()
            outcome = nxt.get("outcome").reshape(batch.batch_size).numpy()
            opp = batch.get("opponent").reshape(batch.batch_size).numpy()
            b, t_len = batch.batch_size
            for t in range(t_len):
                ep_sum += rew[:, t]
                ep_steps += 1
                for w in np.flatnonzero(done[:, t]):
                    ego_log.write(
                        [
                            egos,
                            phase_index,
                            kind,
                            total - (t_len - 1 - t) * b * k_rep,
                            int(w),
                            int(opp[w, t]),
                            OUTCOME_NAMES[int(outcome[w, t])],
                            round(float(ep_steps[w] * k_rep * scen.sim.dt_s), 3),
                            float(ep_sum[w]),
                        ]
                    )
                    egos += 1
                    ep_sum[w] = 0.0
                    ep_steps[w] = 0
            if bar is not None:
                bar.update(n_sim)
                bar.set_postfix(phase=f"{phase_index + 1}/{len(phases)} {kind}", egos=egos)
            if phase_done >= length:
                break
            if total >= next_ckpt:
                checkpoint()
                next_ckpt += cfg.checkpoint_every_sim_steps
            if stop_after_sim_steps is not None and total >= stop_after_sim_steps:
                killed = True
                break
        collector.shutdown()
        if killed:
            break
        # ---- phase end: snapshots, then a checkpoint at the start of the next phase
        if kind == "pretrain":
            save_ego_policy(out / "policy_pretrained.pt", ego.net, cfg, scen)
        if kind in ("pretrain", "ego"):
            keep_ego(phase_index)
        if kind == "adversary":
            pool.append(hw.snapshot())
            pool = pool[-cfg.pool_size :]
            save_highway_policy(out / "highway_policy.pt", pool[-1], cfg, scen)
            save_highway_policy(out / "pool" / f"adversary_{phase_index}.pt", pool[-1], cfg, scen)
        phase_index += 1
        phase_done = 0  # the next phase's collector starts fresh egos in every world
        ep_sum[:] = 0.0
        ep_steps[:] = 0
        checkpoint()
        next_ckpt = (total // cfg.checkpoint_every_sim_steps + 1) * cfg.checkpoint_every_sim_steps
    for log in (ego_log, hw_log, loss_log):
        log.close()
    if bar is not None:
        bar.close()
    wall = time.perf_counter() - t0
    evaluation = None
    if phase_index >= len(phases):
        save_ego_policy(out / "policy_last.pt", ego.net, cfg, scen)
        evaluation = {}
        if cfg.select_episodes > 0 and len(egos_kept) > 1:
            evaluation["selection"] = select_ego(egos_kept, pool, cfg, scen)
            chosen = evaluation["selection"]["chosen_phase_index"]
            ego.net.load_state_dict(dict(egos_kept)[chosen])
        save_ego_policy(out / "policy.pt", ego.net, cfg, scen)
        if cfg.eval_episodes > 0:
            from marlmerge.evaluate import evaluate_policy

            evaluation["scripted"] = evaluate_policy(
                ego.net.greedy, scen, cfg.eval_episodes, cfg.eval_seed, cfg.eval_worlds
            )
            if pool:
                evaluation["latest_highway_policy"] = evaluate_policy(
                    ego.net.greedy,
                    scen,
                    cfg.eval_episodes,
                    cfg.eval_seed,
                    cfg.eval_worlds,
                    highway_policy=snapshot_policy(pool[-1], cfg.hidden, scen),
                )
        (out / "evaluation.json").write_text(json.dumps(evaluation, indent=1))
    return CoTrainResult(out, total, egos, wall, len(pool), evaluation)


def select_ego(
    candidates: list[tuple[int, dict[str, Tensor]]],
    pool: list[dict[str, Tensor]],
    cfg: CoTrainConfig,
    scen: ScenarioConfig,
) -> dict[str, Any]:
    """Score each candidate ego (phase index, weights) by its failures (collisions +
    truncations) in `cfg.select_episodes` greedy episodes against scripted traffic and against
    each pool snapshot, the same episodes for all; the fewest failures wins, the latest on ties."""
    from marlmerge.evaluate import evaluate_policy

    opponents: list[HighwayPolicy | None] = [None] + [
        snapshot_policy(s, cfg.hidden, scen) for s in pool
    ]
    failures: list[list[int]] = []
    for _, weights in candidates:
        net = frozen_net(weights, len(EGO_FEATURES), cfg.hidden, scen.ego.accel_bounds_mps2)
        row = []
        for opp in opponents:
            r = evaluate_policy(
                net.greedy, scen, cfg.select_episodes, cfg.select_seed, cfg.eval_worlds, opp
            )
            row.append(round((r["collision_rate"] + r["truncation_rate"]) * r["episodes"]))
        failures.append(row)
    totals = [sum(row) for row in failures]
    best = min(range(len(candidates)), key=lambda i: (totals[i], -i))
    return {
        "episodes_per_opponent": cfg.select_episodes,
        "opponents": ["scripted"] + [f"pool_{i}" for i in range(len(pool))],
        "candidate_phase_index": [i for i, _ in candidates],
        "failures": failures,
        "chosen_phase_index": candidates[best][0],
    }


__all__ = [
    "INTERACTION_TERMS",
    "CoTrainConfig",
    "GroupLearner",
    "JointPolicy",
    "cotrain",
    "load_cotrain_config",
    "load_highway_policy",
]
