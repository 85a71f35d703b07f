"""The paper's figures regenerated from a run's logs (`loss.csv`, `egos.csv`).

- `fig3_loss.png`: training loss (logged every 5 updates) against updates, raw and moving average.
- `fig4_total_reward.png`: the single total reward of every ego against its index.
- `fig5_reward_terms.png`: the four components (acceleration, distance to gap-front, distance to
  gap-back, speed) per ego; the collision term is drawn on the total only.

    marlmerge plot runs/paper
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

TERM_TITLES = {
    "acceleration": "single_total_reward_acce",
    "gap_front": "single_total_reward_dis_to_front",
    "gap_back": "single_total_reward_dis_to_back",
    "speed": "single_total_reward_speed",
}


def moving_average(x: np.ndarray, window: int) -> np.ndarray:
    """Trailing mean over up to `window` points (shorter at the start), same length as x."""
    if x.size == 0:
        return x
    c = np.cumsum(np.insert(x.astype(np.float64), 0, 0.0))
    idx = np.arange(1, x.size + 1)
    lo = np.maximum(idx - window, 0)
    return (c[idx] - c[lo]) / (idx - lo)


def _read(path: Path) -> dict[str, np.ndarray]:
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        return {}
    out = {}
    for key in rows[0]:
        col = [r[key] for r in rows]
        try:
            out[key] = np.array(col, dtype=np.float64)
        except ValueError:
            out[key] = np.array(col)
    return out


def _raw_and_average(
    ax, x: np.ndarray, y: np.ndarray, window: int, label: str | None, unit: str
) -> None:
    """Raw points faint, their trailing moving average bold."""
    ax.plot(x, y, lw=0.3, alpha=0.35, color="tab:blue", label=label)
    ax.plot(
        x,
        moving_average(y, window),
        color="tab:red",
        label=f"moving average ({window} {unit})" if label else None,
    )


LOSS_COLUMNS = ("update", "loss")
EGO_COLUMNS = ("ego", "total_reward", *TERM_TITLES)


def check_run_logs(run: Path) -> None:
    """Refuse, naming the folder, a run folder that is missing or has neither log (a `--seeds`
    run's parent: name its `seed_*` folders), or a log without the columns the figures draw."""
    if not run.is_dir():
        raise ValueError(f"plot: run folder {str(run)!r} does not exist")
    logs = [run / name for name in ("loss.csv", "egos.csv") if (run / name).is_file()]
    if not logs:
        seeds = sorted(p.parent for p in run.glob("seed_*/egos.csv"))
        hint = (
            f" (the logs are in its seed_* folders: plot each, e.g. {str(seeds[0])!r})"
            if seeds
            else ""
        )
        raise ValueError(
            f"plot: {str(run)!r} has no loss.csv or egos.csv: not a training run's folder{hint}"
        )
    for path in logs:
        with path.open(newline="") as fh:
            header = next(csv.reader(fh), [])
        need = LOSS_COLUMNS if path.name == "loss.csv" else EGO_COLUMNS
        missing = [c for c in need if c not in header]
        if missing:
            raise ValueError(
                f"plot: {str(path)!r} has no column {missing[0]!r} "
                "(plot draws the logs of a `marlmerge train` run)"
            )


def plot_run(run_dir: str | Path) -> list[Path]:
    """Write the three figures into `run_dir`; returns their paths. A folder that is not a
    training run's is refused first (`check_run_logs`)."""
    run = Path(run_dir)
    check_run_logs(run)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    loss = _read(run / "loss.csv") if (run / "loss.csv").exists() else {}
    egos = _read(run / "egos.csv") if (run / "egos.csv").exists() else {}
    ego_window = max(10, egos["total_reward"].size // 50) if egos else 10
    written = []

    def save(fig, name: str) -> None:
        fig.tight_layout()
        written.append(run / name)
        fig.savefig(written[-1], dpi=120)
        plt.close(fig)

    fig, ax = plt.subplots(figsize=(8, 4))
    if loss:
        _raw_and_average(
            ax, loss["update"], loss["loss"], max(10, loss["loss"].size // 100), "loss", "points"
        )
        ax.set_yscale("log")
        ax.legend()
    ax.set(xlabel="gradient update", ylabel="TD loss", title="Fig. 3: training loss")
    save(fig, "fig3_loss.png")

    fig, ax = plt.subplots(figsize=(8, 4))
    if egos:
        _raw_and_average(
            ax, egos["ego"], egos["total_reward"], ego_window, "single total reward", "egos"
        )
        ax.legend()
    ax.set(
        xlabel="ramp vehicle (ego) index",
        ylabel="total reward",
        title="Fig. 4: single total reward of each ramp vehicle",
    )
    save(fig, "fig4_total_reward.png")

    fig, axes = plt.subplots(2, 2, figsize=(10, 6), sharex=True)
    for ax, (term, title) in zip(axes.ravel(), TERM_TITLES.items(), strict=True):
        if egos:
            _raw_and_average(ax, egos["ego"], egos[term], ego_window, None, "egos")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("ego index")
    fig.suptitle("Fig. 5: reward components per ramp vehicle")
    save(fig, "fig5_reward_terms.png")
    return written
