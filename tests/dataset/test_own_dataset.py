"""A user's own LeRobot dataset (issue 101): layouts unlike the bench's, written by `LeRobotDataset.create` as
`lerobot-record` writes them (no `next.success`, no roboscape facts), train the tokenizer and both world models and
serve `roboscape_wm` with the dataset's own camera keys and widths."""

from dataclasses import dataclass, replace

import draccus
import numpy as np
import pytest
from lerobot.configs.default import DatasetConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_roboscape.dataset.reader import open_dataset, read_episode, read_layout
from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.tokenizer.configuration_tokenizer import TinyTokenizerConfig
from lerobot_roboscape.tokenizer.train import TrainTokenizerConfig, train_tokenizer
from lerobot_roboscape.training.checkpoints import FINAL
from lerobot_roboscape.training.loop import TrainingConfig
from lerobot_roboscape.world_model.train import TrainWorldModelConfig, train_world_model
from roboscape_core.errors import InvalidInputError
from tests.conftest import TEST_TOKENIZER, TEST_WM_ARGS, lerobot_train


@dataclass(frozen=True)
class Layout:
    cameras: tuple[str, ...]  # dataset keys
    side: int
    action_dim: int
    state_dim: int  # 0: no observation.state
    done: bool  # a next.done column


LAYOUTS = {
    # LeRobot's PushT: one camera under its own key, 96 px, 2-D state and action, no done column.
    "pusht": Layout(("observation.image",), 96, 2, 2, False),
    # ALOHA's: three cameras, two arms' 14-D actions and states, lerobot-record's next.done.
    "aloha": Layout(tuple(f"observation.images.{c}" for c in ("top", "left_wrist", "right_wrist")), 32, 14, 14, True),
    # a camera-only recording: no state, no done.
    "camera_only": Layout(("observation.images.front",), 32, 7, 0, False),
}


def write_dataset(root, layout: Layout, episodes: int = 3, length: int = 12) -> None:
    features = {
        key: {"dtype": "video", "shape": (layout.side, layout.side, 3), "names": ["height", "width", "channel"]}
        for key in layout.cameras
    }
    features["action"] = {"dtype": "float32", "shape": (layout.action_dim,), "names": None}
    if layout.state_dim:
        features["observation.state"] = {"dtype": "float32", "shape": (layout.state_dim,), "names": None}
    if layout.done:
        features["next.done"] = {"dtype": "bool", "shape": (1,), "names": None}
    dataset = LeRobotDataset.create("user/own", fps=10, root=root, features=features, use_videos=True)
    rng = np.random.default_rng(0)
    for _ in range(episodes):
        for t in range(length):
            frame = {key: rng.integers(0, 255, (layout.side, layout.side, 3), dtype=np.uint8) for key in layout.cameras}
            frame["action"] = rng.uniform(-1, 1, layout.action_dim).astype(np.float32)
            if layout.state_dim:
                frame["observation.state"] = rng.normal(size=layout.state_dim).astype(np.float32)
            if layout.done:
                frame["next.done"] = np.array([t == length - 1])
            dataset.add_frame(frame | {"task": "do the task"})
        dataset.save_episode()
    dataset.finalize()


def train_tiny_tokenizer(root, side: int, output_dir, repo_id: str = "user/own") -> None:
    """One step of the tests' tokenizer at the dataset's image size, through the real training loop."""
    train_tokenizer(
        TrainTokenizerConfig(
            dataset=DatasetConfig(repo_id=repo_id, root=str(root)),
            tokenizer=TinyTokenizerConfig(**(TEST_TOKENIZER | {"image_size": side})),
            train=TrainingConfig(steps=1, batch_size=4, save_freq=1, log_freq=1),
            output_dir=output_dir,
            num_workers=0,
            allow_random_lpips=True,
        )
    )


