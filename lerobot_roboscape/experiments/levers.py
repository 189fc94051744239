"""The guards against a policy that games the world model (issue 49), one entry each in `LEVERS`: its name on the
command line (`--levers=[kl,...]`), its method (a run of PPO in the world model beside the plain one, judged by the
simulator success of its checkpoints, OOD), its settings (`--lever.<name>.<field>`), the run it makes and how the
report describes it. Adding a lever is a settings class, a field of `LeverSettings` and an entry here; the plain run
and every lever are also run at the other PPO seeds of `REPEAT_SEEDS` (`plain_seed1`, `kl_seed1`, ...), so a lever is
judged by two seeds."""

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig, RoboscapeWorldModelEnvConfig
from lerobot_roboscape.experiments.done_refresh import DoneRefresh, ppo_with_done_refresh
from lerobot_roboscape.pipeline import data_stages, layout, stages
from lerobot_roboscape.pipeline.config import PipelineConfig
from lerobot_roboscape.pipeline.methods import RL_WORLD_MODEL, Method, initial_scene, world_model_variant
from lerobot_roboscape.pipeline.policy_stages import RLRun
from roboscape_core.errors import InvalidInputError


@dataclass
class KLSettings:
    """coef: the weight of the KL penalty to the SFT policy (PPO's --kl_coef)."""

    coef: float = 0.1


@dataclass
class EnsembleSettings:
    """members: action world models beside the run's own (seeds 1..n); retrain_blocks: each member is the run's
    action model with its last this many blocks and heads drawn afresh and trained alone, the trunk shared (null:
    whole models trained as the run's own); steps_share: each member's training steps, as a share of the run's
    action model's; disagreement_penalty: lambda on their disagreement (roboscape_wm's --env.disagreement_penalty);
    disagreement_threshold: episodes halt above it (--env.disagreement_threshold; null: never); trained: members
    trained elsewhere (pretrained_model folders of action world models, e.g. other seeds from a GPU), taken instead
    of training `members` here."""

    members: int = 2
    retrain_blocks: int | None = 1
    steps_share: float = 0.25
    disagreement_penalty: float = 1.0
    disagreement_threshold: float | None = None
    trained: list[str] | None = None

    def __post_init__(self):
        if self.members < 1:
            raise InvalidInputError(f"--lever.ensemble.members must be >= 1, got {self.members}")
        if self.trained is not None:
            if not self.trained:
                raise InvalidInputError("--lever.ensemble.trained is empty: name at least one member, or leave it null")
            self.members = len(self.trained)
        if not 0 < self.steps_share <= 1:
            raise InvalidInputError(f"--lever.ensemble.steps_share must be in (0, 1], got {self.steps_share}")


@dataclass
class BranchedSettings:
    """branches_per_episode: starts per demonstration (--env.branches_per_episode); episode_length: in control
    steps."""

    branches_per_episode: int = 4
    episode_length: int = 24


@dataclass
class RefreshSettings:
    """rounds: slices of PPO's clock, the done head refitted before each on simulator rollouts of
    the current policy in the training scenes; episodes: simulator episodes of the policy per refit;
    initial_scene_episodes: that many more per refit in the paper protocol's initial scene, where its SFT policy
    succeeds (a refit on the training scenes alone sees the one-scene policy fail, and the done falls silent);
    branched: PPO's episodes as the branched lever plays them (--lever.branched's settings): short, from starts along
    the demonstrations, some near success, before the world model's frames drift off the data."""

    rounds: int = 3
    episodes: int = 16
    initial_scene_episodes: int = 0
    branched: bool = False

    def __post_init__(self):
        for name in ("rounds", "episodes"):
            if getattr(self, name) < 1:
                raise InvalidInputError(f"--lever.refresh.{name} must be >= 1, got {getattr(self, name)}")
        if self.initial_scene_episodes < 0:
            raise InvalidInputError(
                f"--lever.refresh.initial_scene_episodes must be >= 0, got {self.initial_scene_episodes}"
            )


@dataclass
class TrustSettings:
    """target_kl: an iteration's update stops at the first minibatch whose approximate KL from the rollout's policy
    exceeds it (PPO's --target_kl), so no update carries the policy far from where its world-model data came from."""

    target_kl: float = 0.02

    def __post_init__(self):
        if self.target_kl <= 0:
            raise InvalidInputError(f"--lever.trust.target_kl must be > 0, got {self.target_kl}")


