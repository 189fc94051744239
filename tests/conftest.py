import os
import shutil
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from filelock import FileLock

from lerobot_roboscape.dataset.reader import open_dataset
from lerobot_roboscape.demos.collect import CollectConfig, collect
from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig

IMAGE_SIZE = 32
# Session fixtures that run the simulator (a collection, a recorded file) or a command; a test using one is slow.
SLOW_FIXTURES = {"demo_dataset", "exploration_dataset", "recorded", "mlp_checkpoint", "act_checkpoint", "control_set"}


# Modules whose module-scoped fixtures run for minutes (the demo killed at every boundary, the synthetic worlds
# trained to solve them): under pytest-xdist they start first, on different workers, so the workers end together.
LONGEST_MODULES = ("tests/pipeline/test_demo.py", "tests/world_model/test_synthetic.py")

if os.environ.get("PYTEST_XDIST_WORKER"):
    # A worker per core: one thread each (and in the commands they start), so workers do not compete for cores.
    import torch

    os.environ["OMP_NUM_THREADS"] = "1"
    torch.set_num_threads(1)


def pytest_collection_modifyitems(config, items):
    import torch

    def rank(item):
        path = item.nodeid.split("::")[0]
        return LONGEST_MODULES.index(path) if path in LONGEST_MODULES else len(LONGEST_MODULES)

    items.sort(key=rank)  # stable: every other module keeps its order
    for item in items:
        if SLOW_FIXTURES & set(item.fixturenames):
            item.add_marker(pytest.mark.slow)
        if item.get_closest_marker("gpu") and not torch.cuda.is_available():
            item.add_marker(pytest.mark.skip(reason="needs a CUDA GPU"))


def built_once(tmp_path_factory, name: str, build: Callable[[Path], object]) -> Path:
    """Folder `name`, filled by `build(folder)` once per test session: under pytest-xdist the first worker that asks
    builds it and the others wait for it and read it, so no two workers pay for the same simulator run or training."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # shared by the workers of this session
    folder, built = root / name, root / f"{name}.built"
    with FileLock(root / f"{name}.lock"):
        if not built.exists():
            shutil.rmtree(folder, ignore_errors=True)  # what a worker's failed build left
            folder.mkdir(parents=True)
            build(folder)
            built.touch()
    return folder


@pytest.fixture(scope="session")
def demo_dataset(tmp_path_factory):
    """A small real collection: two families on one scene, one optimal, one suboptimal and one deliberately failed
    episode each (episodes 0-2 pick and place, 3-5 push; the failed ones are 2 and 3), with the object's and the
    container's masks."""
    cfg = CollectConfig(
        repo_id="test/demos",
        root="",
        families=["pick_place", "push"],
        max_scenes=1,
        episodes_per_scene=3,
        failed_fraction=1 / 3,
        suboptimal_fraction=0.5,
        image_size=IMAGE_SIZE,
        workers=2,
        seed=3,
        segmentation=True,
    )
    root = built_once(tmp_path_factory, "collect", lambda out: collect(replace(cfg, root=str(out / "demos")))) / "demos"
    return open_dataset(cfg.repo_id, root), root


@pytest.fixture(scope="session")
def exploration_dataset(tmp_path_factory):
    """Exploratory episodes in a dataset of their own, in the scene of `demo_dataset`: each kind (noisy,
    excursion, random) once per family."""
    cfg = CollectConfig(
        repo_id="test/explore",
        root="",
        families=["pick_place", "push"],
        max_scenes=1,
        episodes_per_scene=3,
        kinds=["noisy", "excursion", "random"],
        image_size=IMAGE_SIZE,
        workers=1,  # in this process (demo_dataset covers the workers' pool)
        seed=11,
    )
    root = built_once(tmp_path_factory, "explore", lambda out: collect(replace(cfg, root=str(out / "explore"))))
    return open_dataset(cfg.repo_id, root / "explore"), root / "explore"


