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


def plot_run(run_dir: str | Path) -> list[Path]:
    """Write the three figures into `run_dir`; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = Path(run_dir)
    written = []
    loss = _read(run / "loss.csv") if (run / "loss.csv").exists() else {}
    egos = _read(run / "egos.csv") if (run / "egos.csv").exists() else {}

    fig, ax = plt.subplots(figsize=(8, 4))
    if loss:
        ax.plot(loss["update"], loss["loss"], lw=0.3, alpha=0.35, color="tab:blue", label="loss")
        window = max(10, loss["loss"].size // 100)
        ax.plot(
            loss["update"],
            moving_average(loss["loss"], window),
            color="tab:red",
            label=f"moving average ({window} points)",
        )
        ax.set_yscale("log")
        ax.legend()
    ax.set_xlabel("gradient update")
    ax.set_ylabel("TD loss")
    ax.set_title("Fig. 3: training loss")
    fig.tight_layout()
    written.append(run / "fig3_loss.png")
    fig.savefig(written[-1], dpi=120)
    plt.close(fig)

    window = max(10, egos["total_reward"].size // 50) if egos else 10
    fig, ax = plt.subplots(figsize=(8, 4))
    if egos:
        ax.plot(
            egos["ego"],
            egos["total_reward"],
            lw=0.3,
            alpha=0.35,
            color="tab:blue",
            label="single total reward",
        )
        ax.plot(
            egos["ego"],
            moving_average(egos["total_reward"], window),
            color="tab:red",
            label=f"moving average ({window} egos)",
        )
        ax.legend()
    ax.set_xlabel("ramp vehicle (ego) index")
    ax.set_ylabel("total reward")
    ax.set_title("Fig. 4: single total reward of each ramp vehicle")
    fig.tight_layout()
    written.append(run / "fig4_total_reward.png")
    fig.savefig(written[-1], dpi=120)
    plt.close(fig)

    fig, axes = plt.subplots(2, 2, figsize=(10, 6), sharex=True)
    for ax, (term, title) in zip(axes.ravel(), TERM_TITLES.items(), strict=True):
        if egos:
            ax.plot(egos["ego"], egos[term], lw=0.3, alpha=0.35, color="tab:blue")
            ax.plot(egos["ego"], moving_average(egos[term], window), color="tab:red")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("ego index")
    fig.suptitle("Fig. 5: reward components per ramp vehicle")
    fig.tight_layout()
    written.append(run / "fig5_reward_terms.png")
    fig.savefig(written[-1], dpi=120)
    plt.close(fig)
    return written