@dataclass
class RangeSettings:
    """margin: episodes halt, that frame unpaid and no success, where the predicted robot state leaves the action
    model's training range widened by this share of its span (roboscape_wm's --env.state_margin)."""

    margin: float = 0.1

    def __post_init__(self):
        if self.margin < 0:
            raise InvalidInputError(f"--lever.range.margin must be >= 0, got {self.margin}")


@dataclass
class LeverSettings:
    """Each lever's settings: starting points; what each measured goes in the claim's report."""

    kl: KLSettings = field(default_factory=KLSettings)
    ensemble: EnsembleSettings = field(default_factory=EnsembleSettings)
    branched: BranchedSettings = field(default_factory=BranchedSettings)
    refresh: RefreshSettings = field(default_factory=RefreshSettings)
    trust: TrustSettings = field(default_factory=TrustSettings)
    range: RangeSettings = field(default_factory=RangeSettings)


@dataclass
class LeverContext:
    """What a lever's run is made from: the pipeline run (`folder`, its settings, demonstrations and tokenizer),
    PPO in the world model's own env and the simulator's over the training scenes. `members`: the ensemble's world
    models where they were trained elsewhere (null: trained here)."""

    pipeline: PipelineConfig
    folder: Path
    demonstrations: DatasetConfig
    tokenizer: Path
    world_model: RoboscapeWorldModelEnvConfig
    simulator: RoboscapeManiSkillEnvConfig
    members: list[str] | None = None


@dataclass(frozen=True)
class Lever:
    """name: on the command line; method: its row; make: its run (env, PPO's settings, runner) from the context and
    its settings; describe: what it ran with, in words; simulator: it uses the simulator during PPO, so it runs
    where the simulator is."""

    name: str
    method: Method
    make: Callable[[LeverContext, LeverSettings], RLRun]
    describe: Callable[[LeverSettings], str]
    simulator: bool = False


def _ensemble(context: LeverContext, settings: LeverSettings) -> RLRun:
    s, p = settings.ensemble, context.pipeline
    members = context.members if context.members is not None else s.trained
    if members is None:
        data = data_stages.demonstrations(p.data, context.folder, p.fresh)  # complete: found, not collected again
        trained = stages.ensemble_members(
            p, context.folder, data, context.tokenizer, s.members, s.retrain_blocks, s.steps_share
        )
        members = [str(m) for m in trained]
    env = replace(
        context.world_model,
        ensemble=members,
        disagreement_penalty=s.disagreement_penalty,
        disagreement_threshold=s.disagreement_threshold,
    )
    return RLRun(env)


def _describe_ensemble(settings: LeverSettings) -> str:
    s = settings.ensemble
    if s.trained is not None:
        members = f"the run's action model and {s.members} more trained elsewhere ({', '.join(s.trained)})"
    elif s.retrain_blocks is not None:
        members = (
            f"the run's action model and {s.members} more (its last {s.retrain_blocks} block(s) and heads drawn "
            f"afresh and retrained alone, {s.steps_share:.0%} of its steps each)"
        )
    else:
        members = (
            f"the run's action model and {s.members} more (whole models trained from other seeds, "
            f"{s.steps_share:.0%} of its steps each)"
        )
    halt = "" if s.disagreement_threshold is None else f"; episodes halt above {s.disagreement_threshold} nats"
    return f"{members}; reward - {s.disagreement_penalty} x their disagreement{halt}"


def _branched(env: RoboscapeWorldModelEnvConfig, s: BranchedSettings) -> RoboscapeWorldModelEnvConfig:
    return replace(env, branches_per_episode=s.branches_per_episode, episode_length=s.episode_length)


def _describe_branched(s: BranchedSettings) -> str:
    return f"{s.branches_per_episode} starts per demonstration, episodes of {s.episode_length} steps"


def _refresh(context: LeverContext, settings: LeverSettings) -> RLRun:
    p = context.pipeline
    refresh = DoneRefresh(
        sim=context.simulator,
        tokenizer=str(context.tokenizer),
        demonstrations_repo_id=context.demonstrations.repo_id,
        demonstrations_root=context.demonstrations.root,
        cache_dir=str(context.folder / layout.TOKEN_CACHE_DIR),
        rounds=settings.refresh.rounds,
        episodes=settings.refresh.episodes,
        focus_scenes=[initial_scene()],
        focus_episodes=settings.refresh.initial_scene_episodes,
        device=p.device,
    )
    env = _branched(context.world_model, settings.branched) if settings.refresh.branched else context.world_model
    return RLRun(env, runner=partial(ppo_with_done_refresh, refresh=refresh))


