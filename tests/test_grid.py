"""The robustness grid at a tiny budget: all outputs written, reproducible, policies parsed."""

import csv

import pytest

from marlmerge.cli import main
from marlmerge.evaluation.grid import default_conditions, expand_conditions, parse_policy, run_grid
from marlmerge.training.train import TrainConfig, train

CONDITIONS = ["grid_light_cooperative", "grid_dense_adversarial"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("run_s0")
    train(
        TrainConfig(
            total_sim_steps=2_048,
            num_worlds=8,
            learning_starts=256,
            update_path="fast",
            eval_episodes=0,
        ),
        out,
        progress=False,
    )
    return out


def _csv(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.slow
def test_a_learned_policy_without_the_left_lane_is_refused_the_left_watch(tmp_path, trained):
    with pytest.raises(ValueError, match="@shield-left reads the left lane, which ego.observat"):
        run_grid(
            [parse_policy(f"paper@shield-left=quadq@shield-left:{trained}")], ["light"],
            episodes=2, out_dir=tmp_path / "g", progress=False,
        )  # fmt: skip
    assert not (tmp_path / "g").exists()  # refused before any file


@pytest.mark.slow
def test_grid_writes_csv_summary_and_heatmaps_reproducibly(tmp_path, trained):
    policies = [parse_policy(p) for p in ("hold", "idm", "gap", f"paper=quadq:{trained}")]
    a = run_grid(policies, CONDITIONS, episodes=4, worlds=4, out_dir=tmp_path / "a", progress=False)
    for name in ("episodes.csv", "summary.md", "heatmap_success.png", "heatmap_collision.png"):
        assert (tmp_path / "a" / name).exists(), name
    rows = _csv(tmp_path / "a" / "episodes.csv")
    assert len(rows) == 4 * 4 * 2 == len(a.rows)
    assert {r["policy"] for r in rows} == {"hold", "idm", "gap", "paper"}
    assert {r["condition"] for r in rows} == {"light cooperative", "dense adversarial"}
    for r in rows:
        assert float(r["success"]) + float(r["collision"]) + float(r["truncation"]) == 1.0
    summary = (tmp_path / "a" / "summary.md").read_text()
    assert "| paper |" in summary and "light cooperative" in summary and "episodes/s" in summary
    run_grid(policies, CONDITIONS, episodes=4, worlds=4, out_dir=tmp_path / "b", progress=False)
    assert _csv(tmp_path / "b" / "episodes.csv") == rows


def test_every_policy_meets_the_same_episodes():
    import numpy as np
    import torch

    from marlmerge.config.presets import resolve_config
    from marlmerge.evaluation.rollout import rollout_first_egos

    scen = resolve_config(CONDITIONS[0])

    def first_samples(policy):
        _, traces = rollout_first_egos(policy, scen, 6, seed=7, worlds=3, record=True)
        return np.array([[t.v_front_mps[0], t.v_back_mps[0], t.v_mps[0]] for t in traces])

    hold = first_samples(lambda obs: torch.zeros(obs.shape[0], 1))
    brake = first_samples(lambda obs: torch.full((obs.shape[0], 1), -2.0))
    # the same roads and ramp vehicles: identical traffic around each ego at the first step...
    assert np.array_equal(hold[:, :2], brake[:, :2], equal_nan=True)
    # ...while the ego's own motion already differs
    assert (brake[:, 2] < hold[:, 2]).all()


def test_rollouts_refuse_what_they_would_ignore():
    import torch

    from marlmerge.config.presets import resolve_config
    from marlmerge.evaluation.rollout import rollout_first_egos

    scen = resolve_config(CONDITIONS[0])
    hold = lambda obs: torch.zeros(obs.shape[0], 1)  # noqa: E731
    highway = lambda obs: torch.zeros(*obs.shape[:2], 1)  # noqa: E731
    # a highway policy drives traffic that no proposal or branch could weigh: refused by name
    with pytest.raises(ValueError, match="lapse_branches: not with a highway policy"):
        rollout_first_egos(hold, scen, 2, seed=0, worlds=2, highway_policy=highway,
                           lapse_branches=[-1, -1])  # fmt: skip
    with pytest.raises(ValueError, match=r"lapse_branches: one per episode \(3\), got 2"):
        rollout_first_egos(hold, scen, 3, seed=0, worlds=3, lapse_branches=[-1, -1])


def test_policy_specs_are_checked():
    assert parse_policy("gap").kind == "gap"
    with pytest.raises(ValueError, match="'tailgate'"):
        parse_policy("tailgate")
    with pytest.raises(ValueError, match="no policy.pt"):
        parse_policy("quadq:/nonexistent/run")
    assert len(default_conditions()) == 12
    assert expand_conditions(["grid_*", "default"]) == default_conditions() + ["default"]
    assert len(expand_conditions(["grid_dense_*"])) == 4
    with pytest.raises(ValueError, match="grid_nothing"):
        expand_conditions(["grid_nothing_*"])


@pytest.mark.slow
def test_cli_grid(tmp_path, capsys):
    assert (
        main(
            [
                "grid",
                "--policy",
                "hold",
                "--condition",
                CONDITIONS[0],
                "--episodes",
                "2",
                "--worlds",
                "2",
                "--out",
                str(tmp_path),
                "--no-progress",
            ]
        )
        == 0
    )
    assert "Success % / collision %" in capsys.readouterr().out


def test_learned_highway_agents_join_the_grid_as_a_condition(tmp_path):
    import torch

    from marlmerge.config import ScenarioConfig
    from marlmerge.evaluation.grid import parse_condition
    from marlmerge.learners.quadq import QuadraticQNet
    from marlmerge.sim.observation import HIGHWAY_FEATURES
    from marlmerge.training.cotrain import CoTrainConfig, load_highway_policy, save_highway_policy

    # a highway policy that brakes at every step: greedy B(s) pinned to the lower bound
    net = QuadraticQNet(12, 64, action_low=-4.5, action_high=2.5)
    with torch.no_grad():
        net.head_weight.zero_()
        net.head_bias[1] = -30.0  # B's pre-squash output -> B ~ -4.5 m/s^2
    for seed in (0, 1):
        (tmp_path / f"adv_s{seed}").mkdir()
        save_highway_policy(
            tmp_path / f"adv_s{seed}" / "highway_policy.pt",
            net.state_dict(),
            CoTrainConfig(ego_init="x", ego_pretrain_sim_steps=0),
            ScenarioConfig(),
            bounds=(-4.5, 2.5),
        )
    # the premise: reloaded with its own bounds, the learned adjustment is -4.5 m/s^2, so the
    # agent (IDM, at most a = 1.5 m/s^2, plus the adjustment) brakes at every step
    obs = torch.rand(3, 4, len(HIGHWAY_FEATURES), generator=torch.Generator().manual_seed(0))
    braking = load_highway_policy(tmp_path / "adv_s0")(obs)
    a_max = ScenarioConfig().driver.accel_mps2
    assert (braking <= a_max - 4.5 + 1e-4).all()
    cond = parse_condition(f"braking=grid_light_cooperative+highway:{tmp_path}/adv_s*")
    assert cond.label == "braking" and len(cond.highway) == 2
    with pytest.raises(ValueError, match="no highway_policy.pt"):
        parse_condition("grid_light_cooperative+highway:/nonexistent/run")
    res = run_grid(
        [parse_policy("hold")],
        ["grid_light_cooperative", cond],
        episodes=4,
        worlds=4,
        out_dir=tmp_path / "g",
        progress=False,
    )
    rows = res.rows
    scripted = [r for r in rows if r["condition"] == "light cooperative"]
    learned = [r for r in rows if r["condition"] == "braking"]
    assert len(scripted) == 4 and len(learned) == 8  # pooled over the two adversary runs
    assert {r["highway"] for r in learned} == {f"{tmp_path}/adv_s0", f"{tmp_path}/adv_s1"}
    # same roads, different drivers: the braking agents change what the ego meets
    assert [r["min_ttc_front_s"] for r in learned[:4]] != [r["min_ttc_front_s"] for r in scripted]
    assert "braking" in (tmp_path / "g" / "summary.md").read_text()


@pytest.mark.slow
def test_a_policy_keeps_its_ego_side_settings_and_the_filter_its_spec_asks_for(tmp_path):
    from marlmerge.config.presets import resolve_config
    from marlmerge.evaluation.registry import scenario_for

    extended = tmp_path / "extended.toml"
    extended.write_text('name = "extended"\n[ego]\nobservation = "extended"\n')
    run = tmp_path / "run"
    train(
        TrainConfig(
            scenario=str(extended), total_sim_steps=1_024, num_worlds=8, learning_starts=256,
            update_path="fast", eval_episodes=0,
        ),
        run,
        progress=False,
    )  # fmt: skip
    condition = resolve_config("grid_dense_adversarial")
    spec = parse_policy(f"quadq:{run}")
    met = scenario_for(spec, str(run), condition)
    assert met.ego.observation == "extended" and not met.ego.safety_filter
    assert met.traffic == condition.traffic and met.name == condition.name  # the same roads
    assert scenario_for(parse_policy(f"quadq@filter:{run}"), str(run), condition).ego.safety_filter
    gap = parse_policy("gap@filter")
    assert gap.name == "gap@filter" and scenario_for(gap, None, condition).ego.safety_filter
    assert scenario_for(parse_policy("gap"), None, condition) == condition
    with pytest.raises(ValueError, match="@careful"):
        parse_policy("gap@careful")
    shielded = parse_policy(f"quadq@shield:{run}")
    assert shielded.shield and shielded.safety_filter is None and shielded.name == "quadq@shield"
    assert not shielded.shield_left
    left = parse_policy(f"quadq@shield-left:{run}")  # the run sees the left lane
    assert left.shield and left.shield_left and left.name == "quadq@shield-left"
    rows = run_grid(
        [parse_policy(f"quadq:{run}"), gap, shielded, left], ["grid_light_mixed"], episodes=2,
        worlds=2, out_dir=tmp_path / "grid", progress=False,
    ).rows  # fmt: skip
    assert {r["policy"] for r in rows} == {
        "quadq",
        "gap@filter",
        "quadq@shield",
        "quadq@shield-left",
    }
    # evaluate and render take the run folder itself in another scenario: its observation kept
    from marlmerge.cli import main

    assert main(["evaluate", str(run), "--scenario", "light", "--episodes", "2"]) == 0
    gif = tmp_path / "run.gif"
    assert (
        main(["render", f"quadq@shield-left:{run}", "--scenario", "light", "--out", str(gif)]) == 0
    )
    assert gif.stat().st_size > 0


def test_a_sensing_condition_keeps_the_roads_and_changes_the_sensor():
    from marlmerge.evaluation.grid import parse_condition

    specs = expand_conditions(["grid_dense_*+sensing:sensing_realistic"])
    assert len(specs) == 4 and all(s.endswith("+sensing:sensing_realistic") for s in specs)
    plain = parse_condition(expand_conditions(["grid_dense_mixed"])[0])
    noisy = parse_condition(specs[-1])
    assert noisy.label == "dense mixed + sensing"
    a, b = plain.scenario(), noisy.scenario()
    assert a.name == b.name and a.traffic == b.traffic and a.driver == b.driver
    assert b.sensing.occlusion and b.sensing.position_noise_std_m > 0 and not a.sensing.active
    with pytest.raises(ValueError, match="no_such_sensor"):
        parse_condition("grid_dense_mixed+sensing:no_such_sensor")


def test_the_grid_adds_importance_sampled_collision_rates(tmp_path, capsys):
    """`--estimator is`: each cell's rate with its interval and ESS in summary.md, from
    estimates kept per cell and reused by a rerun."""
    argv = ["grid", "--policy", "hold", "--condition", "grid_dense_adversarial"]
    argv += ["--episodes", "40", "--worlds", "20", "--out", str(tmp_path), "--no-progress"]
    assert main([*argv, "--estimator", "is", "--backend", "serial"]) == 0
    summary = (tmp_path / "summary.md").read_text()
    assert "Collision % by importance sampling" in summary
    line = next(row for row in summary.splitlines() if row.startswith("| hold |") and "ESS" in row)
    assert "[" in line and "–" in line
    (estimate,) = tmp_path.glob("cells/*.is.json")
    before = estimate.read_text()
    capsys.readouterr()
    assert main([*argv, "--estimator", "is", "--backend", "serial"]) == 0
    table = summary.split("## Collision % by importance sampling")[1]
    assert estimate.read_text() == before
    assert (tmp_path / "summary.md").read_text().split("## Collision % by importance sampling")[
        1
    ] == table
    with pytest.raises(SystemExit):
        main([*argv, "--estimator", "bayes"])


def test_the_worst_cells_in_the_summary_carry_their_intervals():
    from marlmerge.evaluation.grid import _by_cell, _overall_table, _runs_table

    def row(run: str, cond: str, ok: bool) -> dict:
        return {"policy": "p", "run": f"runs/{run}", "condition": cond, "success": float(ok),
                "collision": float(not ok), "truncation": 0.0, "time_to_merge_s": 10.0,
                "max_abs_jerk_mps3": 5.0}  # fmt: skip

    rows = [row("r1", "a", True)] * 10 + [row("r2", "a", True)] * 10
    rows += [row("r1", "b", i < 9) for i in range(10)] + [row("r2", "b", i < 5) for i in range(10)]
    overall = _overall_table(rows, _by_cell(rows), ["p"], ["a", "b"])[2]
    assert "| b: 70.0 [48.1–85.5] | r2 in b: 50.0 [23.7–76.3] |" in overall  # Wilson, 14/20, 5/10
    runs = _runs_table(rows, ["p"], ["a", "b"])
    assert runs[4].endswith("| b: 90.0 [59.6–98.2] |") and runs[5].endswith(
        "| b: 50.0 [23.7–76.3] |"
    )
