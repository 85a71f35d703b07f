"""Bad inputs and odd call orders: each case gives a valid run or one clear error naming the key,
agent, world or file, before any work starts (`docs/reliability.md`)."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from marlmerge import RampMergeEnv, parallel_env
from marlmerge import env as marlmerge_env
from marlmerge.cli import main
from marlmerge.config import ScenarioConfig, bounds_table, to_dict
from marlmerge.io import files
from marlmerge.io.policy_file import read_policy, write_policy
from marlmerge.learners.quadq import QuadraticQNet
from marlmerge.sim import TrafficCore

ROOT = Path(__file__).resolve().parent.parent
SCEN = to_dict(ScenarioConfig())


def _state(core: TrafficCore) -> list[np.ndarray]:
    n = core.n_slots
    return [core.vf[..., :n].copy(), core.vi[..., :n].copy(), core.wf.copy(), core.wi.copy()]


def _same(a: list[np.ndarray], b: list[np.ndarray]) -> bool:
    return all(np.array_equal(x, y, equal_nan=True) for x, y in zip(a, b, strict=True))


# ---------------------------------------------------------------------- 1. one road per seed
@pytest.mark.parametrize("seed", [0, 1000, 2**64])
def test_a_seed_gives_the_same_road_whatever_came_before(seed):
    fresh = _state(TrafficCore(ScenarioConfig(), batch_size=2, seed=seed))
    core = TrafficCore(ScenarioConfig(), batch_size=2, seed=seed)
    core.reset(seed=seed)  # straight after the constructor's reset
    assert _same(_state(core), fresh)
    for _ in range(60):  # and after a stretch of driving and a few merges
        core.rollout(np.zeros(2))
    core.reset(seed=seed)
    assert _same(_state(core), fresh)


def test_the_views_give_the_same_road_for_the_same_seed_twice():
    env = parallel_env(control="ego")
    first = env.reset(seed=0)[0]["ramp_0"]
    env.step({"ramp_0": np.array([1.0], np.float32)})
    assert np.array_equal(env.reset(seed=0)[0]["ramp_0"], first)
    assert np.array_equal(env.reset(seed=0)[0]["ramp_0"], first)
    gym = RampMergeEnv()
    obs0 = gym.reset(seed=1000)[0]
    rewards0 = [gym.step(np.array([0.5], np.float32))[1] for _ in range(5)]
    obs1 = gym.reset(seed=1000)[0]
    rewards1 = [gym.step(np.array([0.5], np.float32))[1] for _ in range(5)]
    assert np.array_equal(obs0, obs1) and rewards0 == rewards1


# ---------------------------------------------------------------------- 2. Gymnasium's order
def test_gymnasium_step_after_the_episode_ended_is_an_error_until_reset():
    env = RampMergeEnv(overrides={"ego.max_episode_s": 2.0})
    env.reset(seed=3)
    done = False
    while not done:
        _, _, terminated, truncated, _ = env.step(np.array([2.5], np.float32))
        done = terminated or truncated
    with pytest.raises(RuntimeError, match="call reset"):
        env.step(np.array([0.0], np.float32))
    env.reset()
    env.step(np.array([0.0], np.float32))  # the next ramp vehicle drives again


# ---------------------------------------------------------------------- 3. policy files
def _policy(tmp_path: Path) -> Path:
    net = QuadraticQNet(7, 8, action_low=-4.5, action_high=2.5, generator=torch.Generator())
    state = {"net": net.state_dict(), "hidden": 8}
    write_policy(tmp_path / "p.pt", "ego", "quadq", (-4.5, 2.5), state, {}, SCEN)
    return tmp_path / "p.pt"


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ({}, "not a marlmerge policy file"),
        ({"format": "marlmerge-policy"}, "no 'version' key"),
        ({"format": "marlmerge-policy", "version": 1, "group": "ego"}, "no 'algorithm' key"),
    ],
)
def test_a_torch_file_without_the_policy_keys_names_the_file_and_the_key(
    tmp_path, content, message
):
    files.save(content, tmp_path / "p.pt")
    with pytest.raises(ValueError, match=message) as err:
        read_policy(tmp_path / "p.pt", "ego")
    assert str(tmp_path / "p.pt") in str(err.value)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"algorithm": "ppo"}, "unknown ego algorithm 'ppo'"),
        ({"policy_state": {"net": {}}}, "lacks 'hidden'"),
        ({"policy_state": {"net": {}, "hidden": 8, "peaks": 0}}, "peaks must be an integer >= 1"),
        (
            {"policy_state": {"net": {}, "hidden": 8, "peak_bands": True}},
            "peak_bands must be true or false, and true only with peaks > 1; got True with peaks",
        ),
        (
            {"policy_state": {"net": {}, "hidden": 8, "peaks": 2, "peak_bands": "yes"}},
            "policy_state.peak_bands must be true or false",
        ),
        ({"action_bounds_mps2": [2.0, -1.0]}, "action_bounds_mps2"),
        ({"scenario": {"road": {"lane_width_m": -1.0}}}, "scenario is not valid"),
        ({"observation": "paper"}, "holds a str, not a dict"),
    ],
)
def test_a_policy_file_with_unusable_contents_names_the_file(tmp_path, change, message):
    saved = files.load(_policy(tmp_path))
    files.save({**saved, **change}, tmp_path / "p.pt")
    with pytest.raises(ValueError, match=message):
        read_policy(tmp_path / "p.pt", "ego")


def test_weights_that_do_not_fit_the_network_name_the_file(tmp_path):
    from marlmerge.learners.loading import load_policy

    saved = files.load(_policy(tmp_path))
    saved["policy_state"]["hidden"] = 16  # the saved weights are 8 wide
    files.save(saved, tmp_path / "p.pt")
    with pytest.raises(ValueError, match="do not fit the network"):
        load_policy(tmp_path / "p.pt")


def test_a_policy_of_several_peaks_loads_as_saved_and_a_wrong_count_names_the_file(tmp_path):
    from marlmerge.learners.loading import load_policy

    net = QuadraticQNet(7, 8, generator=torch.Generator().manual_seed(2), peaks=2)
    state = {"net": net.state_dict(), "hidden": 8, "peaks": 2}
    write_policy(tmp_path / "p.pt", "ego", "quadq", (-4.5, 2.5), state, {}, SCEN)
    obs = torch.randn(9, 7, generator=torch.Generator().manual_seed(3))
    assert torch.equal(load_policy(tmp_path / "p.pt")(obs), net.greedy(obs))
    saved = files.load(tmp_path / "p.pt")
    saved["policy_state"]["peaks"] = 3  # the weights hold two pieces
    files.save(saved, tmp_path / "p.pt")
    with pytest.raises(ValueError, match="p.pt: the saved weights do not fit the network"):
        load_policy(tmp_path / "p.pt")


def test_a_policy_of_banded_pieces_loads_with_its_bands(tmp_path):
    from marlmerge.learners.loading import load_policy

    net = QuadraticQNet(7, 8, generator=torch.Generator().manual_seed(2), peaks=2, peak_bands=True)
    state = {"net": net.state_dict(), "hidden": 8, "peaks": 2, "peak_bands": True}
    write_policy(tmp_path / "p.pt", "ego", "quadq", (-4.5, 2.5), state, {}, SCEN)
    obs = torch.randn(9, 7, generator=torch.Generator().manual_seed(3))
    assert torch.equal(load_policy(tmp_path / "p.pt")(obs), net.greedy(obs))
    unbanded = QuadraticQNet(7, 8, peaks=2)
    unbanded.load_state_dict(net.state_dict())  # same weights, B over the whole range
    assert not torch.equal(unbanded.greedy(obs), net.greedy(obs))


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_a_policy_file_with_non_finite_weights_names_the_file_and_the_weight(tmp_path, bad):
    saved = files.load(_policy(tmp_path))
    name = next(iter(saved["policy_state"]["net"]))
    saved["policy_state"]["net"][name].view(-1)[0] = bad
    files.save(saved, tmp_path / "p.pt")
    with pytest.raises(ValueError, match=f"p.pt: weight '{name}' of policy_state.net holds NaN"):
        read_policy(tmp_path / "p.pt", "ego")


def test_random_bytes_are_not_called_pickled_objects(tmp_path):
    path = tmp_path / "policy.pt"
    path.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(ValueError, match="not a torch archive") as err:
        read_policy(path, "ego")
    assert "pickled" not in str(err.value) and str(path) in str(err.value)


@pytest.mark.parametrize("offset_fraction", [0.05, 0.2, 0.5, 0.8, 0.97])
def test_a_file_with_corrupted_bytes_is_refused_naming_the_file(tmp_path, offset_fraction):
    path = _policy(tmp_path)
    data = bytearray(path.read_bytes())
    at = int(offset_fraction * (len(data) - 64))
    data[at : at + 64] = np.random.default_rng(at).bytes(64)
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="not a|corrupt") as err:
        read_policy(path, "ego")
    assert str(path) in str(err.value)


@pytest.mark.slow
def test_the_cli_refuses_a_keyless_policy_file_in_one_line(tmp_path):
    files.save({}, tmp_path / "p.pt")
    for args in (
        ["evaluate", str(tmp_path / "p.pt"), "--episodes", "1", "--worlds", "1"],
        ["grid", "--policy", f"quadq:{tmp_path / 'p.pt'}", "--episodes", "1", "--out", "g"],
    ):
        out = _cli(*args, cwd=tmp_path)
        assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr[-2000:]
        assert "not a marlmerge policy file" in out.stderr


# ---------------------------------------------------------------------- 4. magnitudes
@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("traffic.flow_vph_per_lane", 1e6),
        ("sim.dt_s", 10.0),
        ("ego.accel_bounds_mps2", (-1e9, 1e9)),
        ("driver.delta", 1e6),
        ("road.merge_zone_m", 1e-9),
        ("sim.n_highway_agents", 1000),
        ("road.speed_limit_mph", 1e6),
        ("road.lane_width_m", 100.0),
    ],
)
def test_implausible_magnitudes_are_refused_naming_the_key_and_the_value(key, value):
    with pytest.raises(ValueError, match=key.replace(".", r"\.")) as err:
        ScenarioConfig().replace(**{key: value})
    assert "must be in" in str(err.value) and repr(value).split(",")[0] in str(err.value)


def test_every_default_and_every_preset_lies_within_the_declared_bounds():
    from marlmerge.config import load_scenario
    from marlmerge.config.presets import preset_dir

    for key, _default, rule in bounds_table(ScenarioConfig):
        assert rule, key  # every number of the scenario has bounds
    for path in sorted(preset_dir("envs").glob("*.toml")):
        load_scenario(path)


# ---------------------------------------------------------------------- 5. validate writes
def test_validate_with_sumo_writes_only_under_out(tmp_path, monkeypatch):
    from marlmerge.validation import report, sumo

    reference = report.REFERENCE.read_bytes()
    ref, _ = report.load_reference()
    monkeypatch.setattr(sumo, "available", lambda: True)
    monkeypatch.setattr(sumo, "sumo_version", lambda: "stand-in")
    monkeypatch.setattr(report, "run_simulator", lambda cfg, name, seeds: ref)
    monkeypatch.setattr(report, "_plots", lambda ours, ref, out: None)
    report.validate(out_dir=tmp_path / "out", use_sumo=True)
    assert report.REFERENCE.read_bytes() == reference  # the shipped reference is untouched
    assert (tmp_path / "out" / "sumo_reference.npz").is_file()
    with pytest.raises(ValueError, match="--update-reference needs SUMO"):
        report.validate(out_dir=tmp_path / "o2", use_sumo=False, update_reference=True)


# ---------------------------------------------------------------------- 7. messages
def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "marlmerge", *args], cwd=cwd, capture_output=True, text=True,
        timeout=300,
    )  # fmt: skip


def test_a_bad_set_value_is_reported_against_the_set_not_the_preset():
    from marlmerge.training.train import load_train_config

    with pytest.raises(ValueError, match=r"^--set lr=-1\.0 \(on quick\.toml\): lr must be"):
        load_train_config("quick", lr=-1.0)


def test_an_unknown_preset_names_the_closest_ones_not_hundreds():
    from marlmerge.config.presets import MAX_LISTED, find_preset, preset_dir

    assert len(list(preset_dir("envs").glob("*.toml"))) > MAX_LISTED
    with pytest.raises(ValueError) as err:
        find_preset("lapse")
    msg = str(err.value)
    assert msg.startswith("unknown scenario preset 'lapse' (the closest: lapses, ")
    assert "presets in" in msg and "heldout3_01" not in msg  # not the whole folder
    with pytest.raises(ValueError, match=r"unknown scenario preset 'zzz' \(\d+ presets in "):
        find_preset("zzz")
    with pytest.raises(ValueError, match=r"unknown training preset 'nope' \(known: .*paper"):
        find_preset("nope", "trainers")  # few enough to list


@pytest.mark.slow
def test_an_unknown_scenario_is_refused_before_the_banner_and_before_any_file(tmp_path):
    out = _cli("train", "quick", "--set", 'scenario="nope"', "--out", "run", cwd=tmp_path)
    assert out.returncode == 2 and "unknown scenario preset 'nope'" in out.stderr
    assert out.stdout == "" and not (tmp_path / "run").exists()


def test_an_unknown_scenario_in_the_python_api_writes_nothing(tmp_path):
    from marlmerge.training.train import TrainConfig, train

    with pytest.raises(ValueError, match="scenario = 'nope'"):
        train(TrainConfig(scenario="nope"), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_a_write_killed_midway_leaves_no_temporary_file_behind(tmp_path):
    target = tmp_path / "checkpoint.pt"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()  # a pid that no longer runs: its temporary file is stale
    (tmp_path / f"checkpoint.pt.tmp{dead.pid}").write_bytes(b"")
    (tmp_path / f"checkpoint.pt.tmp{os.getppid()}").write_bytes(b"")  # a live writer's: kept
    files.save({"a": 1}, target)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "checkpoint.pt",
        f"checkpoint.pt.tmp{os.getppid()}",
    ]


def test_evaluate_refuses_a_bad_scenario_before_importing_torch(tmp_path):
    code = (
        "import sys\n"
        "from marlmerge.cli import main\n"
        "rc = main(['evaluate', 'hold', '--scenario', 'nope'])\n"
        "print(rc, 'torch' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True)
    assert out.stdout.split() == ["2", "False"], out.stderr[-2000:]


def test_evaluate_takes_one_policy_in_the_grids_notation(capsys):
    assert main(["evaluate", "gap@shield", "--episodes", "3", "--worlds", "3"]) == 0
    assert "greedy evaluation on 3 held-out episodes" in capsys.readouterr().out
    assert main(["evaluate", "gap@brave", "--episodes", "3"]) == 2
    assert "unknown modifier @brave" in capsys.readouterr().err
    assert main(["evaluate", "quadq:no/such/run", "--episodes", "3"]) == 2
    assert "no policy.pt in 'no/such/run'" in capsys.readouterr().err


@pytest.mark.parametrize("bad", [None, "abc", [None], float("nan"), True])
def test_a_bad_action_names_the_agent(bad):
    env = parallel_env(control="all")
    env.reset(seed=0)
    actions = {a: np.zeros(1, np.float32) for a in env.agents}
    actions["ramp_0"] = bad
    with pytest.raises(ValueError, match="action of 'ramp_0'"):
        env.step(actions)
    with pytest.raises(ValueError, match="action"):
        _step(RampMergeEnv(), bad)


def _step(env: RampMergeEnv, action) -> None:
    env.reset(seed=0)
    env.step(action)


def test_a_nan_action_for_an_agent_that_is_not_live_is_refused():
    env = parallel_env(control="all")
    env.reset(seed=0)
    idle = [a for a in env.possible_agents if a not in env.agents]
    actions = {a: np.zeros(1, np.float32) for a in env.possible_agents}
    target = idle[0] if idle else "highway_0"
    if not idle:  # every highway agent is live: end one by leaving it out of the roster
        env.agents.remove(target)
    actions[target] = np.array([np.nan], np.float32)
    with pytest.raises(ValueError, match=f"action of '{target}' \\(not live"):
        env.step(actions)


@pytest.mark.parametrize("seed", ["abc", 1.5, -1, True, [1, 2]])
def test_a_seed_that_is_not_a_non_negative_integer_is_refused(seed):
    with pytest.raises(ValueError, match="seed"):
        parallel_env(control="ego").reset(seed=seed)
    with pytest.raises(ValueError, match="seed"):
        RampMergeEnv().reset(seed=seed)
    with pytest.raises(ValueError, match="seed"):
        TrafficCore(ScenarioConfig(), batch_size=1, seed=seed)


def test_a_scenario_path_that_does_not_exist_is_not_the_preset_of_its_name(tmp_path, capsys):
    from marlmerge.config.presets import find_preset

    with pytest.raises(ValueError, match=r"scenario preset file '.*dense\.toml' does not exist"):
        find_preset(tmp_path / "dense.toml")  # not envs/dense.toml
    assert find_preset("envs/dense.toml").name == "dense.toml"  # the preset, from any directory
    assert main(["evaluate", "hold", "--scenario", str(tmp_path / "dense.toml")]) == 2
    assert "does not exist" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["grid", "stress", "render"])
def test_an_out_that_cannot_be_written_is_refused_before_any_work(tmp_path, capsys, command):
    blocker = tmp_path / "file"
    blocker.write_text("")
    out = str(blocker / ("x.gif" if command == "render" else "x"))
    args = {
        "grid": ["grid", "--policy", "hold", "--condition", "light"],
        "stress": ["stress", "hold"],
    }
    argv = args.get(command, ["render", "hold"]) + ["--out", out]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"--out {out!r}: {str(blocker)!r} is not a folder" in err
    assert main(["grid", "--policy", "hold", "--condition", "light", "--out", str(blocker)]) == 2
    assert "exists and is not a folder" in capsys.readouterr().err


@pytest.mark.parametrize(
    "key, value", [("budget_s", -1.0), ("budget_s", float("nan")), ("verify_episodes", 0)]
)
def test_stress_settings_name_the_key_and_the_value(key, value):
    from marlmerge.evaluation.stress import StressSettings

    with pytest.raises(ValueError, match=f"^{key} must be .*, got {value}$"):
        StressSettings(**{key: value})


def test_a_rule_behind_the_left_watching_shield_sees_the_left_lane(capsys):
    from marlmerge.evaluation.registry import parse_policy, scenario_for

    light = ScenarioConfig().replace(name="light")
    assert scenario_for(parse_policy("gap@shield-left"), None, light).ego.observation == "extended"
    assert scenario_for(parse_policy("gap@shield"), None, light) == light
    assert main(["evaluate", "gap@shield-left", "--episodes", "3", "--worlds", "3"]) == 0
    assert "greedy evaluation on 3 held-out episodes" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("files_there", "message"),
    [
        (None, "does not exist"),
        ({}, "has no loss.csv or egos.csv"),
        (
            {"seed_0/egos.csv": "ego,total_reward\n"},
            "the logs are in its seed_* folders: plot each",
        ),
        ({"egos.csv": "ego,phase,total_reward\n"}, "has no column 'acceleration'"),
        ({"loss.csv": "group,step\n"}, "has no column 'update'"),
    ],
)
def test_plot_refuses_a_folder_that_is_not_a_training_run(tmp_path, capsys, files_there, message):
    run = tmp_path / "run"
    for name, text in (files_there or {}).items():
        (run / name).parent.mkdir(parents=True, exist_ok=True)
        (run / name).write_text(text)
    if files_there == {}:
        run.mkdir()
    assert main(["plot", str(run)]) == 2
    err = capsys.readouterr().err
    assert message in err and str(run) in err
    assert not list(tmp_path.rglob("*.png"))  # nothing drawn


@pytest.mark.parametrize("name", ["ego_accel", "ego_join"])
def test_core_commands_that_do_not_fit_the_worlds_name_the_argument(name):
    core = TrafficCore(ScenarioConfig(), batch_size=2, seed=0)
    before = _state(core)
    kwargs = {"ego_accel": np.zeros(2), name: np.zeros(3)}
    with pytest.raises(ValueError, match=f"{name} of shape \\(3,\\) does not fit 2 worlds"):
        core.rollout(**kwargs)
    assert _same(_state(core), before)  # refused before any step


def test_the_gymnasium_env_names_its_own_action_shape():
    env = RampMergeEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action must have shape \(1,\), got shape \(2, 1\)"):
        env.step(np.zeros((2, 1)))
    with pytest.raises(ValueError, match=r"a number or an array of shape \(1,\), got 'a'"):
        env.step("a")


def _vector_env(view: str) -> type:
    if view == "sb3":
        pytest.importorskip("stable_baselines3")
        from marlmerge.views.sb3_env import MergeVecEnv

        return MergeVecEnv
    from marlmerge.views.gym_env import RampMergeVectorEnv

    return RampMergeVectorEnv


@pytest.mark.parametrize("num_envs", [0, -1, 2.5, True])
@pytest.mark.parametrize("view", ["gymnasium", "sb3"])
def test_a_vector_env_without_worlds_is_refused(num_envs, view):
    with pytest.raises(ValueError, match=f"num_envs must be an integer >= 1, got {num_envs!r}"):
        _vector_env(view)(num_envs=num_envs)


def test_a_torchrl_step_without_its_actions_names_the_missing_key():
    from marlmerge.views.torchrl_env import BatchedMergeEnv
    from marlmerge.views.torchrl_groups import MultiAgentMergeEnv

    env = BatchedMergeEnv(num_worlds=2)
    with pytest.raises(KeyError, match="no 'action'.*'observation'"):
        env.step(env.reset())
    env = MultiAgentMergeEnv(num_worlds=2)
    td = env.reset()
    td["action"] = torch.zeros(2, 1)
    with pytest.raises(KeyError, match=r"no \('highway', 'action'\)"):
        env.step(td)


def test_a_dotted_key_below_a_value_says_the_value_is_not_a_table(capsys):
    args = ["train", "paper", "--set", "scenario.traffic.flow_vph_per_lane=5"]
    assert main(args) == 2
    assert "'scenario' is a value, not a table" in capsys.readouterr().err


def _refused_before_any_file(args: list[str], out: Path, message: str, capsys) -> None:
    """`marlmerge ARGS --out OUT` exits with 2, its error holds `message`, and OUT was not
    written."""
    assert main([*args, "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--policy", "gap", "--policy", "gap"], "policy 'gap' is given twice"),
        (["--condition", "default", "--condition", "default"], "condition 'default' is given"),
        (["--condition", "grid_*", "--condition", "grid_dense_mixed"], "'dense mixed' is given"),
    ],
)
def test_the_grid_refuses_a_policy_or_condition_given_twice(tmp_path, capsys, args, message):
    args = ["--policy", "gap", *args] if "--policy" not in args else args
    args = [*args, "--condition", "light"] if "--condition" not in args else args
    _refused_before_any_file(["grid", *args, "--episodes", "1"], tmp_path / "grid", message, capsys)


@pytest.mark.parametrize(
    ("backend", "address", "message"),
    [
        ("serial", "auto", "needs --backend ray"),
        ("ray", "junk", "expected auto, HOST:PORT or ray://HOST:PORT"),
        ("ray", "127.0.0.1:1", "nothing answers there"),
        ("ray", "ray://127.0.0.1:1", "nothing answers there"),
    ],
)
def test_a_ray_address_is_checked_before_any_work(tmp_path, capsys, backend, address, message):
    pytest.importorskip("ray")
    args = ["grid", "--policy", "gap", "--condition", "light", "--episodes", "1"]
    args += ["--backend", backend, "--address", address]
    _refused_before_any_file(args, tmp_path / "grid", message, capsys)


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--method", "mc", "--rounds", "3"], "--rounds 3: the rounds fit the proposal"),
        (["--method", "split", "--round-episodes", "9"], "--method split fits nothing"),
        (["--episodes", "100", "--max-episodes", "50"], "--max-episodes 50 caps a --rel-ci run"),
    ],
)
def test_estimate_refuses_flags_its_method_would_ignore(tmp_path, capsys, flags, message):
    args = ["estimate", "gap", "--scenario", "lapses", *flags]
    _refused_before_any_file(args, tmp_path / "estimate", message, capsys)


def test_an_aec_env_refuses_a_bad_action_at_its_agents_own_turn():
    from marlmerge.views.ramp_flow_env import ramp_flow_env

    env = marlmerge_env()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action of 'ramp_0' must be finite, got nan"):
        env.step(np.array([np.nan]))
    assert env.agent_selection == "ramp_0"  # refused: the turn stays
    env.step(np.zeros(1, dtype=np.float32))
    with pytest.raises(ValueError, match=r"action of 'highway_0' must have shape \(1,\)"):
        env.step(np.zeros(3))
    flow = ramp_flow_env(config="ramp_flow")
    flow.reset(seed=0)
    while not flow.agents:  # ramp agents appear as vehicles enter the ramp
        flow.step(None)
    agent = flow.agent_selection
    with pytest.raises(ValueError, match=f"action of {agent!r} must be finite, got inf"):
        flow.step(np.array([np.inf]))


@pytest.mark.parametrize(
    ("args", "who"),
    [
        (["render", "gap", "--scenario", "ramp_flow", "--episodes", "1"], "render: scenario"),
        (["cotrain", "cotrain", "--set", "scenario=ramp_flow"], "co-training: scenario ="),
        (["estimate", "gap", "--scenario", "ramp_flow", "--method", "mc"], "estimate: scenario"),
    ],
)
def test_ramp_flow_is_refused_where_one_ego_is_followed_before_any_file(
    tmp_path, capsys, args, who
):
    out = tmp_path / ("clip.gif" if args[0] == "render" else "run")
    message = f"{who} 'ramp_flow': ramp.flow_vph = 600.0 runs ramp flow, which has no ego"
    _refused_before_any_file(args, out, message, capsys)


@pytest.mark.parametrize(("episodes", "worlds", "name"), [(0, 4, "episodes"), (4, 0, "worlds")])
def test_greedy_rollouts_refuse_no_episodes_or_no_worlds(episodes, worlds, name):
    from marlmerge.evaluation.registry import policy_from_spec
    from marlmerge.evaluation.rollout import evaluate_policy

    cfg = ScenarioConfig()
    with pytest.raises(ValueError, match=f"{name} must be an integer >= 1, got 0"):
        evaluate_policy(policy_from_spec("gap", cfg), cfg, episodes, 0, worlds)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["rampflow", "gap", "--scenario", "ramp_flow", "--hours", "inf"], "hours must be finite"),
        (["rampflow", "gap", "--scenario", "ramp_flow", "--ramp-flow", "200,200"], "given twice"),
        (["stress", "gap", "--budget-s", "inf"], "budget_s must be finite and > 0, got inf"),
        (["grid", "--policy", "gap", "--condition", "ramp_flow", "--ramp-hours", "inf"], "finite"),
    ],
)
def test_endless_or_repeated_measurements_are_refused(tmp_path, capsys, args, message):
    _refused_before_any_file(args, tmp_path / "out", message, capsys)


def test_view_sizes_and_the_proposal_are_checked_by_type():
    from marlmerge.views.torchrl_env import BatchedMergeEnv

    with pytest.raises(ValueError, match="max_cycles must be an integer >= 1, got 2.5"):
        parallel_env(max_cycles=2.5)
    with pytest.raises(ValueError, match="proposal must be None or a marlmerge.sim.proposal"):
        BatchedMergeEnv(num_worlds=2, proposal="x")


def test_a_grid_cell_is_keyed_by_its_saved_policy_and_its_scenario_as_loaded(tmp_path):
    """A cached grid cell is reused only for the same policy file and scenario: a run trained
    again into the same folder, or a preset edited, gives a new key (and a new result)."""
    from marlmerge.evaluation.grid import Cell, parse_condition
    from marlmerge.evaluation.registry import parse_policy

    run = tmp_path / "run"
    run.mkdir()
    _policy(run).rename(run / "policy.pt")
    preset = tmp_path / "mine.toml"
    preset.write_text("[traffic]\nflow_vph_per_lane = 400.0\n")

    def key() -> str:
        spec = parse_policy(f"quadq:{run}")
        return Cell(spec, str(run), parse_condition(str(preset)), None, 10, 0, 10).key

    first = key()
    assert key() == first
    saved = files.load(run / "policy.pt")
    name = next(iter(saved["policy_state"]["net"]))
    saved["policy_state"]["net"][name] += 1.0  # trained again
    files.save(saved, run / "policy.pt")
    retrained = key()
    assert retrained != first
    preset.write_text("[traffic]\nflow_vph_per_lane = 500.0\n")
    assert key() != retrained


def test_estimate_does_not_resume_onto_a_policy_trained_again(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    _policy(run).rename(run / "policy.pt")
    args = ["estimate", str(run), "--scenario", "light", "--method", "mc", "--episodes", "4"]
    args += ["--worlds", "4", "--out", str(tmp_path / "est")]
    assert main(args) == 0
    assert main(args) == 0  # the same policy: the batches are reused
    saved = files.load(run / "policy.pt")
    name = next(iter(saved["policy_state"]["net"]))
    saved["policy_state"]["net"][name] += 1.0
    files.save(saved, run / "policy.pt")
    assert main(args) == 2
    assert "whose saved policy has changed since" in capsys.readouterr().err
