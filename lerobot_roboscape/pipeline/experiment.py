"""The paper's claim (Table 1), measured on the models a pipeline run already trained: PPO from the SFT checkpoint
in the world model, in the simulator in one scene and in every training scene, at equal wall-clock; the reward
ablation; the simulator success of PPO's checkpoints along its run; world-model rollouts beside the same actions
replayed in the simulator; Table 1 with 95% intervals of the differences; and the report.

Its inputs are the stages before PPO in `output_dir`, as `roboscape-demo` writes them: the demonstrations, the
tokenizer, both world models and the done report (and the SFT checkpoint, unless one is given). Each step skips
what a run with the same settings completed, so a killed run resumes.
"""

import hashlib
import json
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import imageio.v3 as iio
import numpy as np
from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.dataset.reader import open_dataset
from lerobot_roboscape.demos.rollout import EpisodeJob, replay_actions, worker_env
from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.evaluation.success_rate import read_cells
from lerobot_roboscape.io.atomic import write_text_atomically
from lerobot_roboscape.pipeline import data_stages, layout, methods, policy_stages, resume, stages, world_model_runs
from lerobot_roboscape.pipeline.clock import StageClock
from lerobot_roboscape.pipeline.config import PipelineConfig
from lerobot_roboscape.pipeline.done_refresh import DoneRefresh
from lerobot_roboscape.pipeline.experiment_report import write_experiment_report
from lerobot_roboscape.reward.done_report import REPORT_JSON, DoneChoice, token_episodes
from lerobot_roboscape.rl.ppo_state import checkpoint_seconds
from lerobot_roboscape.robot import CONTROL_FREQ
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.training.checkpoints import FINAL, spread_checkpoints
from lerobot_roboscape.training.loop import resolve_device
from lerobot_roboscape.training.records import write_video
from roboscape_core.errors import InvalidInputError, MissingInputError

logger = logging.getLogger(__name__)
CURVE_DIR, REPLAY_DIR = "curve", "replay"
CURVE_SEED = 200_000  # the curve's initial states, apart from Table 1's (EvalConfig's default seed)
REPLAY_STRIPS = 4  # replays drawn in replay.png


