"""The figures of the reports: the world model's open-loop frames, PPO's curves, and the simulator success of
PPO's checkpoints along its run."""

from pathlib import Path

import imageio.v3 as iio
import matplotlib
import numpy as np

from lerobot_roboscape.evaluation.results import curve_of
from lerobot_roboscape.pipeline.layout import rl_dir
from lerobot_roboscape.pipeline.methods import RL_MANISKILL, RL_MANISKILL_ONE_SCENE, RL_WORLD_MODEL, Method
from lerobot_roboscape.rl.history import read_ppo_history

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

WM_FIGURE_FRAMES = 8  # open-loop frames shown in the report's picture


def world_model_figure(video: Path, prompt: int, path: Path, steps: int = WM_FIGURE_FRAMES) -> None:
    """Frames of the fidelity video's first episode (real | predicted, every view), one column per open-loop step."""
    frames = iio.imread(video, plugin="pyav")[prompt : prompt + steps]
    iio.imwrite(path, np.kron(np.concatenate(list(frames), 1), np.ones((2, 2, 1), np.uint8)))


def ppo_curves(
    out: Path, policies, path: Path, methods: tuple[str, ...] = (RL_WORLD_MODEL, RL_MANISKILL, RL_MANISKILL_ONE_SCENE)
) -> None:
    """Training success and return of each PPO run against its wall-clock time."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.2))
    for policy in policies:
        for method in methods:
            history = read_ppo_history(out / rl_dir(policy, method))
            if not history:
                continue
            minutes = [row.seconds / 60 for row in history]
            axes[0].plot(minutes, [row.success for row in history], "-o", markersize=3, label=f"{policy}: {method}")
            axes[1].plot(minutes, [row.episode_return for row in history], "-o", markersize=3)
    axes[0].set_ylabel("success in its own env")
    axes[1].set_ylabel("episode return in its own env")
    for ax in axes:
        ax.set_xlabel("wall-clock (min)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def curve_figure(out: Path, policy: str, curve: list[dict], path: Path) -> None:
    """PPO in the world model over its iterations: its return in the world model (left axis), and the simulator
    success of its checkpoints out of domain with 95% intervals (right axis)."""
    history = read_ppo_history(out / rl_dir(policy, RL_WORLD_MODEL))
    fig, left = plt.subplots(figsize=(7, 3.4))
    left.plot(
        [row.iteration for row in history],
        [row.episode_return for row in history],
        color="tab:blue",
        label="return in the world model (training episodes)",
    )
    left.set_xlabel("PPO iteration (0: the SFT checkpoint)")
    left.set_ylabel("world-model return", color="tab:blue")
    right = left.twinx()
    points = curve_of(curve)
    x = [point.iteration for point in points]
    rate = np.array([100 * point.cell.success_rate for point in points])
    ci = 100 * np.array([point.cell.ci95 for point in points])
    right.errorbar(x, rate, yerr=[rate - ci[:, 0], ci[:, 1] - rate], fmt="o-", color="tab:red", capsize=3)
    right.set_ylabel(f"simulator success, OOD (%, {points[0].cell.episodes} episodes)", color="tab:red")
    right.set_ylim(0, 100)
    left.legend(loc="upper left", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def gaming_figure(out: Path, policy: str, curves: dict[str, list[dict]], path: Path) -> None:
    """Each PPO run in the world model (plain and each lever) over PPO's clock: the simulator success of its
    checkpoints out of domain with 95% intervals (solid), beside the success its own world model's done signal
    gives its training episodes (dashed, same colour). A run that games the world model climbs dashed, falls solid."""
    fig, ax = plt.subplots(figsize=(8, 3.8))
    for (method, curve), colour in zip(curves.items(), plt.rcParams["axes.prop_cycle"].by_key()["color"], strict=False):
        points = curve_of(curve)
        minutes = np.array([point.seconds / 60 for point in points])
        rate = np.array([100 * point.cell.success_rate for point in points])
        ci = 100 * np.array([point.cell.ci95 for point in points])
        ax.errorbar(minutes, rate, yerr=[rate - ci[:, 0], ci[:, 1] - rate], fmt="o-", color=colour, capsize=3)
        ax.plot([], [], "-", color=colour, label=Method.named(method).variant or "no lever")
        history = read_ppo_history(out / rl_dir(policy, method))
        ax.plot(
            [row.seconds / 60 for row in history],
            [100 * row.success for row in history],
            "--",
            color=colour,
            alpha=0.6,
        )
    ax.plot([], [], "k-o", label="simulator, OOD (checkpoints)")
    ax.plot([], [], "k--", alpha=0.6, label="world model's own done (training episodes)")
    ax.set_xlabel("PPO's clock (min; 0: the SFT checkpoint)")
    ax.set_ylabel("success (%)")
    ax.set_ylim(0, 100)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
