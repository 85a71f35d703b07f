"""The one schema of training runs: a shared `RunConfig`, one table per algorithm, and the two
kinds of run built on them (`TrainConfig` here, `marlmerge.cotrain.CoTrainConfig`).

A preset (TOML in `trainers/`) names its kind (`kind = "train"` or `"cotrain"`); its keys are the
fields below, the algorithm tables as TOML tables (`[dqn]`, `[td3]`). Every number is validated
where the config is built: finite, and the sign or range of `RUN_RULES` / `TRAIN_RULES`, with an
error naming the full key and the value.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from marlmerge.config import check_values, require
from marlmerge.learners.baselines_rl import ALGORITHMS
from marlmerge.learners.quadq import PAPER_GAMMA

UPDATE_PATHS = ("compiled", "fast", "torchrl")

RUN_RULES = {
    **dict.fromkeys(
        [
            "num_worlds", "env_steps_per_batch", "batch_size", "target_update_period", "hidden",
            "replay_capacity", "updates_per_call", "threads", "loss_log_every",
            "checkpoint_every_sim_steps", "eval_worlds",
        ],
        ">=1",
    ),
    **dict.fromkeys(["seed", "learning_starts", "eval_episodes", "eval_seed"], ">=0"),
    "lr": ">0",
}  # fmt: skip
"""Signs and ranges of the numbers every run has (`marlmerge.config.check_values`)."""

TRAIN_RULES = {
    **RUN_RULES,
    "total_sim_steps": ">=1",
    **dict.fromkeys(["updates_per_sim_step", "sigma_start", "sigma_end"], ">=0"),
    "sigma_decay_fraction": "[0,1]",
    "dqn.hidden_layers": ">=1",
    "dqn.epsilon_start": "[0,1]",
    "dqn.epsilon_end": "[0,1]",
    "td3.hidden_layers": ">=1",
    "td3.policy_delay": ">=1",
    "td3.target_noise": ">=0",
    "td3.target_noise_clip": ">=0",
}
"""... and of a `TrainConfig`."""


@dataclass(frozen=True)
class RunConfig:
    """What every training run has: its name, traffic, seed, worlds, the Q-learning settings
    shared by its learners, logs, checkpoints and the final evaluation. Defaults are the
    paper's recipe (Sec. IV.B, Table 1)."""

    KIND: ClassVar[str] = ""
    """The `kind` a preset of this schema names."""

    name: str = "paper"
    """Run name; outputs go to `runs/<name>` unless `--out` says otherwise."""
    scenario: str = "default"
    """Scenario preset in `envs/` (or a path): the traffic the run trains in."""
    seed: int = 0
    """Seeds the traffic, the networks, exploration noise and replay sampling."""
    num_worlds: int = 32
    """B: independent worlds stepped together, each with its own ego, feeding one buffer."""
    env_steps_per_batch: int = 4
    """Env steps per world in each collector batch; updates follow each batch."""
    batch_size: int = 32
    """M: minibatch size."""
    gamma: float = PAPER_GAMMA
    lr: float = 1.0e-3
    target_update_period: int = 500
    """p: the target network is a copy of the online one, refreshed every p updates."""
    hidden: int = 64
    """Hidden width of the networks (quadq: each of A, B, C, two layers each)."""
    replay_capacity: int = 200_000
    """Transitions kept in each replay buffer (oldest dropped first)."""
    learning_starts: int = 1_000
    """No updates until a buffer holds this many transitions (those updates are skipped)."""
    update_path: str = "compiled"
    """"compiled" (torch.compile of the fast path), "fast" (same, eager) or "torchrl" (the
    LossModule loop). The peers compile their gradient steps when "compiled"."""
    updates_per_call: int = 10
    """Updates fused into one call of the fast path; must divide `target_update_period`."""
    threads: int = 1
    """torch threads (tiny networks run fastest on one)."""
    loss_log_every: int = 5
    """Log the loss every this many updates (the paper stores it every 5 steps)."""
    checkpoint_every_sim_steps: int = 200_000
    """Checkpoint interval; a killed run resumes from its last checkpoint."""
    eval_episodes: int = 200
    """Greedy evaluation after training: this many held-out episodes ..."""
    eval_seed: int = 1_000_000
    """... on roads seeded from here on (training seeds are small numbers)."""
    eval_worlds: int = 50
    """Episodes evaluated in parallel (one seed per group of this many)."""

    def _check(self, rules: dict[str, str]) -> None:
        check_values(self, rules)
        require(
            [
                (
                    self.replay_capacity >= self.batch_size,
                    f"replay_capacity ({self.replay_capacity}) must be >= batch_size "
                    f"({self.batch_size})",
                ),
                (
                    self.update_path in UPDATE_PATHS,
                    f"update_path must be one of {UPDATE_PATHS}, got {self.update_path!r}",
                ),
                (
                    self.target_update_period % self.updates_per_call == 0,
                    f"updates_per_call ({self.updates_per_call}) must divide "
                    f"target_update_period ({self.target_update_period})",
                ),
                (0.0 < self.gamma < 1.0, f"gamma must lie in (0, 1), got {self.gamma}"),
            ]
        )


