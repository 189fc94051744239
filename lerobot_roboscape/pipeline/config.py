"""What one run of the pipeline does: the config of `roboscape-demo` and `roboscape-experiment`.

The config nests the stages' own settings, each under the name its stage gives it (`--tokenizer.*`, `--wm.*`,
`--wm_train.*`, `--ppo.*`, `--eval.*`, ...). Its defaults are the tiny scale; every other scale is a file of
overrides beside this module (`scales/<name>.yaml`), which `--scale=<name>` applies before the flags, as LeRobot's
`--config_path` does. A field set on the command line wins over the scale's file.
"""

import re
import tempfile
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import draccus
import yaml
from lerobot.utils.utils import flatten_dict

from lerobot_roboscape.reward.train import RewardTrainingConfig
from lerobot_roboscape.rl.configuration_ppo import NUM_ENVS
from lerobot_roboscape.tasks import TASK_FAMILIES
from lerobot_roboscape.tokenizer.configuration_tokenizer import TinyTokenizerConfig, TokenizerConfig
from lerobot_roboscape.tokenizer.train import TokenizerTrainingConfig
from lerobot_roboscape.world_model.configuration_world_model import TinyWorldModelConfig, WorldModelConfig
from lerobot_roboscape.world_model.train import WorldModelTrainingConfig
from roboscape_core.errors import InvalidInputError

SCALES_DIR = Path(__file__).with_name("scales")
TINY = "tiny"  # the defaults below: the embedded default, shows every stage working and judges none
# The scales sized to judge the bench experiment's targets; the others only show every stage working.
JUDGED_SCALES = ("bench", "bench_gpu", "paper")


def preset(choice: draccus.ChoiceRegistry) -> str:
    """The registered name of a preset (`--tokenizer.type=bench` -> "bench")."""
    return choice.get_choice_name(type(choice))


def scales() -> list[str]:
    return [TINY, *sorted(p.stem for p in SCALES_DIR.glob("*.yaml"))]


@dataclass
class DataConfig:
    """The collections (`roboscape-collect`'s names). Args:
    families: task families to collect and evaluate.
    max_scenes: IND scenes per family (null: all).
    episodes_per_scene: planner episodes per (family, IND scene), a quarter of them deliberately failed.
    explore_episodes_per_scene: exploratory episodes per (family, IND scene), noisy, excursion and random dealt
        evenly (demos/exploration.py): a dataset of their own that only the action world model trains on.
    heldout_scenes: OOD scenes of the held-out collection (4 episodes per family and scene, half of them failed)
        that the fidelity, done and reward reports are measured on, and of the controllability set's starts; with
        them, a validation collection (one episode per IND scene, half failed) on which the done threshold is
        chosen. 0: one recorded and converted IND episode instead, and the done threshold chosen on the
        demonstrations.
    report_episodes: held-out episodes (spread over the held-out dataset) behind the fidelity and reward reports.
    ind_control_starts: starts per (family, IND scene) of the IND controllability set (new initial states of the
        training scenes) behind the IND fidelity report, with held-out scenes; 0: neither, for a run whose models
        were judged in domain where they were trained (the set takes an hour on a CPU that renders slowly).
    initial_scene_episodes: planner attempts per family in the initial scene, half of them suboptimal, whose
        successful ones the paper protocol's SFT imitates (the paper collected 500 optimal and 500 suboptimal per
        task and scene); 0: that scene's share of the demonstrations instead.
    image_size: camera resolution (the tokenizer's image_size must match).
    workers: ManiSkill worker processes (collection, and evaluations run side by side).
    """

    families: list[str] = field(default_factory=lambda: ["pick_place", "push"])
    max_scenes: int | None = 2
    episodes_per_scene: int = 2
    explore_episodes_per_scene: int = 1
    heldout_scenes: int = 0
    report_episodes: int = 8
    ind_control_starts: int = 1
    initial_scene_episodes: int = 0
    image_size: int = 64
    workers: int = 2


@dataclass
class SFTConfig:
    """`lerobot-train`'s settings (its own flag names). Args:
    steps, batch_size, num_workers: of the MLP policy's run.
    openvla_steps: of OpenVLA's (LoRA) run; 0 skips it. With OpenVLA, the table has its rows too.
    openvla_base_model: OpenVLA's `--policy.base_model`: "tiny" (random, CPU) or a checkpoint such as
        openvla/openvla-7b.
    """

    steps: int = 400
    batch_size: int = 16
    num_workers: int = 2
    openvla_steps: int = 0
    openvla_base_model: str = "tiny"


