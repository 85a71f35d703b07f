"""Property-based tests (Hypothesis, a fixed seed and a bounded number of examples): random values
and call orders give a valid run or one clear error naming the key, agent or file; never a
traceback of another kind, a hang or a NaN."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from marlmerge import RampMergeEnv, parallel_env
from marlmerge.config import ScenarioConfig, bounds_table, field_bounds, to_dict
from marlmerge.config.training import TrainConfig
from marlmerge.io import files
from marlmerge.io.policy_file import TOP_KEYS, write_policy
from marlmerge.learners.quadq import QuadraticQNet
from marlmerge.sim import TrafficCore

FIXED = settings(
    derandomize=True,  # the same examples on every run
    database=None,
    deadline=None,
    max_examples=60,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
SCENARIO_KEYS = [key for key, _, _ in bounds_table(ScenarioConfig)]
TRAIN_KEYS = [key for key, _, _ in bounds_table(TrainConfig)]
ALL_NAMES = {part for key in SCENARIO_KEYS + TRAIN_KEYS for part in (key, key.split(".")[-1])}

ODD = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.none(),
    st.text(max_size=5),
    st.booleans(),
    st.lists(st.floats(-1e3, 1e3), max_size=3),
)


def _plausible(key: str, defaults: dict) -> st.SearchStrategy:
    """Values near a key's default (mostly valid) or anywhere (mostly not)."""
    default = defaults[key]
    if isinstance(default, tuple):
        return st.one_of(st.tuples(st.floats(-100, 3000), st.floats(-100, 3000)).map(list), ODD)
    if isinstance(default, int):
        return st.one_of(st.integers(0, 2 * max(default, 1) + 2), ODD)
    if default is None:
        return st.one_of(st.tuples(st.floats(0, 2000), st.floats(0, 2000)).map(list), ODD)
    return st.one_of(st.floats(0.0, 2.0 * abs(default) + 1.0), ODD)


def _names_a_key(message: str) -> bool:
    return any(name in message for name in ALL_NAMES) or "mix_*" in message


SCEN_DEFAULTS = dict((k, d) for k, d, _ in bounds_table(ScenarioConfig))
TRAIN_DEFAULTS = dict((k, d) for k, d, _ in bounds_table(TrainConfig))


@st.composite
def overrides(draw, keys: list[str], defaults: dict) -> dict:
    chosen = draw(st.lists(st.sampled_from(keys), min_size=1, max_size=4, unique=True))
    return {k: draw(_plausible(k, defaults)) for k in chosen}


def _within_bounds(cfg, cls, prefix=""):
    for key, _, _ in bounds_table(cls):
        node, parts = cfg, key.split(".")
        for p in parts[:-1]:
            node = getattr(node, p)
        value = getattr(node, parts[-1])
        bounds = field_bounds(type(node), parts[-1])
        for v in value if isinstance(value, tuple) else (value,):
            if v is not None:
                assert math.isfinite(v) and bounds.holds(v), (key, value)


@FIXED
@given(overrides(SCENARIO_KEYS, SCEN_DEFAULTS))
def test_scenario_overrides_give_a_valid_config_or_an_error_naming_the_key(changes):
    try:
        cfg = ScenarioConfig().replace(**changes)
    except ValueError as err:
        assert _names_a_key(str(err)), str(err)
        return
    _within_bounds(cfg, ScenarioConfig)


@FIXED
@given(overrides(TRAIN_KEYS, TRAIN_DEFAULTS))
def test_training_overrides_give_a_valid_config_or_an_error_naming_the_key(changes):
    from marlmerge.training.train import load_train_config

    try:
        cfg = load_train_config("quick", **changes)
    except ValueError as err:
        assert _names_a_key(str(err)) and str(err).startswith("--set"), str(err)
        return
    _within_bounds(cfg, TrainConfig)


@settings(FIXED, max_examples=25)
@given(overrides(SCENARIO_KEYS, SCEN_DEFAULTS), st.integers(0, 2**32))
def test_a_valid_scenario_runs_with_finite_observations(changes, seed):
    try:
        cfg = ScenarioConfig().replace(**changes)
    except ValueError:
        return
    cfg = cfg.replace(**{"traffic.warmup_s": min(cfg.traffic.warmup_s, 5.0)})
    core = TrafficCore(cfg, batch_size=2, seed=seed)
    for _ in range(5):
        out = core.rollout(np.array([1.0, -1.0]))
        assert np.isfinite(out.ego_obs).all() and np.isfinite(out.ego_terms).all()
        core.next_ego(out.ego_outcome != 0)


