"""The paper's claim (Table 1), measured on the models a pipeline run already trained: PPO from the SFT checkpoint
in the world model, in the simulator in one scene and in every training scene, at equal wall-clock; the reward
ablation; the simulator success of PPO's checkpoints along its run; world-model rollouts beside the same actions
replayed in the simulator; Table 1 with 95% intervals of the differences; and the report.

Its inputs are the stages before PPO in `output_dir`, as `roboscape-demo` writes them: the demonstrations, the
tokenizer, both world models and the done report (and the SFT checkpoint, unless one is given). Each step skips
what a run with the same settings completed, so a killed run resumes.
"""

import hashlib
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.dataset.reader import open_dataset
from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.experiments import world_model_runs
from lerobot_roboscape.experiments.curves import Curves, checkpoint_curves
from lerobot_roboscape.experiments.experiment_report import write_experiment_report
from lerobot_roboscape.experiments.levers import BY_METHOD, LEVERS, LeverContext, LeverSettings, lever_runs
from lerobot_roboscape.experiments.pack_format import RESULTS, PackResults, read_results
from lerobot_roboscape.experiments.replay import replay_in_simulator
from lerobot_roboscape.experiments.trained import TrainedStages, trained_stages
from lerobot_roboscape.pipeline import data_stages, layout, methods, policy_stages, resume, stages
from lerobot_roboscape.pipeline.clock import StageClock
from lerobot_roboscape.pipeline.config import PipelineConfig
from lerobot_roboscape.pipeline.methods import Method
from lerobot_roboscape.pipeline.policy_stages import RLRun
from lerobot_roboscape.reward.done_report import token_episodes
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.training.loop import resolve_device
from roboscape_core.errors import InvalidInputError, MissingInputError