@dataclass
class ExperimentConfig:
    """Args:
    pipeline: the `roboscape-demo` run whose trained stages the experiment reads, as it was given
        (`--pipeline.scale`, `--pipeline.output_dir`), and the sizes of PPO and of the table
        (`--pipeline.ppo.time_budget_s`, `--pipeline.eval.episodes`, ...).
    protocol: "paper": SFT on the demonstrations of the initial scene only, PPO in the world model from starts in
        every scene it learned, PPO in the simulator in the initial scene and (the stronger baseline the paper
        lacks) in every training scene; "all_scenes": the same PPO runs from SFT on every training scene. Each
        protocol's policy runs go in their own folder of output_dir (layout.protocol_dir); the world models, their
        goals and the data are shared.
    sft_checkpoint: the SFT'd policy PPO starts from (a pretrained_model directory); null: SFT with lerobot-train
        on `sft_dataset_root` (or the run's demonstrations), of the protocol's scenes.
    sft_dataset_repo_id: demonstrations SFT imitates, when it runs.
    sft_dataset_root: their local root (null: the run's demonstrations, or under the paper's protocol those
        collected in the initial scene when `pipeline.data.initial_scene_episodes`).
    levers: guards against a policy that games the world model, each its own PPO run in the world model beside the
        plain one, judged by the simulator success of its checkpoints (OOD): "kl" (a KL penalty to the SFT
        policy), "ensemble" (the disagreement of `ensemble_members` more action models trained here, by default the
        run's own with its top retrained alone, penalised and/or halting episodes), "branched" (short episodes from
        real frames along the demonstrations), "refresh" (the done head refitted on simulator rollouts of the
        current policy, Dyna-style: it uses the simulator, so its row says how much). The settings below are
        starting points; what each lever measured goes in the report.
    kl_coef: the KL lever's weight (PPO's --kl_coef).
    ensemble_members: action world models beside the run's own in the ensemble lever (seeds 1..n).
    ensemble_retrain_blocks: each member is the run's action model with its last this many blocks and heads drawn
        afresh and trained alone (the trunk shared); null: whole models trained as the run's own.
    ensemble_steps_share: each member's training steps, as a share of the run's action model's.
    disagreement_penalty: the ensemble lever's lambda (roboscape_wm's --env.disagreement_penalty).
    disagreement_threshold: the ensemble lever's halt (--env.disagreement_threshold; null: never halts).
    branches_per_episode: the branched lever's starts per demonstration (--env.branches_per_episode).
    branch_episode_length: the branched lever's episode length, in control steps.
    refresh_rounds: the done-refresh lever's slices of PPO's clock (its done head refitted before each after the
        first, on simulator rollouts of the current policy in the training scenes).
    refresh_episodes: simulator episodes of the policy per refit.
    curve_episodes: simulator episodes per family (OOD) behind each point of the curve of PPO's checkpoints.
    curve_points: points of each such curve: the SFT checkpoint and checkpoints evenly spread over the run (at least
        2: SFT and the last).
    replay_episodes: world-model rollouts of the policy after PPO in the world model replayed in the simulator.
    world_model_runs: a folder: PPO in the world model runs where its models were trained (a lent GPU, when they
        are too slow for this machine's CPUs: pipeline/world_model_runs.py). The first run of the experiment
        writes DIR/pack (the SFT checkpoint, the starts, each run's settings) and stops; once the runs are brought
        back into DIR/runs (scripts/experiments/device_world_models.sh claim, then unpack-runs), the next takes
        them as its own and goes on. The run here then needs no world models; "refresh" cannot go (it needs the
        simulator beside the world model).
    report_dir: where the report (report.md, results.json, figures, videos) goes.
    readme: the README whose results block (between its bench-results markers) is rewritten; null: none.
    """

    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    protocol: str = methods.PAPER_PROTOCOL
    sft_checkpoint: str | None = None
    sft_dataset_repo_id: str = "local/roboscape_sft_demos"
    sft_dataset_root: str | None = None
    levers: list[str] = field(default_factory=list)
    kl_coef: float = 0.1
    ensemble_members: int = 2
    ensemble_retrain_blocks: int | None = 1
    ensemble_steps_share: float = 0.25
    disagreement_penalty: float = 1.0
    disagreement_threshold: float | None = None
    branches_per_episode: int = 4
    branch_episode_length: int = 24
    refresh_rounds: int = 3
    refresh_episodes: int = 16
    curve_episodes: int = 10
    curve_points: int = 6
    replay_episodes: int = 8
    world_model_runs: str | None = None
    report_dir: str = "docs/results/bench"
    readme: str | None = "README.md"

    def __post_init__(self):
        if self.protocol not in methods.PROTOCOLS:
            raise InvalidInputError(f"--protocol must be one of {list(methods.PROTOCOLS)}, got {self.protocol!r}")
        if unknown := [lever for lever in self.levers if lever not in methods.LEVERS]:
            raise InvalidInputError(f"--levers {unknown} unknown; choose from {list(methods.LEVERS)}")
        for name in ("curve_episodes", "replay_episodes", "ensemble_members", "refresh_rounds", "refresh_episodes"):
            if getattr(self, name) < 1:
                raise InvalidInputError(f"--{name} must be >= 1, got {getattr(self, name)}")
        if self.world_model_runs is not None and "refresh" in self.levers:
            raise InvalidInputError(
                "--levers=[refresh] cannot run with --world_model_runs: it refits the done head on simulator "
                "rollouts during PPO, and the simulator stays here while those runs go where the world models are"
            )
        if not 0 < self.ensemble_steps_share <= 1:
            raise InvalidInputError(f"--ensemble_steps_share must be in (0, 1], got {self.ensemble_steps_share}")
        if self.curve_points < 2:
            raise InvalidInputError(
                f"--curve_points must be >= 2 (SFT and the last checkpoint), got {self.curve_points}"
            )


