"""PPO in the world model, run where the world models are.

The world models that can be an environment (the gpu preset, 30M parameters each) train on a lent GPU. There they
are fast; on the 2 CPU cores they are far too slow for PPO, and two of them (57 MiB each in bf16) do not travel
back and forth within a lease's transfer limits. So the experiment's runs in them go to the GPU with what they read,
and come back as PPO runs:

- here, `pack` writes the SFT checkpoint, the tokenizer, the env's starts (`envs/starts.py`), the validation and
  held-out episodes as tokens (the done report's) and each run's settings (`plan.json`);
- there, `run_pack` reads the done report of the models trained there (its threshold is the env's), makes every
  start's goal once, runs PPO in every world-model env at once (one process each, sharing the GPU) and rolls each
  run's policy out in the world model for the replay;
- here again, the experiment takes the runs back (`read_results`) and evaluates their checkpoints in the simulator
  as it does its own (`roboscape-experiment --world_model_runs=DIR`).
"""

import json
import logging
import shutil
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, fields, replace
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch

from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.envs.starts import SELECTION, export_starts
from lerobot_roboscape.envs.world_model_env import RoboscapeWorldModelEnv
from lerobot_roboscape.experiments.pack_format import (
    PLAN,
    RESULTS,
    PackResults,
    Plan,
    PlannedRun,
    ReplayPlan,
    RunRecord,
    read_plan,
    rollouts_file,
)
from lerobot_roboscape.io.atomic import write_text_atomically
from lerobot_roboscape.io.tensor_files import load_tensors, save_tensors
from lerobot_roboscape.pipeline.ppo_run import ppo
from lerobot_roboscape.pipeline.resume import stage_seconds
from lerobot_roboscape.reward.done_readings import DoneReport
from lerobot_roboscape.reward.done_report import (
    DoneChoice,
    DoneReportConfig,
    TokenEpisode,
    evaluate_done,
    save_token_episodes,
)
from lerobot_roboscape.rl.configuration_ppo import PPOConfig
from lerobot_roboscape.rl.policy_loading import PolicyIO, load_policy
from lerobot_roboscape.training.checkpoints import CHECKPOINTS, FINAL, LAST, spread_checkpoints
from lerobot_roboscape.training.loop import resolve_device

logger = logging.getLogger(__name__)
PACK_DIR, RUNS_DIR = "pack", "runs"  # in the experiment's --world_model_runs folder: what goes, what came back
GOALS = "goals.safetensors"
ON_DEVICE = "(set where the runs go)"  # the models' paths in the packed settings: the device sets its own
# The env's settings that name files of this machine: the device sets its own.
_MACHINE_FIELDS = (
    "dataset_repo_id",
    "dataset_root",
    "world_models",
    "tokenizer",
    "action_world_model",
    "text_world_model",
    "starts_file",
    "goal_file",
    "ensemble",
    "success_classifier",
    "device",
    "features",
    "features_map",
)


@dataclass(frozen=True)
class Job:
    """One PPO run of the pack: its method (as Table 1 names it), its settings, and whether its env reads the
    ensemble's disagreement (its members are trained where the runs are)."""

    method: str
    ppo: PPOConfig
    ensemble: bool = False


# ---- here: what the runs read ------------------------------------------------------------------------------------


