"""A plain `pip install .` (a wheel, not editable) works: presets ship inside the package."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_wheel_install_trains_and_runs_a_grid_from_another_directory(tmp_path):
    wheels = tmp_path / "wheels"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheels), str(ROOT)],
        check=True,
        timeout=600,
    )
    venv = tmp_path / "venv"
    # the dependencies come from this interpreter's site-packages; marlmerge from the wheel
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True)
    py = venv / "bin" / "python"
    wheel = next(wheels.glob("marlmerge-*.whl"))
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