@dataclass
class TrainedStages:
    """What the experiment reads from the run's output_dir."""

    demonstrations: DatasetConfig
    tokenizer: Path
    models: dict[str, Path]
    done: DoneChoice | None
    reward_models: dict[str, Path]


def trained_stages(cfg: PipelineConfig, out: Path, world_models: bool = True) -> TrainedStages:
    """The demonstrations, tokenizer, world models, done report and reward models of the run in `out` (without
    `world_models`: the demonstrations and the tokenizer alone, for runs in world models trained elsewhere)."""
    train = DatasetConfig(repo_id=layout.DEMOS_REPO_ID, root=str(out / layout.DEMOS_DIR))
    tokenizer = out / layout.TOKENIZER_DIR / FINAL
    models = {control: out / layout.world_model_dir(control) / FINAL for control in ("action", "text")}
    done = out / layout.DONE_REPORT_DIR / REPORT_JSON
    needed = [Path(train.root) / "meta" / "info.json", tokenizer] + ([*models.values(), done] if world_models else [])
    for path in needed:
        if not path.exists():
            stop = "" if world_models else " --stop_after=tokenizer"
            raise MissingInputError(
                f"{path} is missing: the experiment runs on a pipeline run's trained stages; run roboscape-demo "
                f"--scale={cfg.scale} --output_dir={out}{stop} first"
            )
    if not world_models:
        return TrainedStages(train, tokenizer, {}, None, {})
    reward_models = {
        kind: out / layout.reward_model_dir(kind) / FINAL
        for kind in (*methods.REWARD_BASELINES, methods.SUCCESS_CLASSIFIER)
        if (out / layout.reward_model_dir(kind) / FINAL).exists()
    }
    return TrainedStages(train, tokenizer, models, DoneChoice.read(done.parent), reward_models)


def sft_policy(cfg: ExperimentConfig, out: Path, demonstrations: DatasetConfig) -> dict[str, Path]:
    """{policy: SFT checkpoint}: the one given, or lerobot-train's on the SFT demonstrations of the protocol's
    scenes (under the paper's, the initial scene's: collected there for it when `data.initial_scene_episodes`)."""
    if cfg.sft_checkpoint:
        return {"roboscape_mlp": Path(cfg.sft_checkpoint).resolve()}
    dataset = demonstrations
    if cfg.sft_dataset_root:
        dataset = DatasetConfig(repo_id=cfg.sft_dataset_repo_id, root=str(Path(cfg.sft_dataset_root).resolve()))
    elif cfg.protocol == methods.PAPER_PROTOCOL and cfg.pipeline.data.initial_scene_episodes:
        p = cfg.pipeline
        dataset = data_stages.initial_scene_demonstrations(p.data, Path(p.output_dir).resolve(), p.fresh)
    scenes = [methods.initial_scene()] if cfg.protocol == methods.PAPER_PROTOCOL else None
    return policy_stages.sft(cfg.pipeline, out, dataset, scenes)


