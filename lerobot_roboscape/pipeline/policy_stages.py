"""The policy stages of the pipeline, one function each, after the data and model stages of `stages.py`: SFT with
lerobot-train, LeRobot's evaluation in the world model, PPO in the world model and in the simulator, and the
simulator evaluation behind Table 1. Each resumes as the others do (`resume.py`)."""

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig, RoboscapeWorldModelEnvConfig
from lerobot_roboscape.envs.maniskill_env import build_slots
from lerobot_roboscape.evaluation.results import SCENE, SPLITS, Results
from lerobot_roboscape.evaluation.success_rate import (
    EVAL_JSON,
    EvalConfig,
    eval_batch_size,
    eval_env_config,
    evaluate_success,
    markdown,
    read_cells,
)
from lerobot_roboscape.io.atomic import write_text_atomically
from lerobot_roboscape.pipeline.config import PipelineConfig
from lerobot_roboscape.pipeline.layout import (
    GOAL_FILE,
    eval_dir,
    lerobot_eval_dir,
    rl_dir,
    sft_dir,
)
from lerobot_roboscape.pipeline.lerobot_cli import lerobot_eval, lerobot_sft
from lerobot_roboscape.pipeline.methods import (
    RL_MANISKILL,
    RL_MANISKILL_ONE_SCENE,
    RL_WORLD_MODEL,
    RL_WORLD_MODEL_DENSE,
    RL_WORLD_MODEL_SPARSE,
    SFT,
    Method,
    initial_scene,
)
from lerobot_roboscape.pipeline.ppo_run import ppo
from lerobot_roboscape.pipeline.resume import is_done, mark_done, start
from lerobot_roboscape.rl.configuration_ppo import PPOConfig

# ---- policies ----------------------------------------------------------------------------------------------------


def policy_specs(cfg: PipelineConfig) -> dict[str, list[str]]:
    """{policy name: its lerobot-train arguments} of the policies this run trains."""
    device = [f"--policy.device={cfg.device}"] if cfg.device != "auto" else []
    specs = {"roboscape_mlp": ["--policy.type=roboscape_mlp", *device]}
    if cfg.sft.openvla_steps:
        specs["openvla"] = ["--policy.type=openvla", f"--policy.base_model={cfg.sft.openvla_base_model}", *device]
    return specs


def sft(
    cfg: PipelineConfig, out: Path, demonstrations: DatasetConfig, scenes: list[str] | None = None
) -> dict[str, Path]:
    """SFT of each policy with `lerobot-train` on the demonstrations of `scenes` (None: all); returns
    {policy name: checkpoint}."""
    steps = {"roboscape_mlp": (cfg.sft.steps, cfg.sft.batch_size), "openvla": (cfg.sft.openvla_steps, 8)}
    return {
        name: lerobot_sft(
            out / sft_dir(name),
            demonstrations,
            args,
            *steps[name],
            num_workers=cfg.sft.num_workers,
            fresh=cfg.fresh,
            scenes=scenes,
        )
        for name, args in policy_specs(cfg).items()
    }


# The settings of the world-model env that lerobot-eval is given (the others keep their defaults).
_LEROBOT_EVAL_ENV_KEYS = (
    "dataset_repo_id",
    "dataset_root",
    "tokenizer",
    "action_world_model",
    "text_world_model",
    "max_goal_steps",
    "allow_random_lpips",
    "image_size",
)


def lerobot_eval_in_world_model(
    cfg: PipelineConfig, out: Path, checkpoints: dict[str, Path], env: RoboscapeWorldModelEnvConfig
) -> dict[str, Path]:
    """LeRobot's own evaluation (`lerobot-eval`) of each policy in `roboscape_wm`; returns {name: eval_info.json}."""
    length = cfg.lerobot_eval.episode_length or cfg.env.episode_length  # null: each family's horizon
    env_args = [
        "--env.type=roboscape_wm",
        f"--env.families=[{','.join(cfg.data.families)}]",
        *([f"--env.episode_length={length}"] if length else []),
        *(f"--env.{key}={value}" for key, value in asdict(env).items() if key in _LEROBOT_EVAL_ENV_KEYS),
    ]
    results = {}
    for name, checkpoint in checkpoints.items():
        results[name] = lerobot_eval(
            out / lerobot_eval_dir(name),
            checkpoint,
            env_args,
            cfg.lerobot_eval.n_episodes,
            cfg.lerobot_eval.n_episodes,
            fresh=cfg.fresh,
        )
        result = json.loads(results[name].read_text())["overall"]
        print(
            f"{name} in roboscape_wm: success {result['pc_success']:.0f}% of {result['n_episodes']} episodes, "
            f"mean return {result['avg_sum_reward']:.2f}"
        )
    return results


