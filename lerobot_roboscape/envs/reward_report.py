"""Reward report (the paper's Fig. 3 and its comparison of rewards): every reward type of `roboscape_wm` along
recorded trajectories, and how well each one's episode return separates successful from failed episodes.

Frames are the dataset's own, read through the tokenizer (as the env's frames are), or (`--frames=open_loop`) those
the action model generates from each episode's first frame under its recorded actions; the world-model reward uses
the goal the text model generates for the episode's first frame, and the env's done source (the action model's
head or the success classifier) reads the real frames (teacher forcing); the action model gives the embedding
features. As in the env (Algorithm 1), an episode is scored over its family's fixed horizon: past the recording's
end its last frame holds, and so does each reward.

The goals are checked too: whether the text model reached done within the family's horizon from each start, and,
for the successful episodes, whether the goal is nearer the episode's real final frame than its start frame, by
the similarity in use (a grid shows start, goal and real final frame).
"""

import dataclasses
import json
import logging
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import matplotlib
import numpy as np
import torch
from lerobot.configs.default import DatasetConfig
from torchmetrics.functional.classification import binary_auroc

from lerobot_roboscape.dataset.reader import open_dataset, read_episode
from lerobot_roboscape.envs.batched import EpisodeBook
from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.envs.goal_bank import EpisodeStart, Goal
from lerobot_roboscape.envs.loading import load_reward_model
from lerobot_roboscape.envs.world_model_env import RoboscapeWorldModelEnv
from lerobot_roboscape.io.templates import render_report
from lerobot_roboscape.world_model.clips import model_frames
from roboscape_core.errors import InvalidInputError

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

REPORT_JSON = "reward_report.json"


def read_reward_report(folder: Path) -> dict:
    """The report `write_reward_report` wrote into `folder`."""
    return json.loads((Path(folder) / REPORT_JSON).read_text())


def results_entry(report: dict) -> dict:
    """What a run's results.json keeps of a reward report: each reward's return reading, the goals', the
    similarity."""
    return {"reward": report["summary"], "goals": report["goals"], "similarity": report["similarity"]}


logger = logging.getLogger(__name__)
FRAMES = ("real", "open_loop")


@dataclass
class RewardReportConfig:
    """Args:
    env: the roboscape_wm settings (models, thresholds, weights, similarity); its dataset is the one reported on.
    dataset: held-out episodes, IND and OOD, successful and failed (--dataset.episodes to pick some).
    embedding_reward: embedding-based reward model to include (optional).
    proxy_reward: proxy-based reward model to include (optional).
    output_dir: where reward_report.json, reward_report.md and reward_curves.png go.
    max_episodes: episodes reported, at most.
    plot_episodes: successful episodes drawn in the figure.
    grid_episodes: successful episodes in the picture of goals (start, goal, real final frame).
    frames: "real": the episodes' own frames through the tokenizer, the done head reading them (teacher forced);
        "open_loop": frames the action model generates from each episode's first frame and its recorded actions,
        as `roboscape_wm` would show them to a policy that took those actions (the rule-based reward stays the
        recording's).
    """

    env: RoboscapeWorldModelEnvConfig = field(default_factory=RoboscapeWorldModelEnvConfig)
    dataset: DatasetConfig = field(default_factory=lambda: DatasetConfig(repo_id="local/roboscape"))
    embedding_reward: str | None = None
    proxy_reward: str | None = None
    output_dir: Path = Path("outputs/reward_report")
    max_episodes: int = 16
    plot_episodes: int = 4
    grid_episodes: int = 8
    frames: str = "real"

    def __post_init__(self):
        if self.frames not in FRAMES:
            raise InvalidInputError(f"frames must be one of {FRAMES}, got {self.frames!r}")