def lever_runs(
    cfg: ExperimentConfig,
    run: Path,
    trained: TrainedStages,
    wm_env: RoboscapeWorldModelEnvConfig,
    members: list[str] | None = None,
) -> dict[str, tuple]:
    """{method: (its env, PPO's settings)} of the levers asked for, beside PPO in the world model's own env. The
    ensemble's `members` are trained here unless given."""
    p = cfg.pipeline
    envs = policy_stages.rl_envs(p, run, trained.demonstrations, wm_env)
    wm = envs[methods.RL_WORLD_MODEL]
    runs = {}
    if "kl" in cfg.levers:
        runs[methods.RL_WORLD_MODEL_KL] = (wm, {"kl_coef": cfg.kl_coef})
    if "ensemble" in cfg.levers:
        if members is None:
            data = data_stages.demonstrations(p.data, run, p.fresh)  # complete: found, not collected again
            trained_members = stages.ensemble_members(
                p,
                run,
                data,
                trained.tokenizer,
                cfg.ensemble_members,
                cfg.ensemble_retrain_blocks,
                cfg.ensemble_steps_share,
            )
            members = [str(m) for m in trained_members]
        env = replace(
            wm,
            ensemble=members,
            disagreement_penalty=cfg.disagreement_penalty,
            disagreement_threshold=cfg.disagreement_threshold,
        )
        runs[methods.RL_WORLD_MODEL_ENSEMBLE] = (env, {})
    if "branched" in cfg.levers:
        env = replace(wm, branches_per_episode=cfg.branches_per_episode, episode_length=cfg.branch_episode_length)
        runs[methods.RL_WORLD_MODEL_BRANCHED] = (env, {})
    if "refresh" in cfg.levers:
        refresh = DoneRefresh(
            sim=envs[methods.RL_MANISKILL],
            tokenizer=str(trained.tokenizer),
            demonstrations_repo_id=trained.demonstrations.repo_id,
            demonstrations_root=trained.demonstrations.root,
            cache_dir=str(run / layout.TOKEN_CACHE_DIR),
            rounds=cfg.refresh_rounds,
            episodes=cfg.refresh_episodes,
            device=p.device,
        )
        runs[methods.RL_WORLD_MODEL_REFRESH] = (wm, {"done_refresh": refresh})
    return runs


def pack_world_model_runs(
    cfg: ExperimentConfig, run: Path, out: Path, trained: TrainedStages, sft: dict[str, Path], dest: Path
) -> Path:
    """Pack the protocol's runs in the world model (PPO in it, its reward ablation, the levers) for the machine
    where the world models are trained: their settings as they would run here, the starts, the SFT checkpoint and
    the done report's episodes as tokens (pipeline/world_model_runs.py)."""
    p = cfg.pipeline
    if len(sft) != 1:
        raise InvalidInputError(f"--world_model_runs packs one policy's runs; this run has SFT checkpoints {list(sft)}")
    (policy, checkpoint), placeholder = next(iter(sft.items())), Path(world_model_runs.ON_DEVICE)
    wm_env = stages.world_model_env(
        p, trained.demonstrations, trained.tokenizer, dict.fromkeys(("action", "text"), placeholder)
    )
    envs = {
        method: (env, {})
        for method, env in policy_stages.rl_envs(p, out, trained.demonstrations, wm_env).items()
        if isinstance(env, RoboscapeWorldModelEnvConfig)
    } | lever_runs(cfg, run, trained, wm_env, members=[world_model_runs.ON_DEVICE])
    jobs = {
        methods.method_tag(method): world_model_runs.Job(
            method,
            policy_stages.ppo_config(p, out, policy, method, checkpoint, env, settings),
            ensemble=bool(env.ensemble),
        )
        for method, (env, settings) in envs.items()
    }
    data = data_stages.demonstrations(p.data, run, p.fresh)  # complete: found, not collected again
    sets = {"validation": data.validation, "heldout": stages.spread(data.heldout, p.data.report_episodes)}
    extra = {
        "replay": {"tag": methods.method_tag(methods.RL_WORLD_MODEL), "episodes": cfg.replay_episodes},
        "ensemble": {
            "members": cfg.ensemble_members,
            "retrain_blocks": cfg.ensemble_retrain_blocks,
            "steps_share": cfg.ensemble_steps_share,
        },
        "curve_checkpoints": cfg.curve_points - 1,
    }

    def write():
        device = resolve_device(p.device)
        tokenizer = VisualTokenizer.from_pretrained(trained.tokenizer).to(device).eval()
        done_sets = {
            name: token_episodes(open_dataset(d.repo_id, d.root, d.episodes), tokenizer, p.wm.frame_skip, device)
            for name, d in sets.items()
        }
        world_model_runs.pack(dest, jobs, checkpoint, trained.tokenizer, done_sets, p.wm.frame_skip, **extra)

    settings = {"jobs": jobs, "sft": str(checkpoint), "tokenizer": str(trained.tokenizer), "done_sets": sets, **extra}
    resume.run_once(dest, settings | {"frame_skip": p.wm.frame_skip}, p.fresh, write)
    return dest


