"""Gymnasium and PettingZoo entry points against their checkers; the native vector env against B
single envs; videos people can watch."""

import os

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import api_test, max_cycles_test, render_test, seed_test

import marlmerge
from marlmerge.config import ScenarioConfig
from marlmerge.evaluation.registry import policy_from_spec
from marlmerge.evaluation.video import record_episodes
from marlmerge.policies.scripted import ScriptedHighwayPolicy

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # "human" windows without a display


@pytest.mark.slow
def test_registered_env_passes_check_env():
    env = gymnasium.make(marlmerge.ENV_ID, render_mode="rgb_array", config="adversarial")
    assert env.unwrapped.cfg.name == "adversarial"
    check_env(env.unwrapped, skip_render_check=False)
    obs, info = env.reset(seed=3)
    assert obs.shape == (7,) and info["outcome"] == 0
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3


def test_single_env_with_given_highway_policies():
    env = marlmerge.RampMergeEnv(highway_policy=ScriptedHighwayPolicy("adversarial"))
    check_env(env)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([np.nan]))
    for _ in range(40):
        _, r, term, trunc, info = env.step(np.array([0.0], dtype=np.float32))
        assert r == pytest.approx(sum(v for k, v in info.items() if k.startswith("reward_")))
        if term or trunc:
            break


def _single_runs(seeds, actions):
    """B single envs reset with the seeds, stepped with the actions, reset() when done."""
    out = []
    for w, seed in enumerate(seeds):
        env = gymnasium.make(marlmerge.ENV_ID)
        obs, _ = env.reset(seed=seed)
        rows, done = [obs], False
        for a in actions[:, w]:
            if done:  # the vector env's next-step autoreset does exactly this
                obs, _ = env.reset()
                rows.append(np.concatenate([obs, [0.0, 0.0]]))
                done = False
                continue
            obs, r, term, trunc, _ = env.step(a)
            done = term or trunc
            rows.append(np.concatenate([obs, [r, float(done)]]))
        out.append(rows)
    return out


def test_vector_env_equals_b_single_envs_with_the_same_seeds():
    b, steps = 3, 80
    envs = gymnasium.make_vec(marlmerge.ENV_ID, num_envs=b, vectorization_mode="vector_entry_point")
    assert isinstance(envs.unwrapped, marlmerge.RampMergeVectorEnv)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-4.5, 2.5, (steps, b, 1)).astype(np.float32)
    obs, _ = envs.reset(seed=20)
    got = [[o] for o in obs]
    for t in range(steps):
        obs, r, term, trunc, _ = envs.step(actions[t])
        for w in range(b):
            got[w].append(np.concatenate([obs[w], [r[w], float(term[w] or trunc[w])]]))
    assert any(row[-1] == 1.0 for rows in got for row in rows[1:]), "no episode ended"
    want = _single_runs([20 + w for w in range(b)], actions)
    for w in range(b):
        assert np.allclose(np.stack(want[w][1:]), np.stack(got[w][1:]), rtol=0, atol=1e-6)
        assert np.array_equal(want[w][0], got[w][0])


@pytest.mark.slow
def test_record_video_wrapper_writes_a_video(tmp_path):
    env = gymnasium.make(marlmerge.ENV_ID, render_mode="rgb_array")
    env = gymnasium.wrappers.RecordVideo(env, str(tmp_path), episode_trigger=lambda e: e == 0)
    env.reset(seed=0)
    for _ in range(30):
        *_, term, trunc, _ = env.step(np.array([0.5], dtype=np.float32))
        if term or trunc:
            break
    env.close()
    assert list(tmp_path.glob("*.mp4"))


@pytest.mark.slow
def test_episode_video_has_one_frame_per_simulator_step(tmp_path):
    import imageio.v2 as imageio

    from marlmerge.views.render import write_video

    cfg = ScenarioConfig()
    frames, outcomes = record_episodes(policy_from_spec("hold", cfg), cfg, episodes=1, seed=5)
    steps = (len(frames) - 1) - int(round(1.5 / cfg.sim.dt_s))  # initial frame, held end
    assert outcomes[0] in ("success", "collision", "truncated")
    assert steps >= 40 and len({f.shape for f in frames}) == 1
    path = write_video(tmp_path / "e.mp4", frames, fps=10)
    reader = imageio.get_reader(path)
    assert reader.count_frames() == len(frames)
    h, w = frames[0].shape[:2]
    assert reader.get_data(0).shape[:2] == (h + (-h % 16), w + (-w % 16))
    gif = write_video(tmp_path / "e.gif", frames[:12], fps=10)
    assert len(imageio.mimread(gif)) == 12


@pytest.mark.slow
def test_pettingzoo_suite_on_every_entry_point():
    api_test(marlmerge.env(), num_cycles=200)
    seed_test(marlmerge.env, num_cycles=100)
    max_cycles_test(marlmerge)
    render_test(marlmerge.env)
    meta = marlmerge.parallel_env().metadata
    assert meta["is_parallelizable"] and {"rgb_array", "human"} <= set(meta["render_modes"])
    assert meta["render_fps"] > 0


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["dense", "robust_mix4"])
def test_a_video_shows_the_evaluations_episodes(scenario):
    # episode e of a video is episode e of the evaluation with the same seed: the same outcome
    from marlmerge.config.presets import resolve_config
    from marlmerge.evaluation.registry import policy_from_spec
    from marlmerge.evaluation.rollout import rollout_first_egos
    from marlmerge.evaluation.video import record_episodes
    from marlmerge.sim import OUTCOME_NAMES

    cfg = resolve_config(scenario)
    policy = policy_from_spec("hold", cfg)
    rec, _ = rollout_first_egos(policy, cfg, 5, 100, 5)
    shown = [record_episodes(policy, cfg, 1, 100 + e)[1][0] for e in range(5)]
    assert shown == [OUTCOME_NAMES[o] for o in rec["outcome"]]
