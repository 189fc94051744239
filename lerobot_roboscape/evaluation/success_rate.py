"""`roboscape-eval`: success rate of a policy in `roboscape_maniskill`, per split (IND: training scenes with new
initial states; OOD: held-out scenes) and task family, with 95% Wilson intervals and videos."""

import json
import logging
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig
from lerobot_roboscape.evaluation.results import ALL, Cell
from lerobot_roboscape.io.atomic import write_text_atomically
from lerobot_roboscape.io.templates import render_report
from lerobot_roboscape.rl.policy_loading import PolicyIO, check_policy_fits_env, load_policy
from lerobot_roboscape.tasks import TASK_FAMILIES, select_scenes
from lerobot_roboscape.training.loop import resolve_device
from lerobot_roboscape.training.records import write_video
from roboscape_core.errors import InvalidInputError, OutputExistsError

EVAL_JSON = "eval.json"


def read_cells(folder: Path, split: str) -> dict[str, Cell]:
    """{family (and "all"): cell} of `split` in the evaluation `evaluate_success` wrote into `folder`."""
    cells = json.loads((Path(folder) / EVAL_JSON).read_text())["splits"][split]
    return {family: Cell.from_json(cell) for family, cell in cells.items()}


logger = logging.getLogger(__name__)
SPLITS = "splits"  # each split's result, written when the split is complete


@dataclass
class EvalConfig:
    """Args:
    policy_path: the policy (a pretrained_model directory or a Hub repo id).
    families: task families (empty: all four).
    splits: "ind" and/or "ood".
    scenes: scene ids each split is narrowed to (empty: all its scenes). The paper's IND is the scene the policy
        learned with new initial states: `--splits=[ind] --scenes=[red_cube-plate-wooden]`.
    episodes: episodes per (split, family).
    batch_size: parallel episodes (families are dealt to them in turn).
    episode_length: steps before an episode counts as failed; null: per task family, its registered time limit
        (or the longest successful demonstration in `dataset_root`, when given).
    dataset_repo_id: demonstrations whose episode lengths set the per-family horizons (optional).
    dataset_root: their local directory.
    image_size: camera image side (0: the policy's).
    seed: seed of the initial states; the datasets' episodes use small seeds, so the default is far from them.
    videos: episodes recorded per split (the first batch's), one file each, named with its family and outcome:
        videos/<split>/<k>_<family>_<success|failure>.mp4.
    workers: simulator processes the batch is spread over (null: one per CPU core).
    output_dir: eval.json, eval.md and videos/ (and splits/, each split's result as soon as it is complete).
    device: "auto", "cpu" or "cuda".
    resume: continue an interrupted evaluation in output_dir, keeping the splits it completed.
    """

    policy_path: str = ""
    families: list[str] = field(default_factory=list)
    splits: list[str] = field(default_factory=lambda: ["ind", "ood"])
    scenes: list[str] = field(default_factory=list)
    episodes: int = 20
    batch_size: int = 8
    episode_length: int | None = None
    dataset_repo_id: str | None = None
    dataset_root: str | None = None
    image_size: int = 0
    seed: int = 100_000
    videos: int = 2
    workers: int | None = None
    output_dir: Path = Path("outputs/eval")
    device: str = "auto"
    resume: bool = False

    def __post_init__(self):
        if not self.policy_path:
            raise InvalidInputError("--policy_path is required")
        unknown = set(self.families) - set(TASK_FAMILIES)
        if unknown:
            raise InvalidInputError(f"unknown task families {sorted(unknown)}; known: {list(TASK_FAMILIES)}")
        if not set(self.splits) <= {"ind", "ood"} or not self.splits:
            raise InvalidInputError(f"splits must be among 'ind', 'ood', got {self.splits}")
        if self.scenes and (
            unknown := set(self.scenes) - {s.id for split in self.splits for s in select_scenes(split)}
        ):
            raise InvalidInputError(f"scenes {sorted(unknown)} are not scenes of the splits {self.splits}")
        self.output_dir = Path(self.output_dir)


@torch.no_grad()
def run_episodes(env, policy, io: PolicyIO, seed: int, record: bool = False) -> tuple[np.ndarray, list]:
    """One batch of episodes with the deterministic policy: (success per env, rendered frames if recorded)."""
    observation, _ = env.reset(seed=seed)
    success, _, frames = play(env, policy, io, observation, record)
    return success, frames


