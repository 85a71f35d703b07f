"""Stable-Baselines3 on the batched core: its VecEnv conventions, and SAC training end to end."""

import numpy as np
import pytest
import torch
from stable_baselines3 import SAC
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import marlmerge
from marlmerge.evaluation.rollout import evaluate_policy
from marlmerge.views.sb3_env import MergeVecEnv


def test_single_env_passes_sb3_check_env():
    sb3_check_env(marlmerge.RampMergeEnv(), warn=False)


def test_vecenv_resets_in_the_step_and_keeps_the_terminal_observation():
    env = MergeVecEnv(num_envs=4, seed=0)
    obs = env.reset()
    assert obs.shape == (4, 7)
    ended = 0
    for _ in range(120):  # holding speed: most ramp vehicles end within 48 s
        obs, rewards, dones, infos = env.step(np.zeros((4, 1), dtype=np.float32))
        assert rewards.shape == (4,) and dones.shape == (4,)
        for i in np.flatnonzero(dones):
            ended += 1
            assert infos[i]["outcome"] != 0 and infos[i]["terminal_observation"].shape == (7,)
            assert infos[i]["TimeLimit.truncated"] == (infos[i]["outcome"] == 3)
            # the returned observation is the next ramp vehicle's, back at the ramp start
            assert obs[i, 1] * 100.0 == marlmerge.ScenarioConfig().road.x_ramp_start_m
    assert ended > 0


@pytest.mark.slow  # a training run
def test_sac_trains_a_few_hundred_steps_and_is_evaluated(tmp_path):
    env = MergeVecEnv(num_envs=4, seed=1)
    model = SAC("MlpPolicy", env, learning_starts=100, batch_size=32, seed=0, device="cpu")
    model.learn(400)
    model.save(tmp_path / "m.zip")

    def policy(obs):
        return torch.as_tensor(model.predict(obs.numpy(), deterministic=True)[0])

    ev = evaluate_policy(policy, env.cfg, episodes=4, worlds=4)
    assert ev["episodes"] == 4
    assert ev["success_rate"] + ev["collision_rate"] + ev["truncation_rate"] == 1.0
