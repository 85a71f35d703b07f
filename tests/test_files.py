"""Saved files hold tensors and plain data only: loading one never runs code from it."""

from collections import OrderedDict

import numpy as np
import pytest
import torch

from marlmerge.cli import main
from marlmerge.io import files
from marlmerge.learners.loading import load_policy

RAN = []


def _mark_ran(*args):
    RAN.append(args)


class Payload:
    """Unpickling this calls `_mark_ran`: what a malicious file would do."""

    def __reduce__(self):
        return (_mark_ran, ("code from a file",))


def test_round_trip_keeps_arrays_tensors_and_dict_types(tmp_path):
    data = {
        "vi": np.arange(6, dtype=np.int32).reshape(2, 3),
        "vf": np.linspace(0, 1, 5),
        "scalar": np.float64(2.5),
        "net": OrderedDict(w=torch.ones(2)),
        "rows": [1, (2, 3), "a"],
    }
    files.save(data, tmp_path / "f.pt")
    back = files.load(tmp_path / "f.pt")
    assert back["vi"].dtype == np.int32 and np.array_equal(back["vi"], data["vi"])
    assert np.array_equal(back["vf"], data["vf"]) and back["scalar"] == 2.5
    assert isinstance(back["net"], OrderedDict) and torch.equal(back["net"]["w"], torch.ones(2))
    assert back["rows"] == [1, (2, 3), "a"]


def test_a_file_carrying_a_pickled_object_is_refused_without_running_it(tmp_path):
    torch.save({"algorithm": "quadq", "net": Payload()}, tmp_path / "policy.pt")
    with pytest.raises(ValueError, match=r"policy\.pt: refused to load.*could run code"):
        load_policy(tmp_path / "policy.pt")
    assert RAN == []


@pytest.mark.parametrize("damage", ["empty", "truncated"])
def test_a_damaged_checkpoint_is_a_clear_error_naming_the_file(tmp_path, damage, capsys):
    run = tmp_path / "run"
    run.mkdir()
    files.save({"config": {}}, run / "checkpoint.pt")
    raw = (run / "checkpoint.pt").read_bytes()
    (run / "checkpoint.pt").write_bytes(b"" if damage == "empty" else raw[: len(raw) // 2])
    assert main(["train", "quick", "--out", str(run), "--resume", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "checkpoint.pt: not a readable checkpoint" in err
