"""A plain `pip install .` (a wheel, not editable) works: presets ship inside the package."""

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from venvs import child_venv

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_wheel_install_trains_and_runs_a_grid_from_another_directory(tmp_path):
    wheels = tmp_path / "wheels"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheels), str(ROOT)],
        check=True,
        timeout=600,
    )
    venv = tmp_path / "venv"
    # the dependencies come from this interpreter's site-packages; marlmerge from the wheel
    py = child_venv(venv)
    wheel = next(wheels.glob("marlmerge-*.whl"))
    with zipfile.ZipFile(wheel) as zf:  # the committed SUMO sides the validations compare with
        shipped = set(zf.namelist())
    for name in ("sumo_reference.npz", "sumo_merge.json", "sumo_merge_best.json"):
        assert f"marlmerge/validation/reference/{name}" in shipped
    subprocess.run(
        [str(py), "-m", "pip", "install", "-q", "--no-deps", "--force-reinstall", str(wheel)],
        check=True,
        timeout=600,
    )
    work = tmp_path / "elsewhere"
    work.mkdir()

    def run(*args: str) -> str:
        out = subprocess.run(
            [str(py), "-m", "marlmerge", *args], cwd=work, capture_output=True, text=True,
            timeout=900,
        )  # fmt: skip
        assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
        return out.stdout

    where = subprocess.run(
        [str(py), "-c", "import marlmerge; print(marlmerge.__file__)"],
        cwd=work, capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    assert str(venv) in where, where
    run(
        "train", "quick", "--set", "total_sim_steps=2048", "--set", "num_worlds=8",
        "--set", "learning_starts=256", "--set", "update_path=\"fast\"",
        "--set", "eval_episodes=4", "--set", "eval_worlds=4", "--out", "run", "--no-progress",
    )  # fmt: skip
    assert (work / "run" / "policy.pt").exists()
    out = run(
        "grid", "--policy", "hold", "--policy", "quadq:run", "--condition", "grid_light_mixed",
        "--episodes", "2", "--worlds", "2", "--backend", "serial", "--no-progress", "--out", "g",
    )  # fmt: skip
    assert "light mixed" in out and (work / "g" / "episodes.csv").exists()


def test_a_test_venv_sees_the_packages_of_a_venv_that_runs_the_tests(tmp_path):
    """The README's test command inside a user's venv: the test's own venv must reach that venv's
    packages, not the base interpreter's (a package only the outer venv has stands for them)."""
    outer = child_venv(tmp_path / "outer", with_pip=False)
    probe_dir = Path(
        subprocess.run(
            [str(outer), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
            capture_output=True, text=True, check=True,
        ).stdout.strip()
    )  # fmt: skip
    (probe_dir / "only_in_the_outer_venv.py").write_text("VALUE = 42\n")
    inner = child_venv(tmp_path / "inner", with_pip=False, python=str(outer))
    out = subprocess.run(
        [str(inner), "-c", "import only_in_the_outer_venv as m, gymnasium; print(m.VALUE)"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert out.returncode == 0 and out.stdout.strip() == "42", out.stderr[-2000:]