@dataclass
class LeRobotEvalConfig:
    """`lerobot-eval` in `roboscape_wm` (`--eval.n_episodes`, `--env.episode_length`; null: as env.episode_length)."""

    n_episodes: int = 2
    episode_length: int | None = None


@dataclass
class PPOSettings:
    """What every PPO run of the pipeline shares (`roboscape-ppo`'s own names; the pipeline sets the policy, the env
    and the output). Args:
    num_envs: parallel episodes.
    iterations: PPO iterations (one episode per parallel env each), at most.
    time_budget_s: wall-clock budget of each run in seconds (null: none), so that RL in the world model and in the
        simulator get the same time.
    critic_warmup_iterations: first iterations that train the critic only (null: the policy type's default); a run
        of a few iterations (CPU) keeps it at 1 so that the policy learns at all.
    save_freq: iterations between checkpoints.
    """

    num_envs: int = NUM_ENVS
    iterations: int = 2
    time_budget_s: float | None = None
    critic_warmup_iterations: int | None = 1
    save_freq: int = 2


@dataclass
class EnvSettings:
    """The RL envs' settings (`roboscape_wm`'s own names; the pipeline sets the models and the data). Args:
    episode_length: control steps per PPO episode, in both envs; null: per task family, its longest successful
        demonstration.
    starts_per_scene: demonstrations per (family, scene) whose first frames start PPO's world-model episodes (null:
        all); each start's goal is generated once, before PPO.
    max_goal_steps: control steps the text world model may generate while looking for a goal.
    """

    episode_length: int | None = 30
    starts_per_scene: int | None = None
    max_goal_steps: int = 40


@dataclass
class EvalSettings:
    """Table 1's simulator evaluation (`roboscape-eval`'s own names). Args:
    episodes: episodes per (split, family) behind each cell.
    episode_length: steps of those episodes; null: as env.episode_length.
    """

    episodes: int = 1
    episode_length: int | None = None


def _training(config_class: type, steps: int, batch_size: int):
    return field(default_factory=partial(config_class, steps=steps, batch_size=batch_size))


