"""LeRobot's own command lines (`lerobot-train`, `lerobot-eval`) run from the pipeline: SFT on the successful
demonstrations, and evaluation in a LeRobot env, each in a subprocess, resumed as the stages are."""

import subprocess
import sys
from pathlib import Path

from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.dataset.reader import demonstrations_per_scene, open_dataset
from lerobot_roboscape.pipeline.resume import run_once
from lerobot_roboscape.training.checkpoints import publish_final
from roboscape_core.errors import InvalidInputError


def run_lerobot(script: str, args: list[str]) -> None:
    """A LeRobot command line (`lerobot_train`, `lerobot_eval`) in a subprocess with its own progress display."""
    result = subprocess.run([sys.executable, "-m", f"lerobot.scripts.{script}", *args], stdout=subprocess.DEVNULL)
    if result.returncode != 0:
        raise RuntimeError(f"{script} {' '.join(args)} failed with exit code {result.returncode}")


def sft_episodes(dataset: DatasetConfig, per_scene: int | None = None, scenes: list[str] | None = None) -> list[int]:
    """The episodes SFT imitates: the successful ones (the failed attempts are there for the world model), the
    first `per_scene` of each family and scene (None: all), in `scenes` (None: every scene)."""
    episodes = demonstrations_per_scene(open_dataset(dataset.repo_id, dataset.root), per_scene, scenes)
    if not episodes:
        where = f" in scenes {scenes}" if scenes is not None else ""
        raise InvalidInputError(f"no successful episode{where} in dataset {dataset.root or dataset.repo_id} to imitate")
    return episodes


def lerobot_sft(
    output_dir: Path,
    dataset: DatasetConfig,
    policy_args: list[str],
    steps: int,
    batch_size: int,
    num_workers: int = 2,
    fresh: bool = False,
    per_scene: int | None = None,
    save_freq: int | None = None,
    scenes: list[str] | None = None,
) -> Path:
    """SFT with `lerobot-train` on the dataset's successful episodes (the first `per_scene` of each family and
    scene; None: all) in `scenes` (None: every scene), a checkpoint every `save_freq` steps (None: at the end);
    returns the final model's directory, output_dir/pretrained_model as of every trainer."""
    episodes = sft_episodes(dataset, per_scene, scenes)
    args = [
        f"--dataset.repo_id={dataset.repo_id}",
        *([f"--dataset.root={dataset.root}"] if dataset.root else []),
        f"--dataset.episodes=[{','.join(map(str, episodes))}]",
        *policy_args,
        "--policy.push_to_hub=false",
        f"--steps={steps}",
        f"--batch_size={batch_size}",
        f"--save_freq={save_freq or steps}",
        f"--log_freq={max(steps // 5, 1)}",
        f"--num_workers={num_workers}",
        f"--output_dir={output_dir}",
    ]
    run_once(output_dir, args, fresh, lambda: run_lerobot("lerobot_train", args))
    return publish_final(output_dir)


def lerobot_eval(
    output_dir: Path,
    policy_path: Path,
    env_args: list[str],
    n_episodes: int,
    batch_size: int,
    fresh: bool = False,
) -> Path:
    """Evaluation with `lerobot-eval` of the policy in the env of `env_args`; returns its eval_info.json."""
    args = [
        f"--policy.path={policy_path}",
        *env_args,
        f"--eval.n_episodes={n_episodes}",
        f"--eval.batch_size={batch_size}",
        f"--output_dir={output_dir}",
    ]
    run_once(output_dir, args, fresh, lambda: run_lerobot("lerobot_eval", args))
    return output_dir / "eval_info.json"