def take_world_model_runs(cfg: ExperimentConfig, out: Path, folder: Path, policy: str) -> dict:
    """The runs `run_pack` made, brought back into `folder`, taken as this protocol's own (each into the folder its
    method's run would have here, its seconds kept): {"runs": {method: final checkpoint}, "results": what the
    device reported}."""
    results = world_model_runs.read_results(folder)
    record = hashlib.sha256((folder / world_model_runs.RESULTS).read_bytes()).hexdigest()[:16]
    runs = {}
    for run in results["runs"].values():
        dest = out / layout.rl_dir(policy, run["method"])
        settings = {"world_model_run": str(run["folder"]), "results": record}
        if not resume.is_done(dest, settings, cfg.pipeline.fresh):
            resume.start(dest)
            world_model_runs.copy_run(run["folder"], dest)
            resume.mark_done(dest, settings, seconds=run["seconds"])
        runs[run["method"]] = dest / run["final"].relative_to(run["folder"])
    return {"runs": runs, "results": results}


def checkpoint_curve(
    cfg: ExperimentConfig,
    out: Path,
    demonstrations: DatasetConfig,
    policy: str,
    sft: Path,
    method: str = methods.RL_WORLD_MODEL,
) -> list[dict]:
    """OOD simulator success of the SFT checkpoint (iteration 0) and of `curve_points` - 1 checkpoints the PPO run
    of `method` saved (evenly spread, its last among them), `curve_episodes` per family, on initial states apart
    from Table 1's: [{iteration, seconds, cell}]."""
    points = [(0, 0.0, sft)]
    for folder in spread_checkpoints(out / layout.rl_dir(policy, method), cfg.curve_points - 1):
        points.append((int(folder.name), checkpoint_seconds(folder), folder / FINAL))
    jobs = [
        policy_stages.eval_job(
            cfg.pipeline,
            demonstrations,
            path,
            ("ood",),
            # the SFT checkpoint's point (iteration 0) is every run's: evaluated once, in the plain run's folder
            out / CURVE_DIR / policy / (curve_tag(method) if iteration else "") / f"{iteration:08d}",
            episodes=cfg.curve_episodes,
            seed=CURVE_SEED,
            videos=0,
        )
        for iteration, _, path in points
    ]
    policy_stages.run_evaluations(cfg.pipeline, jobs)
    return [
        {
            "iteration": iteration,
            "seconds": seconds,
            **read_cells(job.output_dir, "ood")["all"],
        }
        for (iteration, seconds, _), job in zip(points, jobs, strict=True)
    ]


def curve_tag(method: str) -> str:
    """The folder of a method's checkpoint curve (PPO in the world model's: the curve folder itself, as before)."""
    return "" if method == methods.RL_WORLD_MODEL else methods.method_tag(method)


def replay_in_simulator(
    cfg: ExperimentConfig,
    out: Path,
    env_cfg: RoboscapeWorldModelEnvConfig | None,
    checkpoint: Path,
    rollouts_file: Path | None = None,
) -> list[dict]:
    """The policy after PPO in the world model, rolled out in `roboscape_wm` from `replay_episodes` starts (spread
    over the starts, so over families and scenes), or its rollouts made where the world models are
    (`rollouts_file`), and its actions replayed open loop in the simulator from the same scene and initial state.
    Writes side-by-side videos (world model | its goal | simulator) and returns, per start, what each world said:
    the world model's return and success, the simulator's success."""
    folder = out / REPLAY_DIR
    if rollouts_file is None:
        settings = {"env": env_cfg, "checkpoint": str(checkpoint), "episodes": cfg.replay_episodes}
    else:
        settings = {
            "rollouts": str(rollouts_file),
            "bytes": rollouts_file.stat().st_size,
            "checkpoint": str(checkpoint),
        }

    def replay():
        if rollouts_file is None:
            rollouts = world_model_runs.roll_out(env_cfg, checkpoint, cfg.replay_episodes, cfg.pipeline.device)
        else:
            rollouts = world_model_runs.load_rollouts(rollouts_file)
        _replay(cfg, folder, rollouts)

    resume.run_once(folder, settings, cfg.pipeline.fresh, replay)
    return json.loads((folder / "replay.json").read_text())