def wm_args(root, tokenizer, layout: Layout, control: str, out, cache) -> list[str]:
    args = [
        "--dataset.repo_id=user/own",
        f"--dataset.root={root}",
        f"--tokenizer={tokenizer}",
        f"--cache_dir={cache}",
        f"--wm.control={control}",
        f"--output_dir={out}",
        "--train.steps=2",
        "--train.save_freq=2",
        *TEST_WM_ARGS,
    ]
    if not layout.done:
        args.append("--wm.done_weight=0")
    if not layout.state_dim:
        args.append("--wm.state=false")
    return args


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(LAYOUTS))
def test_a_users_dataset_trains_both_models_and_serves_roboscape_wm(name, tmp_path):
    layout, root = LAYOUTS[name], tmp_path / "dataset"
    write_dataset(root, layout)
    read = read_layout(root)
    assert (read.image_size, read.action_dim, read.state_dim) == (layout.side, layout.action_dim, layout.state_dim)
    assert sorted(read.cameras.values()) == sorted(layout.cameras)
    episode = read_episode(open_dataset("user/own", root), 0)
    assert episode.has_done_labels == layout.done and episode.state.shape == (12, layout.state_dim)

    train_tiny_tokenizer(root, layout.side, tmp_path / "tokenizer")
    models = {}
    for control in ("action", "text"):
        out = tmp_path / f"wm_{control}"
        args = wm_args(root, tmp_path / "tokenizer" / FINAL, layout, control, out, tmp_path / "cache")
        train_world_model(draccus.parse(TrainWorldModelConfig, args=args))
        models[control] = out / FINAL

    env_cfg = RoboscapeWorldModelEnvConfig(
        dataset_repo_id="user/own",
        dataset_root=str(root),
        tokenizer=str(tmp_path / "tokenizer" / FINAL),
        action_world_model=str(models["action"]),
        text_world_model=str(models["text"]),
        split="",
        similarity="tokenizer",
        episode_length=8,
        max_goal_steps=4,
    )
    # LeRobot maps each of the env's views back to the dataset's own key, which a policy trained on it reads.
    assert sorted(v for k, v in env_cfg.features_map.items() if k.startswith("pixels")) == sorted(layout.cameras)
    assert env_cfg.features["action"].shape == (layout.action_dim,)
    env = env_cfg.create_envs(2)[env_cfg.type][0]
    observation, info = env.reset(seed=0)
    pixels = observation["pixels"]
    if layout.cameras == ("observation.image",):  # LeRobot's one-camera layout: one array, as LeRobot's envs give
        assert set(env_cfg.features) == {"action", "pixels"} and isinstance(pixels, np.ndarray)
        pixels = {"image": pixels}
    assert {f"pixels/{cam}" for cam in pixels} <= {k for k in env_cfg.features if "pixels/" in k} | {"pixels/image"}
    assert len(pixels) == len(layout.cameras)
    assert all(image.shape == (2, layout.side, layout.side, 3) for image in pixels.values())
    assert env.single_action_space.shape == (layout.action_dim,) and info["task"] == ["do the task"] * 2
    total = np.zeros(2)
    for _ in range(8):
        _, reward, _, truncated, _ = env.step(np.zeros((2, layout.action_dim), np.float32))
        total += reward
    assert truncated.all() and np.isfinite(total).all()
    env.close()


@pytest.mark.slow
def test_a_missing_column_is_one_line_naming_the_dataset_the_column_and_the_flag(tmp_path):
    layout, root = LAYOUTS["camera_only"], tmp_path / "dataset"
    write_dataset(root, layout, episodes=2, length=6)
    train_tiny_tokenizer(root, layout.side, tmp_path / "tokenizer")
    args = wm_args(root, tmp_path / "tokenizer" / FINAL, replace(layout, done=True), "action", tmp_path / "a", tmp_path)
    with pytest.raises(
        InvalidInputError,
        match=rf"dataset {root} has no 'next.success' or 'next.done' column.*"
        r"--wm.done_weight=0",
    ):
        train_world_model(draccus.parse(TrainWorldModelConfig, args=[a for a in args if a != "--wm.state=false"]))
    args = wm_args(
        root, tmp_path / "tokenizer" / FINAL, replace(layout, state_dim=2), "action", tmp_path / "b", tmp_path
    )
    with pytest.raises(InvalidInputError, match=r"no 'observation.state' column.*--wm.state=false"):
        train_world_model(draccus.parse(TrainWorldModelConfig, args=args))