@dataclass
class PipelineConfig:
    """Args:
    scale: the scale whose file (scales/<scale>.yaml) was applied: "tiny" (the defaults), "smoke" (every stage at
        its smallest: the end-to-end test), "bench" (the paper's experiment at the largest size 2 CPU cores run in
        hours), "bench_gpu" (bench with the models trained longer on one GPU) or "paper" (GPUs, days).
    output_dir: where every artifact goes. A rerun skips each stage whose outputs are complete and were made with
        the same settings (so a killed run resumes); --fresh=true starts over.
    fresh: retrain everything, ignoring what output_dir holds.
    stop_after: run the stages up to this one and stop (a stage's name, e.g. "tokenizer": the data and the tokenizer
        that scripts/experiments/device_world_models.sh packs for a GPU); null: every stage.
    report_dir: also write the experiment's report (report.md, results.json, figures) here.
    device: "cpu", "cuda" or "auto", for every stage.
    data: the collections.
    tokenizer, tokenizer_train: the image tokenizer (`--tokenizer.type=tiny|bench|paper`, then any field) and its
        training, as `roboscape-train-tokenizer` names them (`--train.*` there).
    wm, wm_train, text_wm_train: the world models (`--wm.type=...`; each model's control is set by its stage) and
        the training of the action and of the text model, as `roboscape-train-wm` names them.
    world_models: models trained elsewhere, taken instead of training them here: a folder holding action/ and
        text/, each a `roboscape-train-wm` output_dir (pretrained_model/ beside its logs), and tokenizer/, the
        `roboscape-train-tokenizer` output_dir they learned, or a part of them (those missing are trained here; world
        models without tokenizer/ must have learned this run's), as scripts/experiments/device_world_models.sh
        brings them back from a GPU and carry_world_models.py carries a run's to another machine; null: train them.
    exploration_share: share of the action world model's training clips drawn from the exploratory episodes.
    reward_models: train the baseline reward models (embedding, proxy) and the success classifier.
    reward_train: their training (`roboscape-train-reward`'s `--train.*`).
    sft: lerobot-train of the policies.
    lerobot_eval: lerobot-eval of the SFT policies in `roboscape_wm`.
    ppo: every PPO run.
    env: the RL envs.
    eval: Table 1's simulator evaluation.
    ppo_one_scene: also run PPO in the simulator in one scene per family, as the paper's baseline did.
    reward_ablation: also run PPO in the world model on its sparse reward only and on its dense reward only (each
        evaluated out of domain).
    push_to_hub: upload every artifact to the Hub (needs `hf auth login`); otherwise write the repos to
        output_dir/hub.
    hub_namespace: the Hub user or organisation of the repos.
    """

    scale: str = TINY
    output_dir: str = "outputs/demo"
    fresh: bool = False
    stop_after: str | None = None
    report_dir: str | None = None
    device: str = "cpu"
    data: DataConfig = field(default_factory=DataConfig)
    tokenizer: TokenizerConfig = field(default_factory=TinyTokenizerConfig)
    tokenizer_train: TokenizerTrainingConfig = _training(TokenizerTrainingConfig, 200, 8)
    wm: WorldModelConfig = field(default_factory=TinyWorldModelConfig)
    wm_train: WorldModelTrainingConfig = _training(WorldModelTrainingConfig, 200, 4)
    text_wm_train: WorldModelTrainingConfig = _training(WorldModelTrainingConfig, 100, 4)
    world_models: str | None = None
    exploration_share: float = 0.5
    reward_models: bool = False
    reward_train: RewardTrainingConfig = field(default_factory=RewardTrainingConfig)
    sft: SFTConfig = field(default_factory=SFTConfig)
    lerobot_eval: LeRobotEvalConfig = field(default_factory=LeRobotEvalConfig)
    ppo: PPOSettings = field(default_factory=PPOSettings)
    env: EnvSettings = field(default_factory=EnvSettings)
    eval: EvalSettings = field(default_factory=EvalSettings)
    ppo_one_scene: bool = False
    reward_ablation: bool = False
    push_to_hub: bool = False
    hub_namespace: str = "local"

    def __post_init__(self):
        if self.scale not in scales():
            raise InvalidInputError(f"--scale must be one of {scales()}, got {self.scale!r}")
        unknown = [f for f in self.data.families if f not in TASK_FAMILIES]
        if unknown:
            raise InvalidInputError(f"unknown task families {unknown}; choose from {list(TASK_FAMILIES)}")
        if self.tokenizer.image_size != self.data.image_size:
            raise InvalidInputError(
                f"--tokenizer.image_size={self.tokenizer.image_size} differs from the cameras' "
                f"--data.image_size={self.data.image_size}: set both"
            )
        if self.data.ind_control_starts < 0:
            raise InvalidInputError(f"--data.ind_control_starts must be >= 0, got {self.data.ind_control_starts}")
        if self.data.initial_scene_episodes < 0:
            raise InvalidInputError(
                f"--data.initial_scene_episodes must be >= 0, got {self.data.initial_scene_episodes}"
            )


# The flat flags of the config before the stages' settings were nested: a script that still passes one is told
# the new flag, not left to draccus's list of every field.
RENAMED_FLAGS = {
    "families": "data.families",
    "scenes": "data.max_scenes",
    "episodes_per_scene": "data.episodes_per_scene",
    "explore_episodes_per_scene": "data.explore_episodes_per_scene",
    "heldout_scenes": "data.heldout_scenes",
    "report_episodes": "data.report_episodes",
    "image_size": "data.image_size",
    "workers": "data.workers",
    "tokenizer_preset": "tokenizer.type",
    "wm_preset": "wm.type",
    "tokenizer_steps": "tokenizer_train.steps",
    "tokenizer_batch_size": "tokenizer_train.batch_size",
    "wm_steps": "wm_train.steps",
    "text_wm_steps": "text_wm_train.steps",
    "wm_batch_size": "wm_train.batch_size",
    "reward_model_steps": "reward_models and --reward_train.steps",
    "mlp_steps": "sft.steps",
    "sft_batch_size": "sft.batch_size",
    "loader_workers": "sft.num_workers",
    "openvla_steps": "sft.openvla_steps",
    "openvla_base": "sft.openvla_base_model",
    "eval_episodes": "lerobot_eval.n_episodes",
    "eval_episode_length": "lerobot_eval.episode_length",
    "ppo_iterations": "ppo.iterations",
    "ppo_minutes": "ppo.time_budget_s (in seconds)",
    "ppo_critic_warmup": "ppo.critic_warmup_iterations",
    "ppo_envs": "ppo.num_envs",
    "ppo_episode_length": "env.episode_length",
    "wm_starts_per_scene": "env.starts_per_scene",
    "table_episodes": "eval.episodes",
    "table_episode_length": "eval.episode_length",
    "max_goal_steps": "env.max_goal_steps",
}


