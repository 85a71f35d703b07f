"""The one policy file format: what it stores, what it refuses, and files of 0.2."""

import pytest
import torch

from marlmerge.config import ScenarioConfig, to_dict
from marlmerge.evaluation.registry import parse_policy
from marlmerge.io import files
from marlmerge.io.policy_file import VERSION, read_policy, write_policy
from marlmerge.learners.loading import load_policy
from marlmerge.learners.quadq import QuadraticQNet
from marlmerge.sim.observation import EGO_FEATURES

SCEN = to_dict(ScenarioConfig())


def _net(low=-4.5, high=2.5):
    return QuadraticQNet(7, 16, action_low=low, action_high=high, generator=torch.Generator())


def test_a_policy_file_names_its_algorithm_observation_bounds_and_config(tmp_path):
    net = _net(-2.0, 1.0)
    state = {"net": net.state_dict(), "hidden": 16}
    write_policy(tmp_path / "p.pt", "ego", "quadq", (-2.0, 1.0), state, {"hidden": 16}, SCEN)
    saved = read_policy(tmp_path / "p.pt", "ego")
    assert saved["version"] == VERSION and saved["algorithm"] == "quadq"
    assert saved["observation"] == {"features": [f.name for f in EGO_FEATURES], "size": 7}
    assert saved["action_bounds_mps2"] == [-2.0, 1.0] and saved["config"] == {"hidden": 16}
    obs = torch.rand(64, 7, generator=torch.Generator().manual_seed(0)) * 3
    # reloaded with its own bounds, not the scenario's (-4.5, 2.5)
    assert torch.equal(load_policy(tmp_path / "p.pt")(obs), net.greedy(obs).detach())


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"version": VERSION + 1}, "newer marlmerge"),
        ({"group": "highway"}, "a highway policy, not a ego policy"),
        ({"observation": {"features": ["x"], "size": 1}}, "retrain it"),
        ({"format": "other"}, "not a marlmerge policy file"),
    ],
)
def test_foreign_newer_or_mismatched_files_are_refused(tmp_path, change, message):
    write_policy(tmp_path / "p.pt", "ego", "quadq", (-4.5, 2.5), {"net": {}}, {}, SCEN)
    saved = files.load(tmp_path / "p.pt")
    files.save({**saved, **change}, tmp_path / "p.pt")
    with pytest.raises(ValueError, match=message):
        read_policy(tmp_path / "p.pt", "ego")


def test_policy_files_of_0_2_still_load(tmp_path):
    net = _net()
    old = {
        "algorithm": "quadq",
        "config": {"hidden": 16},
        "scenario": SCEN,
        "net": net.state_dict(),
    }
    files.save(old, tmp_path / "policy.pt")
    obs = torch.rand(8, 7, generator=torch.Generator().manual_seed(1))
    assert torch.equal(load_policy(tmp_path)(obs), net.greedy(obs).detach())
    assert read_policy(tmp_path, "ego")["version"] == 0


def test_a_kind_in_a_grid_spec_must_match_the_file(tmp_path):
    state = {"net": _net().state_dict(), "hidden": 16}
    (tmp_path / "run").mkdir()
    write_policy(tmp_path / "run" / "policy.pt", "ego", "quadq", (-4.5, 2.5), state, {}, SCEN)
    assert parse_policy(f"quadq:{tmp_path}/run").runs == (f"{tmp_path}/run",)
    with pytest.raises(ValueError, match="holds a quadq policy"):
        parse_policy(f"td3:{tmp_path}/run")
