"""`benchmarks/peak_use.py`: which piece of a several-peak Q drives, counted over the greedy
decisions of a policy file."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import torch

from marlmerge.config import ScenarioConfig, to_dict
from marlmerge.io.policy_file import write_policy
from marlmerge.learners.quadq import QuadraticQNet

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
spec = importlib.util.spec_from_file_location("peak_use", BENCH / "peak_use.py")
pu = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
spec.loader.exec_module(pu)  # type: ignore[union-attr]


def _policy(tmp_path: Path, c_bias: tuple[float, float]) -> Path:
    net = QuadraticQNet(7, 8, generator=torch.Generator().manual_seed(1), peaks=2)
    with torch.no_grad():  # the C heads: constant, piece 0's or piece 1's the larger
        net.head_weight[4:6] = 0.0
        net.head_bias[4:6] = torch.tensor(c_bias)
    state = {"net": net.state_dict(), "hidden": 8, "peaks": 2}
    write_policy(
        tmp_path / "p.pt", "ego", "quadq", (-4.5, 2.5), state, {}, to_dict(ScenarioConfig())
    )
    return tmp_path / "p.pt"


@pytest.mark.parametrize(("c_bias", "piece"), [((1.0, 0.0), 0), ((0.0, 1.0), 1)])
def test_the_piece_with_the_larger_c_drives_every_decision(tmp_path, c_bias, piece):
    r = pu.peak_use(str(_policy(tmp_path, c_bias)), "default", worlds=4, decisions=6, seed=0)
    assert r["share"][piece] == 1.0 and r["share"][1 - piece] == 0.0
    assert 0.0 <= r["brake_share"][piece] <= 1.0 and r["brake_share"][1 - piece] == 0.0
    assert len(r["mean_b_mps2"]) == 2 and r["mean_b_mps2"][0] < r["mean_b_mps2"][1]


def test_a_policy_of_another_algorithm_is_refused_naming_the_file(tmp_path):
    state = {"net": {}, "hidden": 8, "layers": 2}
    write_policy(tmp_path / "t.pt", "ego", "td3", (-4.5, 2.5), state, {}, to_dict(ScenarioConfig()))
    with pytest.raises(ValueError, match="t.pt: a quadq policy is needed, got 'td3'"):
        pu.peak_use(str(tmp_path / "t.pt"), "default", 4, 6, 0)