def scale_overrides(scale: str) -> dict:
    """The settings a scale's file changes from the defaults (nested as the config)."""
    if scale == TINY:
        return {}
    path = SCALES_DIR / f"{scale}.yaml"
    if not path.exists():
        raise InvalidInputError(f"--scale must be one of {scales()}, got {scale!r}")
    return {**yaml.safe_load(path.read_text()), "scale": scale}


def parse_config(config_class: type, args: list[str], prefix: str = ""):
    """`config_class` from the command line `args`, its PipelineConfig (at `prefix`, e.g. "pipeline.") first set to
    the scale its `--scale` names."""
    for arg in args:
        name = arg.split("=", 1)[0].removeprefix("--")
        if name.removeprefix(prefix) in RENAMED_FLAGS and name.startswith(prefix):
            raise InvalidInputError(f"--{name} is now --{prefix}{RENAMED_FLAGS[name.removeprefix(prefix)]}")
    flag = re.compile(rf"--{re.escape(prefix)}scale=(.*)")
    scale = next((m.group(1) for arg in args if (m := flag.fullmatch(arg))), TINY)
    # Every setting written out, not only the scale's: draccus builds a nested config that a flag touches from its
    # class's defaults, which would drop the defaults given here (the tiny scale's) beside the flag.
    # A preset (`type`) is written as its name alone, so that a flag naming another builds that one's defaults.
    defaults = {
        k: {"type": v["type"]} if isinstance(v, dict) and "type" in v else v
        for k, v in draccus.encode(PipelineConfig()).items()
    }
    overrides = _merged(defaults, scale_overrides(scale))
    for key in reversed(prefix.strip(".").split(".") if prefix else []):
        overrides = {key: overrides}
    with tempfile.NamedTemporaryFile("w", suffix=".yaml") as file:
        yaml.safe_dump(overrides, file)
        file.flush()
        return draccus.parse(config_class, config_path=file.name, args=args)


def _merged(base: dict, overrides: dict) -> dict:
    """`base` with `overrides` over it, key by key; a preset named by its `type` replaces the whole of its entry."""
    merged = dict(base)
    for key, value in overrides.items():
        descend = isinstance(value, dict) and isinstance(base.get(key), dict) and "type" not in value
        merged[key] = _merged(base[key], value) if descend else value
    return merged


def scale_config(scale: str = TINY, args: tuple[str, ...] = ()) -> PipelineConfig:
    """The config of `scale` with `args` (flags, as on the command line) over it: the same as `roboscape-demo
    --scale=<scale> <args>` runs."""
    return parse_config(PipelineConfig, [f"--scale={scale}", *args])


def settings_flags(cfg: PipelineConfig) -> list[str]:
    """The flags that make `cfg` from its scale's file: each setting that differs from it, as `--a.b=value`."""
    return changed_flags(cfg, scale_config(cfg.scale), ("scale", "output_dir", "report_dir"))


def changed_flags(cfg, reference, skip: tuple[str, ...] = ()) -> list[str]:
    """Each setting of the config `cfg` that differs from `reference`'s, as `--a.b=value`, but those under `skip`."""
    before = flatten_dict(draccus.encode(reference), sep=".")
    return [
        f"--{name}={as_flag(value)}"
        for name, value in flatten_dict(draccus.encode(cfg), sep=".").items()
        if name.split(".")[0] not in skip and before.get(name) != value
    ]


def as_flag(value) -> str:
    """A value as draccus parses it back from the command line."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, list | tuple):
        return "[" + ",".join(str(v) for v in value) + "]"
    return "null" if value is None else f"{value:g}" if isinstance(value, float) else str(value)
