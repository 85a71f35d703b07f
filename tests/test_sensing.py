"""Imperfect sensing: noise of the configured size from each world's seeded generator, latency of
exactly n simulator steps, occlusion that hides exactly the hidden, and checkpoints of it all."""

import textwrap

import numpy as np
import pytest
from scenes import same_with_and_without_jit, scene

from marlmerge.config import ScenarioConfig, load_scenario
from marlmerge.config.presets import find_preset
from marlmerge.sim import TrafficCore
from marlmerge.sim import layout as L
from marlmerge.sim.observation import EGO_EXTENDED_FEATURES

CFG = ScenarioConfig().replace(**{"ego.observation": "extended"})
POS_STD_M, SPEED_STD_MPS = 0.8, 0.4
NOISY = CFG.replace(
    **{"sensing.position_noise_std_m": POS_STD_M, "sensing.speed_noise_std_mps": SPEED_STD_MPS}
)
RANGE_M = CFG.ego.sensing_range_m


def _drive(core: TrafficCore, n: int, k: int | None = None) -> np.ndarray:
    """[n, B, F] observations after n calls with a fixed ego command (the egos keep merging)."""
    out = []
    for _ in range(n):
        o = core.rollout(np.full(core.batch_size, 0.3), k=k)
        out.append(o.ego_obs.copy())
        core.next_ego(o.ego_outcome != 0)
    return np.stack(out)


def test_noise_has_the_configured_std_on_the_sensed_features_only():
    exact = _drive(TrafficCore(CFG, batch_size=32, seed=1), 40)
    noisy = _drive(TrafficCore(NOISY, batch_size=32, seed=1), 40)
    diff = (noisy.astype(np.float64) - exact) * np.array([f.scale for f in EGO_EXTENDED_FEATURES])
    for i, f in enumerate(EGO_EXTENDED_FEATURES):
        d = diff[..., i].ravel()
        if f.noise == "":
            if f.name != "side_overlap":  # derived from the noisy side_dx
                assert np.all(np.abs(d) < 1e-3), f.name
            continue
        if f.name.startswith("side_"):  # the gap-front or gap-back vehicle, with its errors
            continue  # (which may move it in or out of overlap)
        errors = d[np.abs(d) > 1e-4]  # missing (virtual) vehicles carry no noise
        want = POS_STD_M if f.noise == "position" else SPEED_STD_MPS
        assert errors.size > 150, f.name
        assert np.std(errors) == pytest.approx(want, rel=0.15), f.name
        assert abs(np.mean(errors)) < 4 * want / np.sqrt(errors.size), f.name


def test_noise_is_seeded_per_world():
    a = _drive(TrafficCore(NOISY, batch_size=3, seed=[5, 6, 7]), 30)
    b = _drive(TrafficCore(NOISY, batch_size=3, seed=[5, 6, 7]), 30)
    assert np.array_equal(a, b)
    alone = _drive(TrafficCore(NOISY, batch_size=1, seed=[6]), 30)
    assert np.array_equal(alone[:, 0], a[:, 1])  # a world is the same alone or in a batch
    other = _drive(TrafficCore(NOISY, batch_size=3, seed=[5, 9, 7]), 30)
    assert not np.array_equal(other[:, 1], a[:, 1]) and np.array_equal(other[:, 0], a[:, 0])


def test_noise_leaves_the_reward_and_the_traffic_alone():
    exact, noisy = TrafficCore(CFG, 4, seed=2), TrafficCore(NOISY, 4, seed=2)
    for _ in range(30):
        o1, o2 = exact.rollout(np.full(4, 0.5)), noisy.rollout(np.full(4, 0.5))
        assert np.array_equal(o1.ego_terms, o2.ego_terms)
        assert not np.array_equal(o1.ego_obs, o2.ego_obs)
        exact.next_ego(o1.ego_outcome != 0)
        noisy.next_ego(o2.ego_outcome != 0)
    assert np.array_equal(exact.vf, noisy.vf)