def rl_envs(
    cfg: PipelineConfig, out: Path, demonstrations: DatasetConfig, wm_env: RoboscapeWorldModelEnvConfig | None
) -> dict:
    """{method: env config} of the RL runs: the world model (every training scene), the simulator in every
    training scene and, as the paper's baseline ran it (section 3.2: it "only initializes a single type of
    environment"), the simulator in one scene; with `reward_ablation`, the world model paid only its sparse and
    only its dense reward. The world model's goals are generated once into `wm_env.goal_file` (default: the run's
    own, in `out`), before PPO's clock starts, and shared by its runs. Without `wm_env` (its runs go where the world
    models are: pipeline/world_model_runs.py), the simulator's alone."""
    sim = RoboscapeManiSkillEnvConfig(
        families=cfg.data.families,
        split="ind",
        image_size=cfg.data.image_size,
        episode_length=cfg.env.episode_length,
        dataset_repo_id=demonstrations.repo_id,
        dataset_root=demonstrations.root,
    )
    envs = {RL_MANISKILL: sim}
    if cfg.ppo_one_scene:
        envs[RL_MANISKILL_ONE_SCENE] = replace(sim, scenes=[initial_scene()])
    if wm_env is None:
        return envs
    wm = replace(
        wm_env,
        split="ind",
        episode_length=cfg.env.episode_length,
        starts_per_scene=cfg.env.starts_per_scene,
        goal_file=wm_env.goal_file or str(out / GOAL_FILE),
    )
    envs = {RL_WORLD_MODEL: wm} | envs
    if cfg.reward_ablation:
        envs |= {RL_WORLD_MODEL_SPARSE: replace(wm, beta=0.0), RL_WORLD_MODEL_DENSE: replace(wm, alpha=0.0)}
    return envs


def ppo_config(
    cfg: PipelineConfig, out: Path, policy: str, method: str, sft_checkpoint: Path, env, settings: dict
) -> PPOConfig:
    """PPO's settings for one run: the pipeline's, those of its method (`settings`), from the SFT checkpoint."""
    return PPOConfig(
        policy_path=str(sft_checkpoint),
        env=env,
        output_dir=out / rl_dir(policy, method),
        device=cfg.device,
        **(asdict(cfg.ppo) | settings),
    )


@dataclass(frozen=True)
class RLRun:
    """One PPO run of a method: its env, PPO's settings beside the pipeline's (`--pipeline.ppo.*`), and what runs
    it (PPO, or PPO wrapped by a lever that acts before slices of its clock)."""

    env: object
    settings: dict = field(default_factory=dict)
    runner: Callable[[PPOConfig, bool], Path] = ppo


def rl(
    cfg: PipelineConfig,
    out: Path,
    demonstrations: DatasetConfig,
    wm_env: RoboscapeWorldModelEnvConfig | None,
    checkpoints: dict[str, Path],
    levers: dict[Method, RLRun] | None = None,
    only: list[str] | None = None,
) -> dict[str, dict[str, Path]]:
    """PPO from each SFT checkpoint in each RL env (one multi-task run over the families, at equal wall-clock), and
    the runs of `levers`; `only`: these methods' runs alone. Returns {policy: {method: checkpoint}}."""
    runs = {method: RLRun(env) for method, env in rl_envs(cfg, out, demonstrations, wm_env).items()} | (levers or {})
    runs = {method: run for method, run in runs.items() if only is None or method in only}
    return {
        name: {
            method: run.runner(ppo_config(cfg, out, name, method, sft_checkpoint, run.env, run.settings), cfg.fresh)
            for method, run in runs.items()
        }
        for name, sft_checkpoint in checkpoints.items()
    }