logger = logging.getLogger(__name__)


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
        plain one, judged by the simulator success of its checkpoints (OOD); pipeline/levers.py lists them and says
        what each does.
    lever: each lever's settings (`--lever.kl.coef`, `--lever.ensemble.members`, ...): starting points; what each
        measured goes in the report.
    curve_episodes: simulator episodes per family (OOD) behind each point of the curve of PPO's checkpoints.
    curve_points: points of each such curve: the SFT checkpoint and checkpoints evenly spread over the run (at least
        2: SFT and the last).
    replay_rollouts: world-model episodes of each policy after PPO in the world model (the plain run's and each
        lever's), from starts spread over families and scenes, from which the replay picks.
    replay_episodes: of them, at most this many the world model called successes, and as many it called failures,
        replayed in the simulator (16: the share of its successes the simulator confirms rests on that many when the
        done fires in a quarter of the rollouts).
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
    lever: LeverSettings = field(default_factory=LeverSettings)
    curve_episodes: int = 10
    curve_points: int = 6
    replay_rollouts: int = 64
    replay_episodes: int = 16
    world_model_runs: str | None = None
    report_dir: str = "docs/results/bench"
    readme: str | None = "README.md"

    def __post_init__(self):
        if self.protocol not in methods.PROTOCOLS:
            raise InvalidInputError(f"--protocol must be one of {list(methods.PROTOCOLS)}, got {self.protocol!r}")
        if unknown := [lever for lever in self.levers if lever not in LEVERS]:
            raise InvalidInputError(f"--levers {unknown} unknown; choose from {list(LEVERS)}")
        for name in ("curve_episodes", "replay_rollouts", "replay_episodes"):
            if getattr(self, name) < 1:
                raise InvalidInputError(f"--{name} must be >= 1, got {getattr(self, name)}")
        if self.world_model_runs is not None and (simulator := [n for n in self.levers if LEVERS[n].simulator]):
            raise InvalidInputError(
                f"--levers={simulator} cannot run with --world_model_runs: they use the simulator during PPO, and the "
                "simulator stays here while those runs go where the world models are"
            )
        if self.curve_points < 2:
            raise InvalidInputError(
                f"--curve_points must be >= 2 (SFT and the last checkpoint), got {self.curve_points}"
            )


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


def lever_context(cfg: ExperimentConfig, run: Path, out: Path, trained: TrainedStages, wm_env, members=None):
    """What the levers' runs are made from: the run's stages, PPO in the world model's env and the simulator's."""
    envs = policy_stages.rl_envs(cfg.pipeline, out, trained.demonstrations, wm_env)
    return LeverContext(
        cfg.pipeline,
        run,
        trained.demonstrations,
        trained.tokenizer,
        envs[methods.RL_WORLD_MODEL],
        envs[methods.RL_MANISKILL],
        members,
    )


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
        p, trained.demonstrations, trained.tokenizer, layout.WorldModelPaths(placeholder, placeholder)
    )
    runs = {
        method: RLRun(env)
        for method, env in policy_stages.rl_envs(p, out, trained.demonstrations, wm_env).items()
        if isinstance(env, RoboscapeWorldModelEnvConfig)
    }
    context = lever_context(cfg, run, out, trained, wm_env, members=[world_model_runs.ON_DEVICE])
    runs |= lever_runs(cfg.levers, context, cfg.lever)
    jobs = {
        Method.named(method).tag: world_model_runs.Job(
            method,
            policy_stages.ppo_config(p, out, policy, method, checkpoint, job.env, job.settings),
            ensemble=bool(job.env.ensemble),
        )
        for method, job in runs.items()
    }
    data = data_stages.demonstrations(p.data, run, p.fresh)  # complete: found, not collected again
    sets = {"validation": data.validation, "heldout": stages.spread(data.heldout, p.data.report_episodes)}
    extra = {
        "replay": {"episodes": cfg.replay_rollouts},
        "ensemble": {
            "members": cfg.lever.ensemble.members,
            "retrain_blocks": cfg.lever.ensemble.retrain_blocks,
            "steps_share": cfg.lever.ensemble.steps_share,
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


@dataclass(frozen=True)
class TakenRuns:
    """The world-model runs taken back: the final checkpoint of each method's run here, what the device reported,
    and each method's rollouts for the replay."""

    runs: dict[str, Path]
    results: PackResults
    rollouts: dict[str, Path]


def take_world_model_runs(cfg: ExperimentConfig, out: Path, folder: Path, policy: str) -> TakenRuns:
    """The runs `run_pack` made, brought back into `folder`, taken as this protocol's own (each into the folder its
    method's run would have here, its seconds kept)."""
    results = read_results(folder, methods.RL_WORLD_MODEL)
    record = hashlib.sha256((folder / RESULTS).read_bytes()).hexdigest()[:16]
    runs = {}
    for run in results.runs.values():
        dest = out / layout.rl_dir(policy, run.method)
        settings = {"world_model_run": str(run.folder), "results": record}
        if not resume.is_done(dest, settings, cfg.pipeline.fresh):
            resume.start(dest)
            world_model_runs.copy_run(run.folder, dest)
            resume.mark_done(dest, settings, seconds=run.seconds)
        runs[run.method] = dest / run.final.relative_to(run.folder)
    rollouts = {run.method: folder / results.replays[tag] for tag, run in results.runs.items()}
    return TakenRuns(runs, results, rollouts)


# The experiment's steps, in order; each header names one.
STEPS = ("world-model env", "SFT", "levers", "PPO", "Table 1", "checkpoint curve", "replay", "report")


@dataclass(frozen=True)
class Experiment:
    """A protocol's experiment on a pipeline run: the run's folder, the protocol's folder in it (`out`), what the
    run trained, and where the runs in the world model go (`elsewhere`, with --world_model_runs)."""

    cfg: ExperimentConfig
    run: Path
    out: Path
    trained: TrainedStages
    elsewhere: Path | None

    @classmethod
    def of(cls, cfg: ExperimentConfig) -> "Experiment":
        run = Path(cfg.pipeline.output_dir).resolve()
        elsewhere = Path(cfg.world_model_runs).resolve() if cfg.world_model_runs else None
        trained = trained_stages(cfg.pipeline, run, world_models=elsewhere is None)
        return cls(cfg, run, run / layout.protocol_dir(cfg.protocol), trained, elsewhere)

    @property
    def runs_back(self) -> Path | None:
        """The folder the runs in the world model were brought back into, once they are."""
        folder = self.elsewhere and self.elsewhere / world_model_runs.RUNS_DIR
        return folder if folder and (folder / RESULTS).is_file() else None

    @property
    def scene(self) -> str | None:
        """Under the paper's protocol, the scene SFT learned: new initial states there are a column of their own."""
        return methods.initial_scene() if self.cfg.protocol == methods.PAPER_PROTOCOL else None

    def sft(self, clock: StageClock) -> dict[str, Path]:
        data = "the initial scene" if self.scene else "every training scene"
        clock("SFT", f"the SFT checkpoint: {self.cfg.sft_checkpoint or f'SFT with lerobot-train on {data}'}")
        return sft_policy(self.cfg, self.out, self.trained.demonstrations)

    def world_model_env(self) -> RoboscapeWorldModelEnvConfig:
        """The roboscape_wm env on the run's world models, with one set of goals for every protocol."""
        p, t = self.cfg.pipeline, self.trained
        env = stages.world_model_env(p, t.demonstrations, t.tokenizer, t.models, t.done, t.reward_models)
        return replace(env, goal_file=str(self.run / layout.GOAL_FILE))

    def splits(self) -> str:
        return "the initial scene, IND and OOD" if self.scene else "IND and OOD"


@dataclass(frozen=True)
class Packed:
    """The runs in the world model, packed for the machine where its models train (`folder`), with what to do."""

    folder: Path
    runs_dir: Path

    def __str__(self) -> str:
        return (
            f"The runs in the world model are packed in {self.folder}: run them where the world models train "
            f"(scripts/experiments/device_world_models.sh claim), bring them back into {self.runs_dir} and run this "
            "command again."
        )


def pack_experiment(cfg: ExperimentConfig) -> Packed:
    """With --world_model_runs, before the runs come back: pack the runs in the world model for the machine where
    its models train, and do here what needs no world model meanwhile (SFT, PPO in the simulator, their Table 1
    cells)."""
    e = Experiment.of(cfg)
    p, clock = cfg.pipeline, StageClock(STEPS)
    clock("world-model env", f"none here: the runs in roboscape_wm go where its models are ({e.elsewhere})")
    sft = e.sft(clock)
    clock("levers", f"the guards against gaming the world model: {', '.join(cfg.levers) or 'none'}")
    dest = e.elsewhere / world_model_runs.PACK_DIR
    pack = pack_world_model_runs(cfg, e.run, e.out, e.trained, sft, dest)
    packed = Packed(pack, e.elsewhere / world_model_runs.RUNS_DIR)
    print(packed)
    clock("PPO", "PPO in roboscape_maniskill (those in roboscape_wm run where its models are)")
    rl = policy_stages.rl(p, e.out, e.trained.demonstrations, None, sft)
    clock("Table 1", f"success in the simulator of SFT and of PPO in the simulator, {e.splits()}")
    checkpoints = policy_stages.every_checkpoint(sft, rl)
    policy_stages.simulator_eval(p, e.out, e.trained.demonstrations, checkpoints, e.scene)
    clock.done()
    print(packed)
    return packed


def run_experiment(cfg: ExperimentConfig) -> Path:
    """Run every step of the protocol (skipping those complete); returns the report. With --world_model_runs, the
    runs in the world model are taken back (pack_experiment packed them) as this protocol's own."""
    e = Experiment.of(cfg)
    if e.elsewhere and not e.runs_back:
        raise MissingInputError(
            f"--world_model_runs={cfg.world_model_runs}: the runs in the world model are not back in "
            f"{e.elsewhere / world_model_runs.RUNS_DIR}; pack them first (pack_experiment; roboscape-experiment packs "
            "them while they are not back)"
        )
    p, clock, trained = cfg.pipeline, StageClock(STEPS), e.trained
    wm_env, levers, rollouts, taken = None, {}, {}, None
    if e.runs_back:
        clock("world-model env", f"none here: the runs in roboscape_wm went where its models are ({e.elsewhere})")
    else:
        clock("world-model env", "the roboscape_wm env on the run's world models (every start's goal, once)")
        wm_env = e.world_model_env()
    sft = e.sft(clock)
    policy = next(iter(sft))
    clock("levers", f"the guards against gaming the world model: {', '.join(cfg.levers) or 'none'}")
    context = None if wm_env is None else lever_context(cfg, e.run, e.out, trained, wm_env)
    if context is not None:
        levers = lever_runs(cfg.levers, context, cfg.lever)
    clock(
        "PPO",
        "PPO in roboscape_wm and in roboscape_maniskill"
        + (" (and the reward ablation)" if p.reward_ablation else "")
        + (" (and each lever)" if cfg.levers else "")
        + (f" (those in roboscape_wm brought back from {e.elsewhere})" if e.runs_back else ""),
    )
    rl = policy_stages.rl(p, e.out, trained.demonstrations, wm_env, sft, levers)
    if e.runs_back:
        taken = take_world_model_runs(cfg, e.out, e.runs_back, policy)
        rl[policy] |= taken.runs
        levers = {m: None for m in taken.runs if Method.named(m) in BY_METHOD}
        rollouts = taken.rollouts
    checkpoints = policy_stages.every_checkpoint(sft, rl)
    clock("Table 1", f"success in the simulator, {e.splits()} (Table 1)")
    results = policy_stages.simulator_eval(p, e.out, trained.demonstrations, checkpoints, e.scene)
    clock("checkpoint curve", "simulator success of PPO's checkpoints, OOD, in the world model and in ManiSkill")
    baselines = [m for m in (methods.RL_MANISKILL_ONE_SCENE, methods.RL_MANISKILL) if m in rl[policy]]
    runs = [methods.RL_WORLD_MODEL, *levers, *baselines]
    by_run = checkpoint_curves(cfg, e.out, trained.demonstrations, policy, sft[policy], runs)
    curves = Curves(by_run[runs[0]], {m: by_run[m] for m in levers}, {m: by_run[m] for m in baselines})
    clock("replay", "each world-model run's rollouts replayed in the simulator")
    envs = (
        {} if context is None else {methods.RL_WORLD_MODEL: context.world_model} | {m: r.env for m, r in levers.items()}
    )
    replays = {
        m: replay_in_simulator(
            p,
            e.out / layout.replay_dir(m),
            envs.get(m),
            rl[policy][m],
            rollouts.get(m),
            episodes=cfg.replay_rollouts,
            per_outcome=cfg.replay_episodes,
        )
        for m in [methods.RL_WORLD_MODEL, *levers]
    }
    clock("report", "the claim's report")
    report = write_experiment_report(cfg, e.out, results, curves, replays, taken and taken.results)
    clock.done()
    return report


def run_or_pack(cfg: ExperimentConfig) -> Path | Packed:
    """The command's step: the runs in the world model packed while they are elsewhere and not back, else the
    whole experiment (its report)."""
    if cfg.world_model_runs and not Experiment.of(cfg).runs_back:
        return pack_experiment(cfg)
    return run_experiment(cfg)