@pytest.mark.parametrize("n", [1, 3])
def test_latency_shifts_the_observation_by_exactly_n_steps(n):
    late = CFG.replace(**{"sensing.latency_s": n * CFG.sim.dt_s})
    exact = _drive(TrafficCore(CFG, batch_size=2, seed=3), 60, k=1)
    delayed = _drive(TrafficCore(late, batch_size=2, seed=3), 60, k=1)
    assert np.array_equal(delayed[n:], exact[:-n])
    first = TrafficCore(CFG, batch_size=2, seed=3).observe()[0]
    assert all(np.array_equal(delayed[i], first) for i in range(n))  # the first measurement


def test_latency_holds_across_env_steps():
    # one env step is 4 simulator steps; 0.2 s = 2 steps of delay
    late = CFG.replace(**{"sensing.latency_s": 0.2})
    exact = _drive(TrafficCore(CFG, batch_size=2, seed=4), 40, k=1)
    delayed = _drive(TrafficCore(late, batch_size=2, seed=4), 10)
    # after env step m the ego sees the measurement of simulator step 4 (m + 1) - 2
    assert np.array_equal(delayed, exact[4 * np.arange(10) + 1])


def _left(core: TrafficCore) -> dict[str, float]:
    obs = core.observe()[0][0]
    names = ("left_front_dx", "left_back_dx")
    idx = [next(i for i, f in enumerate(EGO_EXTENDED_FEATURES) if f.name == n) for n in names]
    return {n: float(obs[i]) * 100.0 for n, i in zip(names, idx, strict=True)}


CFG_EXT = {"ego.observation": "extended"}
OCCLUSION = {**CFG_EXT, "sensing.occlusion": True}
LEFT_CARS = [(-40.0, 25.0), (-100.0, 25.0)]


def test_occlusion_hides_the_hidden_and_not_the_visible():
    # the ego's centre at (-62.5, -2.27); the left-lane cars' centres at (-42.5 / -102.5, 3.75).
    # The line to the front one crosses the right lane's body band over x in [-58.0, -52.0],
    # the line to the back one over [-83.6, -71.6].
    ahead = scene((-60.0, 20.0), right=[(-52.0, 20.0)], left=LEFT_CARS, overrides=OCCLUSION)
    assert _left(ahead) == pytest.approx({"left_front_dx": RANGE_M, "left_back_dx": -40.0})
    behind = scene((-60.0, 20.0), right=[(-72.0, 20.0)], left=LEFT_CARS, overrides=OCCLUSION)
    assert _left(behind) == pytest.approx({"left_front_dx": 20.0, "left_back_dx": -RANGE_M})
    clear = scene((-60.0, 20.0), right=[(-64.0, 20.0)], left=LEFT_CARS, overrides=OCCLUSION)
    assert _left(clear) == pytest.approx({"left_front_dx": 20.0, "left_back_dx": -40.0})
    seeing = scene((-60.0, 20.0), right=[(-52.0, 20.0)], left=LEFT_CARS, overrides=CFG_EXT)
    assert _left(seeing) == pytest.approx({"left_front_dx": 20.0, "left_back_dx": -40.0})


def test_occlusion_follows_the_line_of_sight_as_the_blocker_moves():
    hidden = []
    for x in np.arange(-62.0, -40.0, 1.0):  # the blocker's front bumper
        core = scene((-60.0, 20.0), right=[(x, 20.0)], left=LEFT_CARS[:1], overrides=OCCLUSION)
        hidden.append(_left(core)["left_front_dx"] == pytest.approx(RANGE_M))
    blocked = np.arange(-62.0, -40.0, 1.0)[np.array(hidden)]
    # the body [x - 5, x] meets the line's stretch [-57.96, -51.98]
    assert blocked.min() == -57.0 and blocked.max() == -47.0 and blocked.size == 11