def every_checkpoint(sft: dict[str, Path], rl: dict[str, dict[str, Path]]) -> dict[str, dict[str, Path]]:
    """{policy: {method: checkpoint}}: each policy's SFT checkpoint, then its PPO runs' (Table 1's rows)."""
    return {name: {SFT: sft[name]} | runs for name, runs in rl.items()}


# ---- evaluation in the simulator ---------------------------------------------------------------------------------

EVAL_BATCH_SIZE = 8  # parallel episodes of each simulator evaluation


def eval_job(
    cfg: PipelineConfig,
    demonstrations: DatasetConfig,
    checkpoint: Path,
    splits: tuple[str, ...],
    output_dir: Path,
    episodes: int | None = None,
    seed: int | None = None,
    videos: int = 2,
    scenes: list[str] | None = None,
) -> EvalConfig:
    """The simulator evaluation of one checkpoint: `episodes` (default: Table 1's) per (split, family), in
    `scenes` of the splits only when given."""
    return EvalConfig(
        policy_path=str(checkpoint),
        families=cfg.data.families,
        splits=list(splits),
        scenes=list(scenes or []),
        episodes=episodes or cfg.eval.episodes,
        batch_size=EVAL_BATCH_SIZE,
        episode_length=cfg.eval.episode_length or cfg.env.episode_length,
        dataset_repo_id=demonstrations.repo_id,
        dataset_root=demonstrations.root,
        image_size=cfg.data.image_size,
        videos=videos,
        workers=cfg.data.workers,
        output_dir=output_dir,
        device=cfg.device,
        **({} if seed is None else {"seed": seed}),
    )


def run_evaluations(cfg: PipelineConfig, jobs: list[EvalConfig]) -> None:
    """Run the evaluations not yet complete, one after another on the same simulator envs (built once, spread over
    `workers` processes)."""
    pending = [job for job in jobs if not is_done(job.output_dir, job, cfg.fresh)]
    if not pending:
        return
    slots = build_slots(eval_env_config(pending[0], "ind", cfg.data.image_size), eval_batch_size(pending[0]))
    try:
        for job in pending:
            start(job.output_dir)
            evaluate_success(job, slots)
            mark_done(job.output_dir, job)
    finally:
        slots.close()


def simulator_eval(
    cfg: PipelineConfig,
    out: Path,
    demonstrations: DatasetConfig,
    checkpoints: dict[str, dict[str, Path]],
    scene: str | None = None,
) -> Results:
    """Success of every checkpoint in the simulator, IND and OOD, and in `scene` (a training scene, new initial
    states: split "scene") when given (the reward ablation's and the levers' OOD only; 95% Wilson intervals), one
    evaluation per (checkpoint, split)."""
    jobs, splits = {}, [split for split in SPLITS if scene or split != SCENE]
    for name, methods in checkpoints.items():
        for method, checkpoint in methods.items():
            for split in ("ood",) if Method.named(method).ood_only else splits:
                jobs[name, method, split] = eval_job(
                    cfg,
                    demonstrations,
                    checkpoint,
                    ("ind",) if split == SCENE else (split,),
                    out / eval_dir(name, method) / split,
                    scenes=[scene] if split == SCENE else None,
                )
    # OOD's cells first, every checkpoint's: the claim's, complete when a long table is stopped midway.
    run_evaluations(cfg, sorted(jobs.values(), key=lambda job: job.splits[0] != "ood"))
    cells = {}
    for (name, method, split), job in jobs.items():
        cells.setdefault(name, {}).setdefault(method, {})[split] = read_cells(job.output_dir, job.splits[0])
    results = Results(cells)
    for name in results.policies:  # both splits in one eval.json per checkpoint (its policy card's table)
        for method, splits in results.to_json()[name].items():
            length = jobs[name, method, next(iter(splits))].episode_length or "per family"
            merged = {"policy": str(checkpoints[name][method]), "episode_length": length, "splits": splits}
            folder = out / eval_dir(name, method)
            write_text_atomically(folder / EVAL_JSON, json.dumps(merged, indent=2))
            (folder / "eval.md").write_text(markdown(merged))
    return results