@torch.no_grad()
def teacher_forced_done(
    env: RoboscapeWorldModelEnv, tokens_TS: torch.Tensor, actions: torch.Tensor, states_TD: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Done probability (T,) of known model frames of one episode, and the action model's features (T, C) of
    them, as the action model reads them one after the other (actions ((T - 1) * k, A), one per control step;
    states (T, D) of the frames, for a model with a state channel)."""
    states = None if states_TD is None else states_TD[None]
    with env.autocast():
        done, features = env.action_model.teacher_forced(tokens_TS[None], actions[None], states=states)
    return env.done_of(tokens_TS, done[0]), features[0]


@torch.no_grad()
def replay_rewards(
    env: RoboscapeWorldModelEnv, episode_index: int, tokens_TS: torch.Tensor, done_T: torch.Tensor
) -> tuple[np.ndarray, bool]:
    """The world-model reward `env` pays along given model frames from one of its starts, as if the action
    model had predicted them: frames (T, S) tokens, the first being the start, one per `frame_skip` control
    steps, and the done signal of each (T,). As in the env's `step`, a frame is paid at the last step of its chunk and
    the steps between are paid 0; past the last frame, it holds (with its done) until the start's horizon.
    Returns the rewards of the horizon's control steps (0 after an early termination) and whether the episode
    succeeded."""
    start = next(s for s in env.starts if s.episode_index == episode_index)
    k, steps = env.frame_skip, np.arange(1, start.horizon + 1)
    shown = np.minimum(steps // k, len(tokens_TS) - 1)  # the model frame seen after each control step
    paid = steps % k == 0
    goal = env.decode(env.goal_bank.goals_for([start])[0])
    per_step = []
    for chunk in np.array_split(shown, -(-len(shown) // 64)):  # bounded memory for long horizons
        frames = env.decode(tokens_TS[chunk])
        with env.autocast():
            parts = env.reward_fn(frames, goal.expand_as(frames), done_T[chunk])
        per_step.append(parts.reward.cpu().numpy())
    per_step, done = np.where(paid, np.concatenate(per_step), 0.0), done_T[shown].cpu().numpy()
    book = EpisodeBook(np.array([start.horizon]), env.config.terminate_on_success, env.reward_fn.max_step_reward)
    rewards = np.array(
        [book.step(per_step[t : t + 1], done[t : t + 1] >= env.config.theta)[0] for t in range(start.horizon)]
    )
    return rewards, bool(book.succeeded[0])


@torch.no_grad()
def episode_rewards(
    env: RoboscapeWorldModelEnv, episode, models: dict, open_loop: bool = False
) -> dict[str, np.ndarray]:
    """Every reward type along one recorded episode, step by step over its horizon. The world model reads the
    episode's model frames (every k-th step; `open_loop`: the frames it generates from the first one under the
    recorded actions instead); its reward is what the env pays (at each chunk's last step), the others are read at
    the model frame seen after each step (the last one holds)."""
    indices = model_frames(len(episode.action), env.frame_skip)
    frames = {cam: episode.images[cam][indices] for cam in env.cameras}
    tokens = env.encode(frames)  # (T, S), T model frames
    actions = torch.from_numpy(episode.action[: (len(indices) - 1) * env.frame_skip]).to(env.device)
    states = torch.from_numpy(episode.state[indices]).to(env.device) if env.action_model.config.state else None
    if open_loop and len(tokens) > 1:
        with env.autocast():
            first_state = None if states is None else states[None, :1]
            generated = env.action_model.generate(
                tokens[None, :1], len(tokens) - 1, actions=actions[None], states=first_state
            )
        tokens = torch.cat([tokens[:1], generated.tokens[0]])
        states = None if states is None else torch.cat([states[:1], generated.state[0].to(states.dtype)])
    start = next(s for s in env.starts if s.episode_index == episode.index)
    goal_tokens, _ = env.goal_bank.goals_for([start])
    decoded = env.decode(tokens)  # (T, n, 3, H, W)
    goal = env.decode(goal_tokens).expand(len(tokens), -1, -1, -1, -1)
    done, features = teacher_forced_done(env, tokens, actions, states)
    world_model, _ = replay_rewards(env, episode.index, tokens, done)
    per_frame = {
        "world_model_dense": env.reward_fn(decoded, goal, done).dense,
        "rule_based": torch.from_numpy(episode.reward_label[indices]),
    }
    if "embedding" in models:
        per_frame["embedding"] = models["embedding"](features)
    if "proxy" in models:
        per_frame["proxy"] = models["proxy"](decoded)
    held = np.minimum(np.arange(1, start.horizon + 1) // env.frame_skip, len(tokens) - 1)
    return {"world_model": world_model} | {k: v.float().cpu().numpy()[held] for k, v in per_frame.items()}


@torch.no_grad()
def goal_check(env: RoboscapeWorldModelEnv, episode, other: Goal | None = None) -> tuple[dict, torch.Tensor]:
    """The goal of the episode's start, judged against its real start and final frames, and (`other`: the goal made
    from the same start under another family's instruction) whether the real final frame is nearer its own goal
    than that one; and the three images (3, n, 3, H, W): start, goal, real final frame, as the env decodes them."""
    start = next(s for s in env.starts if s.episode_index == episode.index)
    goal = env.goal_bank.goal_of(start)
    images = env.decode(torch.stack([start.first_tokens, goal.tokens, start.last_tokens]))
    goal_image = images[1:2].expand(2, -1, -1, -1, -1)
    to_start, to_final = env.reward_fn(images[[0, 2]], goal_image, torch.zeros(2, device=env.device)).distance.tolist()
    to_other = None
    if other is not None:
        other_image = env.decode(other.tokens[None])
        to_other = env.reward_fn(images[2:3], other_image, torch.zeros(1, device=env.device)).distance.item()
    check = {
        "reached": goal.reached,
        "steps": goal.steps,
        "horizon": start.horizon,
        "reached_within_horizon": goal.reached and goal.steps <= start.horizon,
        "distance_to_start": to_start,
        "distance_to_final": to_final,
        "nearer_final_than_start": to_final < to_start,
        "distance_of_final_to_other_instructions_goal": to_other,
        "final_nearer_own_goal_than_other_instructions": None if other is None else to_final < to_other,
    }
    return check, images


def other_family_starts(env: RoboscapeWorldModelEnv, indices: list[int]) -> dict[int, EpisodeStart]:
    """Each start of `indices` given the instruction of a start of another task family (the first of that family
    in the dataset; none when the env holds one family)."""
    by_family = {}
    for s in env.starts:
        by_family.setdefault(s.family, s)
    out = {}
    for s in (s for s in env.starts if s.episode_index in indices):
        other = next((o for family, o in by_family.items() if family != s.family), None)
        if other is not None:
            out[s.episode_index] = dataclasses.replace(s, task=other.task)
    return out


def write_reward_report(cfg: RewardReportConfig) -> dict:
    cfg.env.dataset_repo_id, cfg.env.dataset_root = cfg.dataset.repo_id, cfg.dataset.root
    env = RoboscapeWorldModelEnv(cfg.env, num_envs=1)
    dataset = open_dataset(cfg.dataset.repo_id, cfg.dataset.root, cfg.dataset.episodes)
    models = {
        kind: load_reward_model(path, env.device)
        for kind, path in (("embedding", cfg.embedding_reward), ("proxy", cfg.proxy_reward))
        if path
    }
    selected = [
        s.episode_index for s in env.starts if cfg.dataset.episodes is None or s.episode_index in cfg.dataset.episodes
    ][: cfg.max_episodes]
    env.goal_bank.goals_for([s for s in env.starts if s.episode_index in selected])  # in full batches, not one by one
    swapped = other_family_starts(env, selected)
    other_goals = dict(zip(swapped, env.goal_bank.generate(list(swapped.values())), strict=True))
    episodes, grid = [], []
    for index in selected:
        episode = read_episode(dataset, index)
        rewards = episode_rewards(env, episode, models, open_loop=cfg.frames == "open_loop")
        goal, images = goal_check(env, episode, other_goals.get(index))
        success = bool(episode.done_label.max() > 0.5)
        episodes.append(
            {
                "episode_index": index,
                "task": episode.task,
                "split": episode.info.get("split", ""),
                "success": success,
                "goal": goal,
                "rewards": rewards,
            }
        )
        if success and len(grid) < cfg.grid_episodes:
            grid.append(images)
    success = np.array([e["success"] for e in episodes])
    summary, goals = _separation(episodes, success), _goal_summary(episodes)
    report = {
        "config": json.loads(json.dumps(asdict(cfg), default=str)),
        "summary": summary,
        "goals": goals,
        "similarity": env.similarity,
        "done_source": cfg.env.done_source,
        "theta": cfg.env.theta,
        "episodes": [{**e, "rewards": {k: v.tolist() for k, v in e["rewards"].items()}} for e in episodes],
    }
    out = Path(cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / REPORT_JSON).write_text(json.dumps(report, indent=2))
    (out / "reward_report.md").write_text(markdown(report, len(episodes), int(success.sum())))
    _plot(
        [e for e in episodes if e["success"]][: cfg.plot_episodes] or episodes[: cfg.plot_episodes],
        out / "reward_curves.png",
    )
    if grid:
        _plot_goals(torch.stack(grid), out / "goal_grid.png")
    return report


def _separation(episodes: list[dict], success: np.ndarray) -> dict:
    """Per reward: how well its return separates successful episodes from failed ones (ROC-AUC; None with one
    class only) and its mean return on each."""
    summary = {}
    for kind in episodes[0]["rewards"]:
        returns = np.array([e["rewards"][kind].sum() for e in episodes])
        auc = None
        if 0 < success.sum() < len(success):
            # binary_auroc squashes scores outside [0, 1] with a sigmoid, which ties every return above ~17 at 1.0
            # (an AUC of 0.5): hand it the returns' ranks scaled into [0, 1], which keeps their order.
            ranks = torch.from_numpy(returns).argsort().argsort().float() / max(len(returns) - 1, 1)
            auc = float(binary_auroc(ranks, torch.from_numpy(success.astype(np.int64))))
        summary[kind] = {
            "roc_auc_of_return": auc,
            "mean_return_success": _mean(returns[success]),
            "mean_return_failure": _mean(returns[~success]),
        }
    return summary


def _goal_summary(episodes: list[dict]) -> dict:
    """How the text model's goals did: reached within the horizon, nearer the real success than the start, nearer
    the episode's own goal than other instructions' (on the successful episodes)."""
    successful = [e["goal"] for e in episodes if e["success"]]
    own = [g["final_nearer_own_goal_than_other_instructions"] for g in successful]
    return {
        "starts": len(episodes),
        "reached_within_horizon": float(np.mean([e["goal"]["reached_within_horizon"] for e in episodes])),
        "successful_starts": len(successful),
        "nearer_final_than_start": float(np.mean([g["nearer_final_than_start"] for g in successful]))
        if successful
        else None,
        "final_nearer_own_goal_than_other_instructions": _mean(np.array(own, dtype=float))
        if successful and all(value is not None for value in own)
        else None,
    }


def _plot_goals(images: torch.Tensor, path: Path) -> None:
    """(N, 3, n, 3, H, W) start, goal, real final frame per episode -> a grid: a row per episode, the three
    images side by side, views stacked."""
    N, _, n, _, H, W = images.shape
    grid = images.permute(0, 2, 4, 1, 5, 3).reshape(N * n * H, 3 * W, 3)  # rows: episode, view, y; cols: image, x
    fig, ax = plt.subplots(figsize=(3 * 1.2, N * n * 1.2))
    ax.imshow(grid.clamp(0, 1).cpu().numpy())
    ax.set_xticks([W / 2, 3 * W / 2, 5 * W / 2], ["start", "goal (text model)", "real final"], fontsize=7)
    ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _mean(values: np.ndarray) -> float | None:
    return float(values.mean()) if len(values) else None


def headline(report: dict) -> str:
    """The report in one line, for a run's console: each reward's ROC-AUC of the return."""
    return ", ".join(f"{kind} {auc_text(s)}" for kind, s in report["summary"].items())


def auc_text(summary: dict) -> str:
    """A reward's ROC-AUC of the return in words: why there is none where there is none."""
    if summary["roc_auc_of_return"] is None:
        return "ROC-AUC not defined (the episodes are all successes or all failures)"
    return f"ROC-AUC {summary['roc_auc_of_return']:.3f}"


def markdown(report: dict, episodes: int, successes: int) -> str:
    return render_report("reward_report.md", report=report, episodes=episodes, successes=successes)


def _plot(episodes: list[dict], path: Path) -> None:
    fig, axes = plt.subplots(1, len(episodes), figsize=(4 * len(episodes), 3), squeeze=False)
    for ax, episode in zip(axes[0], episodes, strict=True):
        for kind, values in episode["rewards"].items():
            span = values.max() - values.min()
            ax.plot((values - values.min()) / span if span > 0 else values * 0, label=kind)  # each scaled to [0, 1]
        ax.set_title(f"ep {episode['episode_index']} {episode['split']}: {episode['task'][:32]}", fontsize=8)
        ax.set_xlabel("step")
    axes[0][0].set_ylabel("reward (scaled to [0, 1])")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_rollout_rewards(rewards: np.ndarray, tasks: Sequence[str], path: Path) -> None:
    """The reward curve of each episode of a rollout, `rewards` of shape (steps, episodes), labelled by its task."""
    fig, ax = plt.subplots(figsize=(6, 3))
    for curve, task in zip(rewards.T, tasks, strict=True):
        ax.plot(curve, label=task)
    ax.set_xlabel("step")
    ax.set_ylabel("reward")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