def record_pusht(root, episodes: int = 3, length: int = 12) -> None:
    """LeRobot's PushT layout recorded from gym-pusht (the package LeRobot's pusht env runs) with a random policy:
    one 96 px camera under `observation.image`, the agent's 2-D position as state, 2-D actions in pixels, and the
    reward, done and success columns of LeRobot's pusht dataset."""
    import gym_pusht  # noqa: F401  (registers gym_pusht/PushT-v0)
    import gymnasium as gym

    features = {
        "observation.image": {"dtype": "video", "shape": (96, 96, 3), "names": ["height", "width", "channel"]},
        "observation.state": {"dtype": "float32", "shape": (2,), "names": None},
        "action": {"dtype": "float32", "shape": (2,), "names": None},
        "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
    }
    env = gym.make("gym_pusht/PushT-v0", obs_type="pixels_agent_pos", observation_width=96, observation_height=96)
    dataset = LeRobotDataset.create("user/pusht", fps=10, root=root, features=features, use_videos=True)
    for episode in range(episodes):
        observation, _ = env.reset(seed=episode)
        for t in range(length):
            action = env.action_space.sample().astype(np.float32)
            following, reward, terminated, _, info = env.step(action)
            done = terminated or t == length - 1
            dataset.add_frame(
                {
                    "observation.image": observation["pixels"],
                    "observation.state": observation["agent_pos"].astype(np.float32),
                    "action": action,
                    "next.reward": np.array([reward], np.float32),
                    "next.done": np.array([done]),
                    "next.success": np.array([bool(info["is_success"])]),
                    "task": "Push the T-shaped block onto the T-shaped target.",
                }
            )
            observation = following
            if done:
                break
        dataset.save_episode()
    dataset.finalize()
    env.close()


@pytest.mark.slow
def test_a_pusht_recording_trains_both_models_and_lerobot_trains_and_evaluates_in_roboscape_wm(tmp_path):
    """gym-pusht recorded in LeRobot's pusht layout through every stage: the tokenizer, both world models with their
    done heads (from next.success), and LeRobot's own commands on the models they give: lerobot-train's periodic
    evaluation and lerobot-eval, both in roboscape_wm."""
    import json
    import subprocess
    import sys

    root = tmp_path / "pusht"
    record_pusht(root)
    assert read_layout(root).cameras == {"image": "observation.image"}
    train_tiny_tokenizer(root, 96, tmp_path / "tokenizer", repo_id="user/pusht")
    models = {}
    for control in ("action", "text"):
        out = tmp_path / f"wm_{control}"
        args = wm_args(root, tmp_path / "tokenizer" / FINAL, LAYOUTS["pusht"], control, out, tmp_path / "cache")
        args = [a for a in args if a != "--wm.done_weight=0"]  # pusht has its success labels: the done head trains
        # A random policy's episodes fail: keep them all (the models' defaults learn from successes only).
        args += ["--dataset.repo_id=user/pusht", "--only_optimal=false", "--only_successful=false"]
        train_world_model(draccus.parse(TrainWorldModelConfig, args=args))
        models[control] = out / FINAL
    env_args = [
        "--env.type=roboscape_wm",
        "--env.dataset_repo_id=user/pusht",
        f"--env.dataset_root={root}",
        f"--env.tokenizer={tmp_path / 'tokenizer' / FINAL}",
        f"--env.action_world_model={models['action']}",
        f"--env.text_world_model={models['text']}",
        "--env.split=",
        "--env.similarity=tokenizer",
        "--env.episode_length=8",
        "--env.max_goal_steps=4",
    ]
    policy = lerobot_train(
        root,
        tmp_path / "train",
        2,
        "--policy.type=roboscape_mlp",
        "--policy.hidden_dim=32",
        "--policy.image_feature_dim=32",
        "--env_eval_freq=2",
        "--eval.n_episodes=1",
        "--eval.batch_size=1",
        *env_args,
        repo_id="user/pusht",
    )
    assert len(list((tmp_path / "train" / "eval" / "videos_step_000002").rglob("*.mp4"))) == 1
    evaluate = [
        sys.executable,
        "-m",
        "lerobot.scripts.lerobot_eval",
        f"--policy.path={policy}",
        "--policy.device=cpu",
        "--eval.n_episodes=2",
        "--eval.batch_size=2",
        f"--output_dir={tmp_path / 'eval'}",
        *env_args,
    ]
    result = subprocess.run(evaluate, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    assert json.loads((tmp_path / "eval" / "eval_info.json").read_text())["overall"]["n_episodes"] == 2