def test_sensing_state_continues_bit_for_bit_from_a_checkpoint():
    cfg = NOISY.replace(**{"sensing.latency_s": 0.3, "sensing.occlusion": True})
    core = TrafficCore(cfg, batch_size=3, seed=4)
    _drive(core, 40)
    saved = core.state_dict()
    assert saved["version"] == 5 and saved["arrays"]["ring"].shape == (3 * 4, 16)
    expected = _drive(core, 60)
    other = TrafficCore(cfg, batch_size=3, seed=99)
    other.load_state_dict(saved)
    assert np.array_equal(_drive(other, 60), expected)


def test_a_version_1_state_still_loads():
    cfg = ScenarioConfig()
    core = TrafficCore(cfg, batch_size=2, seed=1)
    _drive(core, 20)
    saved = core.state_dict()
    v1 = {**saved, "version": 1, "arrays": dict(saved["arrays"])}
    v1["arrays"]["wi"] = saved["arrays"]["wi"][:, : L.WI_ROWS_V1]
    v1["arrays"]["vi"] = saved["arrays"]["vi"][:, : L.VI_ROWS_V2]  # no ramp flow then
    v1["arrays"]["wf"] = saved["arrays"]["wf"][:, : L.WF_ROWS_V2]
    v1["arrays"]["lanes"] = saved["arrays"]["lanes"][:, :2]
    v1["arrays"]["vf"] = saved["arrays"]["vf"][:, : L.VF_ROWS_V3]
    del v1["arrays"]["ring"], v1["arrays"]["noise"]
    expected = _drive(core, 40)
    other = TrafficCore(cfg, batch_size=2, seed=7)
    other.load_state_dict(v1)
    assert np.array_equal(_drive(other, 40), expected)
    with pytest.raises(ValueError, match="version 0"):
        other.load_state_dict({**saved, "version": 0})


@pytest.mark.parametrize(
    ("key", "value", "match"),
    [
        ("sensing.latency_s", 0.15, r"sensing\.latency_s must be a multiple of sim\.dt_s"),
        ("sensing.latency_s", 2.5, r"sensing\.latency_s must be in \[0, 2\], got 2\.5"),
        ("sensing.position_noise_std_m", -0.1, r"position_noise_std_m must be in \[0, 50\]"),
        ("sensing.speed_noise_std_mps", float("nan"), r"sensing\.speed_noise_std_mps.*finite"),
        ("sensing.occlusion", 1, r"sensing\.occlusion' must be true or false"),
    ],
)
def test_bad_sensing_values_are_named(key, value, match):
    with pytest.raises(ValueError, match=match):
        ScenarioConfig().replace(**{key: value})


def test_the_realistic_preset_is_documented_and_loads():
    cfg = load_scenario(find_preset("sensing_realistic"))
    s = cfg.sensing
    assert 0.5 <= s.position_noise_std_m <= 1.0 and 0.3 <= s.speed_noise_std_mps <= 0.5
    assert 0.1 <= s.latency_s <= 0.2 and s.occlusion and cfg.ego.observation == "extended"


@pytest.mark.slow
def test_same_sensed_trajectory_with_the_compiler_off(tmp_path):
    code = textwrap.dedent("""
        import sys
        import numpy as np
        from marlmerge.config import ScenarioConfig
        from marlmerge.sim import TrafficCore
        cfg = ScenarioConfig().replace(**{
            "traffic.warmup_s": 2.0, "ego.observation": "extended", "ego.safety_filter": True,
            "sensing.position_noise_std_m": 0.7, "sensing.speed_noise_std_mps": 0.3,
            "sensing.latency_s": 0.2, "sensing.occlusion": True, "reward.w_back_ttc": 1.0,
        })
        core = TrafficCore(cfg, batch_size=1, seed=3)
        rows = []
        for i in range(40):
            out = core.rollout(np.array([np.sin(i) * 2.0]))
            rows.append(np.concatenate([out.ego_obs[0], out.ego_terms[0], core.vf[0, 0],
                                        out.filter_interventions]))
            core.next_ego(out.ego_outcome != 0)
        np.save(sys.argv[1], np.stack(rows))
    """)
    assert same_with_and_without_jit(code, tmp_path)