@torch.no_grad()
def play(env, policy, io: PolicyIO, observation: dict, record: bool = False) -> tuple[np.ndarray, np.ndarray, list]:
    """Play one batch of episodes from the observation of a reset to their horizon (or end), the policy acting on
    the env's own observations: (success per env, return per env, rendered frames if recorded)."""
    policy.reset()
    tasks = list(env.call("task"))
    success = np.zeros(env.num_envs, dtype=bool)
    ended = np.zeros(env.num_envs, dtype=bool)
    returns = np.zeros(env.num_envs)
    frames = [np.concatenate(env.render(), axis=1)] if record else []
    for _ in range(env.call("_max_episode_steps")[0]):
        action = policy.select_action(io.batch(observation["pixels"], tasks))
        observation, reward, terminated, truncated, info = env.step(io.env_action(action))
        success |= np.asarray(info["is_success"], dtype=bool)
        returns += reward
        ended |= terminated | truncated
        if record:
            frames.append(np.concatenate(env.render(), axis=1))
        if ended.all():
            break
    return success, returns, frames


@dataclass
class RecordedEpisode:
    """One simulator episode of a policy, frame-aligned like a token cache's rows: frame t is the observation before
    action t (the last frame, after the last action, repeats that action), done[t] whether the task was accomplished
    by frame t."""

    images: dict[str, np.ndarray]  # camera -> (T, H, W, 3) uint8
    action: np.ndarray  # (T, A) float32
    state: np.ndarray  # (T, D) float32 the robot's state (an env with include_state)
    done: np.ndarray  # (T,) float32
    task: str


@torch.no_grad()
def record_episodes(env, policy, io: PolicyIO, seed: int) -> list[RecordedEpisode]:
    """One batch of episodes of the deterministic policy, each recorded until it ended (an env with include_state:
    the world models read the robot's state too)."""
    observation, _ = env.reset(seed=seed)
    policy.reset()
    tasks = list(env.call("task"))
    frames, actions, done = [observation["pixels"]], [], [np.zeros(env.num_envs, dtype=np.float32)]
    states = [observation["agent_pos"]]
    lengths = np.zeros(env.num_envs, dtype=int)  # actions taken while running
    ended = np.zeros(env.num_envs, dtype=bool)
    for _ in range(env.call("_max_episode_steps")[0]):
        action = io.env_action(policy.select_action(io.batch(observation["pixels"], tasks)))
        observation, _, terminated, truncated, info = env.step(action)
        lengths += ~ended
        ended |= terminated | truncated
        frames.append(observation["pixels"])
        states.append(observation["agent_pos"])
        actions.append(action)
        done.append(np.asarray(info["is_success"], dtype=np.float32))
        if ended.all():
            break
    actions.append(actions[-1])
    return [
        RecordedEpisode(
            images={cam: np.stack([f[cam][i] for f in frames[: n + 1]]) for cam in frames[0]},
            action=np.stack([a[i] for a in actions[: n + 1]]).astype(np.float32),
            state=np.stack([s[i] for s in states[: n + 1]]).astype(np.float32),
            done=np.array([d[i] for d in done[: n + 1]], dtype=np.float32),
            task=tasks[i],
        )
        for i, n in enumerate(lengths)
    ]


def eval_env_config(cfg: EvalConfig, split: str, image_size: int) -> RoboscapeManiSkillEnvConfig:
    # Success at any step is what counts, so an episode can stop at its first success.
    return RoboscapeManiSkillEnvConfig(
        families=list(cfg.families) or list(TASK_FAMILIES),
        split=split,
        scenes=list(cfg.scenes),
        image_size=image_size,
        episode_length=cfg.episode_length,
        terminate_on_success=True,
        dataset_repo_id=cfg.dataset_repo_id,
        dataset_root=cfg.dataset_root,
        workers=cfg.workers,
        seed=cfg.seed,
        include_state=True,  # unread by the image-only policies; the world models start from it when paired
    )


def eval_batch_size(cfg: EvalConfig) -> int:
    return min(cfg.batch_size, cfg.episodes * len(cfg.families or TASK_FAMILIES))