def record_maniskill_file(out_dir, obs_mode="rgb", episodes=2, steps=6, env_id="PickCube-v1") -> Path:
    """Trajectory file written by ManiSkill's own RecordEpisode wrapper (random actions)."""
    import mani_skill.envs  # noqa: F401  registers PickCube-v1
    from mani_skill.utils.wrappers.record import RecordEpisode

    env = gym.make(
        env_id,
        obs_mode=obs_mode,
        control_mode="pd_ee_delta_pose",
        max_episode_steps=steps,
        sensor_configs=dict(width=IMAGE_SIZE, height=IMAGE_SIZE),
    )
    env = RecordEpisode(
        env,
        str(out_dir),
        save_trajectory=True,
        trajectory_name="traj",
        save_video=False,
        source_type="test",
        source_desc="random actions",
    )
    rng = np.random.default_rng(0)
    for k in range(episodes):
        env.reset(seed=k)
        for _ in range(steps + k):  # episodes of different lengths; the time limit ends each at `steps`
            _, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 7).astype(np.float32))
            if bool(terminated.any()) or bool(truncated.any()):
                break
    env.close()
    return out_dir / "traj.h5"


# Tokenizer for the tests' 32 px views: 4x4 codes of 6 bits per view, so a frame of two views has 32 tokens.
TEST_TOKENIZER = dict(image_size=IMAGE_SIZE, base_channels=8, channel_multipliers=(1, 2, 2, 2), codebook_bits=6)


@pytest.fixture(scope="session")
def trained_tokenizer(demo_dataset, tmp_path_factory):
    """Directory of a tokenizer trained for a few steps on `demo_dataset` (through the real training loop)."""
    from lerobot.configs.default import DatasetConfig

    from lerobot_roboscape.tokenizer.configuration_tokenizer import TinyTokenizerConfig
    from lerobot_roboscape.tokenizer.train import TrainTokenizerConfig, train_tokenizer
    from lerobot_roboscape.training.checkpoints import FINAL
    from lerobot_roboscape.training.loop import TrainingConfig

    _, root = demo_dataset
    cfg = TrainTokenizerConfig(
        dataset=DatasetConfig(repo_id="test/demos", root=str(root)),
        tokenizer=TinyTokenizerConfig(**TEST_TOKENIZER),
        train=TrainingConfig(steps=8, batch_size=8, save_freq=8, log_freq=4, eval_freq=4),
        heldout=DatasetConfig(repo_id="test/demos", root=str(root), episodes=[1, 3]),
        num_workers=0,
        allow_random_lpips=True,
    )
    return built_once(tmp_path_factory, "tokenizer", lambda out: train_tokenizer(replace(cfg, output_dir=out))) / FINAL


@pytest.fixture(scope="session")
def token_cache(demo_dataset, trained_tokenizer, tmp_path_factory):
    from lerobot.configs.default import DatasetConfig

    from lerobot_roboscape.world_model.train import prepare_token_cache

    _, root = demo_dataset
    dataset = DatasetConfig(repo_id="test/demos", root=str(root))
    folder = built_once(tmp_path_factory, "token_cache", partial(prepare_token_cache, dataset, str(trained_tokenizer)))
    return prepare_token_cache(dataset, str(trained_tokenizer), folder)[0]  # built: read


# A world model small enough to train in seconds on the tests' token cache.
TEST_WM_ARGS = [
    "--wm.d_model=64",
    "--wm.n_head=2",
    "--wm.n_layer=2",
    "--wm.window=4",
    "--wm.prompt_frames=1",
    "--train.batch_size=4",
    "--train.log_freq=5",
    "--train.warmup_steps=5",
    "--train.mixed_precision=no",
]


@pytest.fixture(scope="session")
def world_models(demo_dataset, trained_tokenizer, token_cache, tmp_path_factory):
    """{"action": dir, "text": dir} of tiny world models trained for a few steps on `demo_dataset`."""
    import draccus

    from lerobot_roboscape.training.checkpoints import FINAL
    from lerobot_roboscape.world_model.train import TrainWorldModelConfig, train_world_model

    _, root = demo_dataset
    dirs = {}
    for control in ("action", "text"):
        args = [
            "--dataset.repo_id=test/demos",
            f"--dataset.root={root}",
            f"--tokenizer={trained_tokenizer}",
            f"--token_cache={token_cache.root}",
            f"--wm.control={control}",
            "--train.steps=20",
            "--train.save_freq=20",
            *TEST_WM_ARGS,
        ]

        def train(out, args=args):
            train_world_model(draccus.parse(TrainWorldModelConfig, args=[*args, f"--output_dir={out}"]))

        dirs[control] = built_once(tmp_path_factory, f"wm_{control}", train) / FINAL
    return dirs


