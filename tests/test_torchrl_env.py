"""The native torchrl view over the batched core."""

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from marlmerge.sim.reward import EGO_TERMS
from marlmerge.views.torchrl_env import BatchedMergeEnv


def _hold(td):
    return td.set("action", torch.zeros(td.batch_size[0], 1))


def test_check_env_specs():
    check_env_specs(BatchedMergeEnv(num_worlds=4, seed=0), seed=0)


def test_rollout_resets_finished_worlds_and_reports_terms():
    env = BatchedMergeEnv(num_worlds=8, seed=1)
    td = env.rollout(150, _hold, break_when_any_done=False)
    nxt = td["next"]
    done = nxt["done"].squeeze(-1)
    assert done.sum() >= 8, "hold-speed egos finish an episode within 60 s"
    total = sum(nxt["reward_terms", t] for t in EGO_TERMS)
    assert torch.allclose(total, nxt["reward"], atol=1e-5)
    assert (nxt["reward"] <= 0).all()
    outcome = nxt["outcome"].squeeze(-1)
    assert ((outcome != 0) == done).all()
    assert (nxt["terminated"].squeeze(-1) == ((outcome == 1) | (outcome == 2))).all()
    # the step after a done starts a new ego at the ramp start (rollouts are [B, T])
    assert td.batch_size == (8, 150)
    ramp_start = env.cfg.road.x_ramp_start_m / 100.0
    after = td["observation"][:, 1:][done[:, :-1]]
    assert torch.allclose(after[:, 1], torch.full_like(after[:, 1], ramp_start))


def test_same_seed_same_rollout():
    a = BatchedMergeEnv(num_worlds=4, seed=3).rollout(60, _hold, break_when_any_done=False)
    b = BatchedMergeEnv(num_worlds=4, seed=3).rollout(60, _hold, break_when_any_done=False)
    assert torch.equal(a["next", "observation"], b["next", "observation"])
    assert torch.equal(a["next", "reward"], b["next", "reward"])


def test_non_finite_action_is_named():
    env = BatchedMergeEnv(num_worlds=3, seed=0)
    td = env.reset()
    td["action"] = torch.tensor([[0.0], [float("nan")], [0.0]])
    with pytest.raises(ValueError, match="world 1.*nan"):
        env.step(td)


def test_cooperative_traffic_is_easier_than_adversarial():
    rates = {}
    for mix, shares in {"coop": (1.0, 0.0, 0.0), "adv": (0.0, 0.0, 1.0)}.items():
        env = BatchedMergeEnv(
            num_worlds=32,
            seed=5,
            overrides={
                "driver.mix_cooperative": shares[0],
                "driver.mix_neutral": shares[1],
                "driver.mix_adversarial": shares[2],
            },
        )
        td = env.rollout(120, _hold, break_when_any_done=False)
        out = td["next", "outcome"][td["next", "done"]].numpy()
        rates[mix] = np.mean(out == 1)
    assert rates["coop"] > rates["adv"]