def evaluate_success(cfg: EvalConfig, slots=None) -> dict:
    """Evaluate, write eval.json / eval.md / videos under output_dir, and return the results. slots: the simulator's
    envs from `build_slots` (of `eval_env_config(cfg, ...)` and `eval_batch_size(cfg)`), to share them between
    evaluations; by default the evaluation builds its own, once for all its splits."""
    from lerobot_roboscape.envs.maniskill_env import build_slots

    done = completed_splits(cfg)
    device = resolve_device(cfg.device)
    policy, preprocessor, postprocessor = load_policy(cfg.policy_path, device)
    policy.eval()
    io = PolicyIO(preprocessor, postprocessor)
    image_size = cfg.image_size or next(
        feature.shape[-1] for feature in policy.config.input_features.values() if len(feature.shape) == 3
    )
    results = {"policy": cfg.policy_path, "episode_length": cfg.episode_length or "per family", "splits": {}}
    own_slots = None
    try:
        for split in cfg.splits:
            if split in done:
                results["splits"][split] = done[split]
                continue
            env_cfg = eval_env_config(cfg, split, image_size)
            check_policy_fits_env(policy, env_cfg, cfg.policy_path)
            if slots is None:
                slots = own_slots = build_slots(env_cfg, eval_batch_size(cfg))
            results["splits"][split] = evaluate_split(cfg, env_cfg, slots, policy, io)
            write_text_atomically(cfg.output_dir / SPLITS / f"{split}.json", json.dumps(results["splits"][split]))
    finally:
        if own_slots is not None:
            own_slots.close()
    # The tables appear only complete: a killed evaluation leaves its finished splits, never a partial eval.json.
    write_text_atomically(cfg.output_dir / EVAL_JSON, json.dumps(results, indent=2))
    write_text_atomically(cfg.output_dir / "eval.md", markdown(results))
    return results


def evaluate_split(cfg: EvalConfig, env_cfg: RoboscapeManiSkillEnvConfig, slots, policy, io: PolicyIO) -> dict:
    """{family: cell, "all": cell} of one split, its episodes run in batches on `slots`."""
    from lerobot_roboscape.envs.maniskill_env import RoboscapeManiSkillEnv

    env = RoboscapeManiSkillEnv(env_cfg, num_envs=eval_batch_size(cfg), slots=slots)
    outcomes = {family: [] for family in env_cfg.families}
    batches = math.ceil(cfg.episodes * len(env_cfg.families) / env.num_envs)
    for k in tqdm(range(batches), desc=f"eval {env_cfg.split}", leave=False):
        record = k == 0 and cfg.videos > 0
        success, frames = run_episodes(env, policy, io, seed=cfg.seed + 7919 * k, record=record)
        for family, ok in zip(env.slot_families, success, strict=True):
            if len(outcomes[family]) < cfg.episodes:
                outcomes[family].append(bool(ok))
        if record:
            for i, (family, ok) in enumerate(zip(env.slot_families[: cfg.videos], success, strict=False)):
                name = f"{i:02d}_{family}_{'success' if ok else 'failure'}.mp4"
                clip = [
                    frame[:, i * frame.shape[1] // env.num_envs : (i + 1) * frame.shape[1] // env.num_envs]
                    for frame in frames
                ]
                write_video(cfg.output_dir / "videos" / env_cfg.split / name, clip, env.metadata["render_fps"])
    env.close()
    cells = {family: Cell.of(o).to_json() for family, o in outcomes.items()}
    cells[ALL] = Cell.of([x for o in outcomes.values() for x in o]).to_json()
    return cells


def completed_splits(cfg: EvalConfig) -> dict[str, dict]:
    """The splits an interrupted evaluation with the same settings completed (with --resume=true)."""
    # The worker count changes no episode (envs/simulator_slots.py), so a resume may use another.
    kept = {k: str(v) for k, v in asdict(cfg).items() if k not in ("resume", "workers")}
    settings = json.dumps(kept, sort_keys=True)
    written = cfg.output_dir / SPLITS / "eval_config.json"
    if (cfg.output_dir / EVAL_JSON).exists() or written.exists():
        if not cfg.resume:
            raise OutputExistsError(
                f"{cfg.output_dir} already holds an evaluation: pass --resume=true to continue "
                "it, or choose another --output_dir"
            )
        if written.exists() and written.read_text() != settings:
            raise InvalidInputError(
                f"--resume=true: {cfg.output_dir} was evaluated with other settings "
                f"({written}); use them, or choose another --output_dir"
            )
    write_text_atomically(written, settings)
    return {
        split: json.loads((cfg.output_dir / SPLITS / f"{split}.json").read_text())
        for split in cfg.splits
        if (cfg.output_dir / SPLITS / f"{split}.json").exists()
    }


def markdown(results: dict) -> str:
    return render_report("success_rate.md", results=results)