def _replay(cfg: ExperimentConfig, folder: Path, rollouts: world_model_runs.Rollouts) -> None:
    folder.mkdir(parents=True)
    rows, strips = [], []
    for i, start in enumerate(rollouts.starts):
        family, scene, seed = start["task_family"], start["scene"], int(start["seed"])
        job = EpisodeJob(family, scene, seed, "optimal", cfg.pipeline.data.image_size)
        replayed = replay_actions(worker_env(job), job, rollouts.actions[:, i], {})
        simulator = np.concatenate([replayed.images[camera] for camera in rollouts.cameras], axis=1)  # (T, 2H, W, 3)
        clip = [np.concatenate([rollouts.frames[t, i], simulator[t]], axis=1) for t in range(len(simulator))]
        row = {
            "episode_index": start["episode_index"],
            "family": family,
            "scene": scene,
            "world_model_return": round(float(rollouts.returns[i]), 3),
            "world_model_success": bool(rollouts.success[i]),
            "simulator_success": bool(replayed.success.any()),
        }
        outcome = f"wm-{'success' if row['world_model_success'] else 'failure'}_sim-" + (
            "success" if row["simulator_success"] else "failure"
        )
        row["video"] = f"{i:02d}_{family}_{outcome}.mp4"
        write_video(folder / row["video"], clip, CONTROL_FREQ)
        rows.append(row)
        strips.append(_strip(clip))
    iio.imwrite(folder / "replay.png", np.concatenate(strips[:REPLAY_STRIPS], axis=0))
    write_text_atomically(folder / "replay.json", json.dumps(rows, indent=2))


def _strip(clip: list[np.ndarray], columns: int = 5) -> np.ndarray:
    """`columns` frames of a clip, evenly spaced, side by side."""
    picks = np.linspace(0, len(clip) - 1, columns).round().astype(int)
    return np.concatenate([clip[t] for t in picks], axis=1)


# The experiment's steps, in order; each header names one.
STEPS = ("world-model env", "SFT", "levers", "PPO", "Table 1", "checkpoint curve", "replay", "report")


