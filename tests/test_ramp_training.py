"""Ramp flow in torchrl and in training: the `"ramp"` group, one shared-parameter policy for every
merging vehicle, trained by the one loop, resumed exactly."""

import csv

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from marlmerge.cli import main
from marlmerge.config.training import TrainConfig
from marlmerge.io import files
from marlmerge.training.train import train
from marlmerge.views.ramp_flow_torchrl import RampFlowTorchEnv

OVER = {"ramp.flow_vph": 900.0}
TINY = dict(
    name="tiny_ramp",
    scenario="ramp_flow",
    total_sim_steps=6_400,
    num_worlds=8,
    env_steps_per_batch=4,
    learning_starts=256,
    replay_capacity=5_000,
    update_path="fast",
    checkpoint_every_sim_steps=2_048,
    eval_episodes=0,
)


def _rows(path):
    with open(path, newline="") as fh:
        return list(csv.reader(fh))


def _drive(env: RampFlowTorchEnv, n: int) -> list[torch.Tensor]:
    td, seen = env.reset(), []
    for i in range(n):
        td.set(("ramp", "action"), torch.full((env.num_worlds, env.n_agents, 1), 0.3 * (i % 3)))
        td = env.step(td)["next"]
        seen.append(torch.cat([td["ramp", "observation"].flatten(), td["ramp", "reward"].ravel()]))
    return seen


def test_the_ramp_group_passes_check_env_specs_and_resumes_bit_for_bit():
    env = RampFlowTorchEnv(overrides=OVER, num_worlds=3, seed=1)
    check_env_specs(env)
    wide = RampFlowTorchEnv(overrides={**OVER, "ego.observation": "extended"}, num_worlds=2)
    check_env_specs(wide)  # the agents see the ego's layout
    assert wide.reset()["ramp", "observation"].shape == (2, wide.n_agents, 16)
    _drive(env, 60)
    saved = env.sim_state()
    expected = _drive(env, 80)
    other = RampFlowTorchEnv(overrides=OVER, num_worlds=3, seed=7)
    other.load_sim_state(saved)
    assert all(torch.equal(a, b) for a, b in zip(expected, _drive(other, 80), strict=True))


def test_columns_hold_one_vehicle_until_its_merge_ends():
    env = RampFlowTorchEnv(overrides=OVER, num_worlds=4, seed=2)
    td = env.reset()
    ids = env.table.ids.copy()
    ended = 0
    for _ in range(150):
        td.set(("ramp", "action"), torch.ones((4, 8, 1)))
        nxt = env.step(td)["next"]
        out = nxt["ramp", "outcome"].numpy()
        kept = (ids >= 0) & (out == 0)
        assert np.array_equal(env.table.ids[kept], ids[kept])  # a running merge keeps its column
        assert np.all((out == 0) | (ids >= 0))  # only a held column ends a merge
        assert np.array_equal(nxt["ramp", "terminal"].numpy(), np.isin(out, (1, 2)))
        ended += int((out != 0).sum())
        ids, td = env.table.ids.copy(), nxt
    assert ended >= 20
    td.set(("ramp", "action"), torch.full((4, 8, 1), float("nan")))
    with pytest.raises(ValueError, match=r"action of ramp agent \d+ in world \d+ must be finite"):
        env.step(td)


@pytest.mark.slow
def test_a_ramp_flow_run_trains_every_merging_vehicle_and_resumes_exactly(tmp_path):
    cfg = TrainConfig(**TINY)
    straight = train(cfg, tmp_path / "a", progress=False)
    rows = _rows(tmp_path / "a" / "egos.csv")
    assert straight.egos == len(rows) - 1 > 50  # one row per merging vehicle whose merge ended
    assert {r[3] for r in rows[1:]} <= {"success", "collision", "truncated"}
    train(cfg, tmp_path / "b", progress=False, stop_after_sim_steps=5_120)
    resumed = train(cfg, tmp_path / "b", resume=True, progress=False)
    assert resumed.sim_steps == straight.sim_steps and resumed.updates == straight.updates
    assert rows == _rows(tmp_path / "b" / "egos.csv")
    assert _rows(tmp_path / "a" / "loss.csv") == _rows(tmp_path / "b" / "loss.csv")
    wa = files.load(tmp_path / "a" / "policy.pt")["policy_state"]["net"]
    wb = files.load(tmp_path / "b" / "policy.pt")["policy_state"]["net"]
    assert all(torch.equal(wa[k], wb[k]) for k in wa)


@pytest.mark.slow
def test_the_trained_policy_drives_ramp_flow_and_bad_combinations_are_refused(tmp_path, capsys):
    out = tmp_path / "run"
    values = {**TINY, "eval_episodes": 30, "eval_worlds": 2}
    quote = {k: f'"{v}"' if isinstance(v, str) else v for k, v in values.items()}
    sets = [f"--set={k}={v}" for k, v in quote.items()]
    assert main(["train", "--out", str(out), "--no-progress", *sets]) == 0
    assert "greedy evaluation under ramp flow (600 veh/h on the ramp)" in capsys.readouterr().out
    assert main(["rampflow", str(out), "--hours", "0.05", "--skip", "60", "--worlds", "2"]) == 0
    assert '"driver"' in capsys.readouterr().out.splitlines()[-1]
    assert main(["evaluate", str(out), "--episodes", "30", "--worlds", "2"]) == 0  # as a merge
    evaluated = capsys.readouterr().out.splitlines()
    assert "under ramp flow" in evaluated[-2] and '"merged_vph"' in evaluated[-1]
    assert (
        main(
            [
                "grid",
                "--policy",
                f"quadq:{out}",
                "--condition",
                "ramp_flow",
                "--out",
                str(tmp_path / "grid"),
                "--ramp-hours",
                "0.03",
                "--no-progress",
            ]
        )
        == 0
    )
    summary = (tmp_path / "grid" / "summary.md").read_text()
    assert "## Merge under ramp flow" in summary and "| quadq | run | ramp flow |" in summary
    assert main(["train", "ramp_flow", "--seeds", "0-1", "--out", str(tmp_path / "s")]) != 0
    assert "train its seeds one by one" in capsys.readouterr().err
    mixed = f"{out}=0.5,gap@shield-left=0.5"  # the run sees the paper's layout, the shield more
    assert main(["rampflow", mixed, "--hours", "0.05", "--skip", "60", "--worlds", "2"]) != 0
    err = capsys.readouterr().err
    assert "must see it alike" in err and "'extended'" in err and "'paper'" in err