def pack(
    dest: Path,
    jobs: dict[str, Job],
    sft: Path,
    tokenizer: Path,
    done_sets: dict[str, list[TokenEpisode]],
    frame_skip: int,
    curve_checkpoints: int,
    replay: dict | None = None,
    ensemble: dict | None = None,
) -> Path:
    """Write into `dest` what `run_pack` needs: the SFT checkpoint, the tokenizer, each distinct start selection of
    the jobs' envs (read from their dataset), the done report's episodes as tokens at the world model's frame skip
    (`done_sets`: validation, heldout) and the plan: each job's settings, the checkpoints the curve reads, the
    replay's starts per run ({episodes}) and the ensemble members' settings; returns `dest`."""
    dest = Path(dest)
    partial = dest.with_name(dest.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    shutil.copytree(sft, partial / "sft")
    shutil.copytree(tokenizer, partial / "tokenizer")
    for name, episodes in done_sets.items():
        save_token_episodes(episodes, frame_skip, partial / f"done_{name}.safetensors", f"the {name} episodes")
    runs, starts = {}, {}
    for tag, job in jobs.items():
        env = job.ppo.env
        selection = json.dumps({name: getattr(env, name) for name in SELECTION}, sort_keys=True)
        if selection not in starts:
            starts[selection] = f"starts_{len(starts)}.safetensors"
            export_starts(env, partial / starts[selection])
        settings = {f.name: getattr(job.ppo, f.name) for f in fields(job.ppo) if f.name not in ("env", "policy_path")}
        runs[tag] = PlannedRun(
            job.method,
            job.ensemble,
            starts[selection],
            {k: v for k, v in asdict(env).items() if k not in _MACHINE_FIELDS},
            json.loads(json.dumps(settings, default=str)),
        )
    plan = Plan(runs, curve_checkpoints, replay and ReplayPlan(**replay), ensemble or {})
    write_text_atomically(partial / PLAN, json.dumps(plan.to_json(), indent=2))
    shutil.rmtree(dest, ignore_errors=True)
    partial.replace(dest)
    return dest


# ---- there: the runs ---------------------------------------------------------------------------------------------


@dataclass
class RunPackConfig:
    """Args:
    pack: the folder `roboscape-experiment --world_model_runs=DIR` packed (DIR/pack).
    action, text: the world models the runs go in (pretrained_model folders).
    members: more action models, the ensemble whose disagreement the ensemble lever's env reads.
    output_dir: where the runs, the done report, the goals and the replay's rollouts go (then brought back to
        DIR/runs).
    time_budget_s: PPO's clock of each run, instead of the packed budget (null: the packed one).
    device: "auto", "cpu" or "cuda".
    """

    pack: str = ""
    action: str = ""
    text: str = ""
    members: list[str] = field(default_factory=list)
    output_dir: str = ""
    time_budget_s: float | None = None
    device: str = "auto"


def run_pack(cfg: RunPackConfig) -> PackResults:
    """Run the pack's PPO runs in the world models into `output_dir`: the done report first (its threshold is every
    env's), then every start's goal, then the runs, all at once, one process each, then each run's rollouts for the
    replay. Returns the results (also `output_dir/results.json`)."""
    pack_dir, out, device, members = Path(cfg.pack).resolve(), Path(cfg.output_dir).resolve(), cfg.device, cfg.members
    action, text = cfg.action, cfg.text
    plan = read_plan(pack_dir)
    out.mkdir(parents=True, exist_ok=True)
    report = DoneReportConfig(
        dataset_tokens=str(pack_dir / "done_heldout.safetensors"),
        validation_tokens=str(pack_dir / "done_validation.safetensors"),
        tokenizer=str(pack_dir / "tokenizer"),
        world_model=str(action),
        output_dir=out / "done_report",
        device=device,
    )
    chosen = DoneReport.from_json(evaluate_done(report))
    done = DoneChoice(chosen.source, chosen.theta)
    # Without members (none was given, or none saved in its budget) the ensemble's runs fail alone, as a failed run.
    runs = {
        tag: RunRecord(run.method, Path("rl", tag), error="no ensemble member was given")
        for tag, run in plan.runs.items()
        if run.ensemble and not members
    }
    jobs = {}
    for tag, run in plan.runs.items():
        if tag in runs:
            continue
        env = RoboscapeWorldModelEnvConfig(
            **run.env,
            tokenizer=str(pack_dir / "tokenizer"),
            action_world_model=str(action),
            text_world_model=str(text),
            starts_file=str(pack_dir / run.starts),
            goal_file=str(out / GOALS),
            ensemble=[str(m) for m in members] if run.ensemble else [],
            device=device,
        )
        env = replace(env, done_source=done.source, theta=done.theta, theta_sps=done.theta)
        settings = {k: v for k, v in run.ppo.items() if k != "output_dir"} | {"device": device}
        if cfg.time_budget_s is not None:
            settings["time_budget_s"] = cfg.time_budget_s
        jobs[tag] = PPOConfig(policy_path=str(pack_dir / "sft"), env=env, output_dir=out / "rl" / tag, **settings)
    for config in {c.env.starts_file: c.env for c in jobs.values()}.values():  # every goal, once, before the clocks
        RoboscapeWorldModelEnv(config, num_envs=1).close()
    # A run that fails is recorded as failed; the others still come back.
    finals = {}
    with ProcessPoolExecutor(max_workers=max(len(jobs), 1), mp_context=get_context("spawn")) as pool:
        futures = {tag: pool.submit(ppo, config) for tag, config in jobs.items()}
        for tag, future in futures.items():
            method, folder = plan.runs[tag].method, Path("rl", tag)
            try:
                finals[tag] = future.result()
            except Exception as error:  # noqa: BLE001 (any failure of one run: recorded, the others kept)
                logger.exception("PPO run %s failed", tag)
                runs[tag] = RunRecord(method, folder, error=f"{type(error).__name__}: {error}")
                continue
            runs[tag] = RunRecord(method, folder, finals[tag].relative_to(out), stage_seconds(out / folder))
    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else None
    budget = next(iter(jobs.values())).time_budget_s if jobs else None
    results = PackResults(chosen.choice(), gpu, budget, runs)
    for tag in finals if plan.replay else ():
        save_rollouts(roll_out(jobs[tag].env, finals[tag], plan.replay.episodes, device), out / rollouts_file(tag))
        results.replays[tag] = rollouts_file(tag)
    slim([out / "rl" / tag for tag in finals], plan.curve_checkpoints)
    write_text_atomically(out / RESULTS, json.dumps(results.to_json(), indent=2))
    return results


def slim(runs: list[Path], checkpoints: int) -> None:
    """Keep what the experiment reads of each of `runs`, in half the bytes: `checkpoints` of its checkpoints spread
    over the run (those the checkpoint curve evaluates, its last among them), their policy weights and the run's
    published model in bf16 (`copy_run` casts them back), without the optimiser's state."""
    for run in runs:
        kept = set(spread_checkpoints(run, checkpoints))
        for folder in (run / CHECKPOINTS).iterdir():
            if folder.is_dir() and folder not in kept:
                shutil.rmtree(folder)
        for folder in kept:
            (folder / "training_state" / "optimizer_state.safetensors").unlink(missing_ok=True)
            _cast(folder / FINAL / "model.safetensors", torch.bfloat16)
        _cast(run / FINAL / "model.safetensors", torch.bfloat16)
        last = run / CHECKPOINTS / LAST  # names the newest checkpoint, which is kept
        if last.is_file() and not (run / CHECKPOINTS / last.read_text().strip()).is_dir():
            raise RuntimeError(f"{run}: the last checkpoint was dropped")


def copy_run(source: Path, dest: Path) -> None:
    """A run `slim` trimmed, copied to `dest` with its policy weights cast back to float32 (their values rounded to
    bf16's precision on the way)."""
    shutil.copytree(source, dest, dirs_exist_ok=True)
    for weights in [
        *(Path(dest) / CHECKPOINTS).glob(f"*/{FINAL}/model.safetensors"),
        Path(dest) / FINAL / "model.safetensors",
    ]:
        _cast(weights, torch.float32)


def _cast(path: Path, dtype: torch.dtype) -> None:
    metadata, tensors = load_tensors(path, "save_pretrained")
    save_tensors(path, {k: v.to(dtype) if v.is_floating_point() else v for k, v in tensors.items()}, metadata)


# ---- rollouts of a policy in the world model (the replay's first half) --------------------------------------------


@dataclass(frozen=True)
class RolloutStart:
    """Where a rollout started: its demonstration's episode, and the facts the simulator replays it from."""

    episode_index: int
    task_family: str
    scene: str
    seed: int

    @classmethod
    def of(cls, start) -> "RolloutStart":
        """From one of `roboscape_wm`'s starts."""
        return cls(start.episode_index, start.family, start.scene, int(start.facts["seed"]))


@dataclass
class Rollouts:
    """A policy's episodes in `roboscape_wm` from chosen starts: what the env drew (frames, T + 1 per episode), the
    policy's actions, and what the world model said of each episode."""

    frames: np.ndarray  # (T + 1, B, H, W, 3) uint8: env.render() of each episode
    actions: np.ndarray  # (T, B, A)
    returns: np.ndarray  # (B,)
    success: np.ndarray  # (B,) bool: the world model's done reached theta
    starts: list[RolloutStart]
    cameras: list[str]  # the views, top to bottom in each frame


@torch.no_grad()
def roll_out(env_cfg: RoboscapeWorldModelEnvConfig, checkpoint: Path, episodes: int, device: str = "auto") -> Rollouts:
    """The policy at `checkpoint` in `roboscape_wm` from `episodes` starts spread over the env's starts (so over
    families and scenes), to the horizon."""
    env = RoboscapeWorldModelEnv(env_cfg, num_envs=episodes)
    chosen = [env.starts[int(i)] for i in np.linspace(0, len(env.starts) - 1, episodes).round()]
    policy, preprocessor, postprocessor = load_policy(checkpoint, resolve_device(device))
    policy.eval()
    policy.reset()
    io = PolicyIO(preprocessor, postprocessor)
    observation, _ = env.reset(seed=0, options={"episode_index": [s.episode_index for s in chosen]})
    frames, actions = [np.stack(env.render())], []
    returns, succeeded = np.zeros(env.num_envs), np.zeros(env.num_envs, dtype=bool)
    for _ in range(env.call("_max_episode_steps")[0]):
        action = io.env_action(policy.select_action(io.batch(observation["pixels"], env.tasks())))
        observation, reward, terminated, truncated, info = env.step(action)
        frames.append(np.stack(env.render()))
        actions.append(action)
        returns += reward
        succeeded |= info["is_success"]
        if (terminated | truncated).all():
            break
    env.close()
    starts = [RolloutStart.of(s) for s in chosen]
    return Rollouts(np.stack(frames), np.stack(actions), returns, succeeded, starts, list(env.cameras))


def save_rollouts(rollouts: Rollouts, path: Path) -> Path:
    tensors = {
        "frames": torch.from_numpy(rollouts.frames),
        "actions": torch.from_numpy(rollouts.actions.astype(np.float32)),
        "returns": torch.from_numpy(rollouts.returns.astype(np.float32)),
        "success": torch.from_numpy(rollouts.success.astype(np.uint8)),
    }
    starts = json.dumps([asdict(start) for start in rollouts.starts])
    return save_tensors(path, tensors, {"starts": starts, "cameras": json.dumps(rollouts.cameras)})


def load_rollouts(path: Path) -> Rollouts:
    records, tensors = load_tensors(path, "save_rollouts", ("starts", "cameras"))
    t = {name: tensor.numpy() for name, tensor in tensors.items()}
    returns, success = t["returns"].astype(np.float64), t["success"].astype(bool)
    starts = [RolloutStart(**start) for start in json.loads(records["starts"])]
    return Rollouts(t["frames"], t["actions"], returns, success, starts, json.loads(records["cameras"]))