def run_experiment(cfg: ExperimentConfig) -> Path:
    """Run every step of the protocol (skipping those complete); returns the report. With --world_model_runs, the
    runs in the world model are packed for the machine where its models train (returns the pack) until they are
    brought back, then taken as this protocol's own."""
    p, run = cfg.pipeline, Path(cfg.pipeline.output_dir).resolve()
    elsewhere = Path(cfg.world_model_runs).resolve() if cfg.world_model_runs else None
    trained = trained_stages(p, run, world_models=elsewhere is None)
    out = run / layout.protocol_dir(cfg.protocol)  # this protocol's policy runs
    clock = StageClock(STEPS)
    wm_env, rollouts = None, None
    if elsewhere is not None:
        clock("world-model env", f"none here: the runs in roboscape_wm go where its models are ({elsewhere})")
    else:
        clock("world-model env", "the roboscape_wm env on the run's world models (every start's goal, once)")
        wm_env = stages.world_model_env(
            p, trained.demonstrations, trained.tokenizer, trained.models, trained.done, trained.reward_models
        )
        wm_env = replace(wm_env, goal_file=str(run / layout.GOAL_FILE))  # one set of goals for every protocol
    sft_data = "the initial scene" if cfg.protocol == methods.PAPER_PROTOCOL else "every training scene"
    # Under the paper's protocol its IND, the scene SFT learned with new initial states, is a column of its own.
    scene = methods.initial_scene() if cfg.protocol == methods.PAPER_PROTOCOL else None
    splits = "the initial scene, IND and OOD" if scene else "IND and OOD"
    clock("SFT", f"the SFT checkpoint: {cfg.sft_checkpoint or f'SFT with lerobot-train on {sft_data}'}")
    sft = sft_policy(cfg, out, trained.demonstrations)
    policy = next(iter(sft))
    clock("levers", f"the guards against gaming the world model: {', '.join(cfg.levers) or 'none'}")
    if elsewhere is None:
        levers = lever_runs(cfg, run, trained, wm_env)
    elif not (elsewhere / world_model_runs.RUNS_DIR / world_model_runs.RESULTS).is_file():
        # Pack, then do here what needs no world model while the runs go: PPO in the simulator, its Table 1 cells.
        pack = pack_world_model_runs(cfg, run, out, trained, sft, elsewhere / world_model_runs.PACK_DIR)
        wait = (
            f"The runs in the world model are packed in {pack}: run them where the world models train "
            f"(scripts/experiments/device_world_models.sh claim), bring them back into "
            f"{elsewhere / world_model_runs.RUNS_DIR} and run this command again."
        )
        print(wait)
        clock("PPO", "PPO in roboscape_maniskill (those in roboscape_wm run where its models are)")
        rl = policy_stages.rl(p, out, trained.demonstrations, None, sft)
        clock("Table 1", f"success in the simulator of SFT and of PPO in the simulator, {splits}")
        checkpoints = {name: {methods.SFT: sft[name]} | runs for name, runs in rl.items()}
        policy_stages.simulator_eval(p, out, trained.demonstrations, checkpoints, scene)
        clock.done()
        print(wait)
        return pack
    clock(
        "PPO",
        "PPO in roboscape_wm and in roboscape_maniskill"
        + (" (and the reward ablation)" if p.reward_ablation else "")
        + (" (and each lever)" if cfg.levers else "")
        + (f" (those in roboscape_wm brought back from {elsewhere})" if elsewhere else ""),
    )
    rl = policy_stages.rl(p, out, trained.demonstrations, wm_env, sft, levers if elsewhere is None else None)
    if elsewhere is not None:
        taken = take_world_model_runs(cfg, out, elsewhere / world_model_runs.RUNS_DIR, policy)
        rl[policy] |= taken["runs"]
        levers = {m: None for m in taken["runs"] if m in methods.LEVERS.values()}
        if replay := taken["results"].get("replay"):
            rollouts = elsewhere / world_model_runs.RUNS_DIR / replay["file"]
    checkpoints = {name: {methods.SFT: sft[name]} | runs for name, runs in rl.items()}
    clock("Table 1", f"success in the simulator, {splits} (Table 1)")
    results = policy_stages.simulator_eval(p, out, trained.demonstrations, checkpoints, scene)
    clock("checkpoint curve", "simulator success of PPO's checkpoints in the world model, OOD")
    curve = checkpoint_curve(cfg, out, trained.demonstrations, policy, sft[policy])
    lever_curves = {m: checkpoint_curve(cfg, out, trained.demonstrations, policy, sft[policy], m) for m in levers}
    clock("replay", "world-model rollouts replayed in the simulator")
    ppo_env = None
    if elsewhere is None:
        ppo_env = policy_stages.rl_envs(p, out, trained.demonstrations, wm_env)[methods.RL_WORLD_MODEL]
    replays = replay_in_simulator(cfg, out, ppo_env, rl[policy][methods.RL_WORLD_MODEL], rollouts)
    clock("report", "the claim's report")
    report = write_experiment_report(cfg, out, results, curve, replays, lever_curves)
    clock.done()
    return report