def _describe_refresh(settings: LeverSettings) -> str:
    s = settings.refresh
    initial = f" (and {s.initial_scene_episodes} in the initial scene)" if s.initial_scene_episodes else ""
    branched = f"; branched: {_describe_branched(settings.branched)}" if s.branched else ""
    return (
        f"the done head refitted {s.rounds} times on {s.episodes} simulator episodes of the current policy"
        f"{initial}{branched}"
    )


LEVERS = {
    lever.name: lever
    for lever in (
        Lever(
            "kl",
            world_model_variant("KL to SFT", "kl"),
            lambda context, settings: RLRun(context.world_model, {"kl_coef": settings.kl.coef}),
            lambda settings: f"KL to the SFT policy x {settings.kl.coef}",
        ),
        Lever("ensemble", world_model_variant("ensemble disagreement", "ensemble"), _ensemble, _describe_ensemble),
        Lever(
            "branched",
            world_model_variant("branched short rollouts", "branched"),
            lambda context, settings: RLRun(_branched(context.world_model, settings.branched)),
            lambda settings: _describe_branched(settings.branched),
        ),
        Lever(
            "refresh",
            world_model_variant("done refreshed in the simulator", "done_refresh"),  # uses the simulator: its own row
            _refresh,
            _describe_refresh,
            simulator=True,
        ),
        Lever(
            "trust",
            world_model_variant("updates stopped at a target KL", "trust"),
            lambda context, settings: RLRun(context.world_model, {"target_kl": settings.trust.target_kl}),
            lambda settings: (
                f"each iteration's update stopped once its KL from the rollout's policy > {settings.trust.target_kl}"
            ),
        ),
        Lever(
            "range",
            world_model_variant("halted off the training states", "range"),
            lambda context, settings: RLRun(replace(context.world_model, state_margin=settings.range.margin)),
            lambda settings: (
                "episodes halted where the predicted robot state leaves the training range, widened by "
                f"{settings.range.margin:.0%} of its span"
            ),
        ),
    )
}
REPEAT_SEEDS = (1,)  # PPO's seeds the plain run and each lever are repeated at (`--levers=[kl_seed1]`): judged twice


def _at_seed(lever: Lever, seed: int) -> Lever:
    """`lever`'s run again at PPO's seed `seed`: its own row and folder."""
    tag = lever.method.tag.removeprefix(f"{RL_WORLD_MODEL.tag}_")

    def make(context: LeverContext, settings: LeverSettings) -> RLRun:
        run = lever.make(context, settings)
        return replace(run, settings=run.settings | {"seed": seed})

    return Lever(
        f"{lever.name}_seed{seed}",
        world_model_variant(f"{lever.method.variant}, seed {seed}", f"{tag}_seed{seed}"),
        make,
        lambda settings: f"{lever.describe(settings)}; PPO's seed {seed}",
        lever.simulator,
    )


def _plain_at_seed(seed: int) -> Lever:
    return Lever(
        f"plain_seed{seed}",
        world_model_variant(f"seed {seed}", f"seed{seed}"),
        lambda context, settings: RLRun(context.world_model, {"seed": seed}),
        lambda settings: f"the plain run at PPO's seed {seed}",
    )


LEVERS |= {
    repeat.name: repeat
    for seed in REPEAT_SEEDS
    for repeat in (_plain_at_seed(seed), *(_at_seed(lever, seed) for lever in LEVERS.values()))
}
BY_METHOD = {lever.method: lever for lever in LEVERS.values()}


def lever_runs(names: list[str], context: LeverContext, settings: LeverSettings) -> dict[Method, RLRun]:
    """{lever's method: its run} of the levers named, in their order."""
    return {LEVERS[name].method: LEVERS[name].make(context, settings) for name in names}


def lever_descriptions(methods, settings: LeverSettings) -> dict[str, str]:
    """{lever's method: what it ran with, in words} of the levers whose methods are given."""
    return {method: BY_METHOD[Method.named(method)].describe(settings) for method in methods}