@dataclass(frozen=True)
class DqnConfig:
    """`[dqn]`: the DQN peer (torchrl `DQNLoss` over discrete acceleration levels)."""

    hidden_layers: int = 2
    """Hidden ReLU layers of width `hidden` in the Q-network."""
    levels: int = 7
    """Acceleration levels evenly spaced over the ego bounds, both ends included."""
    double: bool = False
    """Double DQN target (online argmax, target value); the target is a hard copy every
    `target_update_period` updates."""
    epsilon_start: float = 1.0
    """Epsilon-greedy exploration, epsilon falling linearly from this ..."""
    epsilon_end: float = 0.05
    """... to this over `sigma_decay_fraction` of `total_sim_steps`, then constant."""


@dataclass(frozen=True)
class Td3Config:
    """`[td3]`: the TD3 peer. Its exploration is the Gaussian noise of `sigma_start` /
    `sigma_end`, m/s^2."""

    hidden_layers: int = 2
    """Hidden ReLU layers of width `hidden` in the actor and each critic."""
    tau: float = 0.005
    """Polyak factor of the target networks (updated with each actor step)."""
    policy_delay: int = 2
    """Critic updates per actor update."""
    target_noise: float = 0.7
    """Std of the target-policy smoothing noise, m/s^2 (TD3's 0.2 x half-range 3.5) ..."""
    target_noise_clip: float = 1.75
    """... clipped to +- this, m/s^2 (TD3's 0.5 x 3.5)."""


@dataclass(frozen=True)
class TrainConfig(RunConfig):
    """One run training the ego against scripted traffic (`marlmerge train`)."""

    KIND: ClassVar[str] = "train"

    total_sim_steps: int = 1_600_000
    """N: simulator steps of ego experience, summed over all worlds (paper: 1.6 M)."""
    updates_per_sim_step: float = 1.0
    """Gradient updates per simulator step of experience (paper: 1, i.e. k per transition)."""
    sigma_start: float = 1.0
    """Exploration (quadq, td3): std of the Gaussian noise on the greedy action at the start,
    m/s^2 ..."""
    sigma_end: float = 0.1
    """... decaying linearly to this ..."""
    sigma_decay_fraction: float = 0.5
    """... over this fraction of `total_sim_steps`, then constant (dqn: epsilon likewise)."""
    algorithm: str = "quadq"
    """Learner: "quadq" (the paper's quadratic Q), "dqn" (discrete levels, `[dqn]`) or "td3"
    (`[td3]`). All use the shared settings above."""
    dqn: DqnConfig = field(default_factory=DqnConfig)
    td3: Td3Config = field(default_factory=Td3Config)

    def __post_init__(self) -> None:
        self._check(TRAIN_RULES)
        require(
            [
                (
                    self.algorithm in ALGORITHMS,
                    f"algorithm must be one of {ALGORITHMS}, got {self.algorithm!r}",
                ),
                (self.dqn.levels >= 2, f"dqn.levels must be >= 2, got {self.dqn.levels}"),
                (
                    0.0 < self.td3.tau <= 1.0,
                    f"td3.tau must lie in (0, 1], got {self.td3.tau}",
                ),
            ]
        )


FLAT_KEYS = {
    "mlp_hidden_layers": ("dqn.hidden_layers", "td3.hidden_layers"),
    "dqn_levels": ("dqn.levels",),
    "dqn_double": ("dqn.double",),
    "epsilon_start": ("dqn.epsilon_start",),
    "epsilon_end": ("dqn.epsilon_end",),
    "td3_tau": ("td3.tau",),
    "td3_policy_delay": ("td3.policy_delay",),
    "td3_target_noise": ("td3.target_noise",),
    "td3_target_noise_clip": ("td3.target_noise_clip",),
}
"""Keys of version-0.3 configs (flat) and where they live now (the algorithm tables)."""


def upgrade_flat_keys(data: dict[str, Any]) -> dict[str, Any]:
    """A saved `TrainConfig` dict of an older version (flat algorithm keys) in today's layout."""
    out = {k: v for k, v in data.items() if k not in FLAT_KEYS}
    for old, new_keys in FLAT_KEYS.items():
        if old in data:
            for dotted in new_keys:
                table, key = dotted.split(".")
                out.setdefault(table, {})[key] = data[old]
    return out