ACTION = st.one_of(
    st.floats(-10, 10).map(lambda v: np.array([v], np.float32)),
    st.floats(allow_nan=True, allow_infinity=True),
    st.none(),
    st.text(max_size=3),
    st.lists(st.floats(-5, 5), max_size=3),
)
CALL = st.one_of(
    st.tuples(st.just("reset"), st.one_of(st.none(), st.integers(0, 2**64), ODD)),
    st.tuples(
        st.just("step"),
        st.dictionaries(
            st.sampled_from(["ramp_0", "highway_0", "highway_3", "nobody"]), ACTION, max_size=4
        ),
    ),  # fmt: skip
    st.tuples(st.just("step_valid"), st.floats(-4.5, 2.5)),
)


@settings(FIXED, max_examples=40)
@given(st.lists(CALL, min_size=1, max_size=12))
def test_pettingzoo_call_orders_give_results_or_clear_errors(calls):
    env = parallel_env(control="all", overrides={"traffic.warmup_s": 2.0})
    for kind, arg in calls:
        try:
            if kind == "reset":
                obs, infos = env.reset(seed=arg)
            elif kind == "step":
                obs, rewards, *_ = env.step(arg)
            else:
                obs, rewards, *_ = env.step({a: np.array([arg], np.float32) for a in env.agents})
        except ValueError as err:
            assert any(w in str(err) for w in ("seed", "agent", "action of")), str(err)
            continue
        except RuntimeError as err:
            assert "reset" in str(err), str(err)
            continue
        assert all(np.isfinite(o).all() for o in obs.values())
        if kind != "reset":
            assert all(math.isfinite(r) for r in rewards.values())


GYM_CALL = st.one_of(
    st.tuples(st.just("reset"), st.one_of(st.none(), st.integers(0, 99))),
    st.tuples(st.just("step"), ACTION),
)


@settings(FIXED, max_examples=25)
@given(st.lists(GYM_CALL, min_size=1, max_size=40))
def test_gymnasium_call_orders_give_results_or_clear_errors(calls):
    env = RampMergeEnv(overrides={"traffic.warmup_s": 2.0, "ego.max_episode_s": 3.0})
    for kind, arg in calls:
        try:
            if kind == "reset":
                obs, _ = env.reset(seed=arg)
            else:
                obs, reward, *_ = env.step(arg)
                assert math.isfinite(reward)
        except ValueError as err:
            assert "action" in str(err), str(err)
            continue
        except RuntimeError as err:
            assert "reset" in str(err), str(err)
            continue
        assert np.isfinite(obs).all()


@pytest.fixture(scope="module")
def valid_policy(tmp_path_factory) -> dict:
    path = tmp_path_factory.mktemp("policy") / "p.pt"
    net = QuadraticQNet(7, 8, action_low=-4.5, action_high=2.5, generator=torch.Generator())
    state = {"net": net.state_dict(), "hidden": 8}
    write_policy(path, "ego", "quadq", (-4.5, 2.5), state, {}, to_dict(ScenarioConfig()))
    return files.load(path)


VALUE = st.one_of(
    ODD,
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=2),
    st.sampled_from(["quadq", "dqn", "td3", "marlmerge-policy", "ego", "highway"]),
)


@settings(FIXED, max_examples=60)
@given(
    st.lists(st.sampled_from(list(TOP_KEYS)), max_size=3),
    st.dictionaries(st.sampled_from([k for k in TOP_KEYS if k != "format"]), VALUE, max_size=2),
    st.one_of(st.none(), st.tuples(st.floats(0, 1), st.integers(1, 256))),
)
def test_a_mangled_policy_file_loads_or_names_the_file(
    valid_policy, tmp_path_factory, dropped, replaced, damage
):
    from marlmerge.learners.loading import load_policy

    saved = {k: v for k, v in valid_policy.items() if k not in dropped} | replaced
    path: Path = tmp_path_factory.mktemp("mangled") / "p.pt"
    files.save(saved, path)
    if damage is not None:  # and some bytes overwritten
        data = bytearray(path.read_bytes())
        at, n = int(damage[0] * (len(data) - 1)), damage[1]
        data[at : at + n] = bytes((b + 1) % 256 for b in data[at : at + n])
        path.write_bytes(bytes(data))
    try:
        policy = load_policy(path)
    except ValueError as err:
        assert str(path) in str(err), str(err)
        return
    out = policy(torch.zeros(4, 7))
    assert out.shape == (4, 1) and torch.isfinite(out).all()