def lerobot_train(root, out, steps, *policy_args, repo_id: str = "test/demos") -> Path:
    """Run `lerobot-train` on `demo_dataset` (or the dataset `repo_id` at `root`) in a subprocess; returns the last
    checkpoint's pretrained_model."""
    import subprocess
    import sys

    cmd = [
        sys.executable,
        "-m",
        "lerobot.scripts.lerobot_train",
        f"--dataset.repo_id={repo_id}",
        f"--dataset.root={root}",
        "--policy.device=cpu",
        "--policy.push_to_hub=false",
        f"--steps={steps}",
        "--batch_size=2",
        "--num_workers=0",
        f"--save_freq={steps}",
        f"--output_dir={out}",
        *policy_args,
    ]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    return last_checkpoint(out, steps)


def last_checkpoint(out: Path, steps: int) -> Path:
    """The pretrained_model of a lerobot-train run into `out` that ended after `steps` steps."""
    return out / "checkpoints" / f"{steps:06d}" / "pretrained_model"


def lerobot_train_once(tmp_path_factory, name: str, root, steps: int, *policy_args) -> Path:
    """`lerobot_train` into folder `name`, once per test session (`built_once`)."""
    folder = built_once(tmp_path_factory, name, lambda out: lerobot_train(root, out / "train", steps, *policy_args))
    return last_checkpoint(folder / "train", steps)


def roboscape_wm_args(root, tokenizer, world_models) -> list[str]:
    """`--env.*` arguments of LeRobot's commands for `roboscape_wm` on the test models (k = 4) and data."""
    return [
        "--env.type=roboscape_wm",
        "--env.dataset_repo_id=test/demos",
        f"--env.dataset_root={root}",
        f"--env.tokenizer={tokenizer}",
        f"--env.action_world_model={world_models['action']}",
        f"--env.text_world_model={world_models['text']}",
        f"--env.image_size={IMAGE_SIZE}",
        "--env.allow_random_lpips=true",
        "--env.episode_length=9",  # two model frames and a partial chunk
        "--env.max_goal_steps=4",
    ]


@pytest.fixture(scope="session")
def act_checkpoint(demo_dataset, tmp_path_factory):
    """LeRobot's ACT policy after two lerobot-train steps on `demo_dataset`."""
    _, root = demo_dataset
    return lerobot_train_once(
        tmp_path_factory,
        "act",
        root,
        2,
        "--policy.type=act",
        "--policy.pretrained_backbone_weights=null",
        "--policy.dim_model=32",
        "--policy.n_encoder_layers=1",
        "--policy.n_decoder_layers=1",
        "--policy.chunk_size=4",
        "--policy.n_action_steps=4",
    )


@pytest.fixture(scope="session")
def mlp_checkpoint(demo_dataset, tmp_path_factory):
    """The roboscape_mlp policy after a few lerobot-train steps on `demo_dataset`, evaluated in
    roboscape_maniskill at the end of training (lerobot-train's periodic evaluation)."""
    _, root = demo_dataset
    return lerobot_train_once(
        tmp_path_factory,
        "mlp",
        root,
        4,
        "--policy.type=roboscape_mlp",
        "--policy.hidden_dim=32",
        "--policy.image_feature_dim=32",
        "--env_eval_freq=4",
        "--env.type=roboscape_maniskill",
        f"--env.image_size={IMAGE_SIZE}",
        "--env.episode_length=2",
        "--eval.n_episodes=1",
        "--eval.batch_size=1",
    )


@pytest.fixture
def env_config(demo_dataset, trained_tokenizer, world_models):
    """A `roboscape_wm` config on the test models and data, with small horizons; overrides as keywords."""
    _, root = demo_dataset

    def make(**overrides):
        kwargs = dict(
            dataset_repo_id="test/demos",
            dataset_root=str(root),
            tokenizer=str(trained_tokenizer),
            action_world_model=str(world_models["action"]),
            text_world_model=str(world_models["text"]),
            image_size=IMAGE_SIZE,
            allow_random_lpips=True,
            episode_length=6,
            max_goal_steps=4,
        )
        return RoboscapeWorldModelEnvConfig(**{**kwargs, **overrides})

    return make
