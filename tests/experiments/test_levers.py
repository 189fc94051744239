"""The methods as values and the levers' registry: a method read back from a results file by its name is the same
method (its tag, whether it runs OOD only); each lever makes its run from its own settings (env, PPO's settings,
runner) and describes it; the experiment's config takes them from the command line."""

import copy
import dataclasses
import pickle
from functools import partial
from pathlib import Path

import pytest
from draccus.utils import ParsingError
from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig, RoboscapeWorldModelEnvConfig
from lerobot_roboscape.experiments.done_refresh import ppo_with_done_refresh
from lerobot_roboscape.experiments.experiment import ExperimentConfig
from lerobot_roboscape.experiments.levers import (
    LEVERS,
    EnsembleSettings,
    LeverContext,
    LeverSettings,
    RefreshSettings,
    lever_descriptions,
    lever_runs,
)
from lerobot_roboscape.pipeline import policy_stages
from lerobot_roboscape.pipeline.config import PipelineConfig, parse_config
from lerobot_roboscape.pipeline.layout import rl_dir
from lerobot_roboscape.pipeline.methods import REWARD_ABLATION, RL_WORLD_MODEL, SFT, Method, initial_scene
from lerobot_roboscape.pipeline.policy_stages import RLRun
from lerobot_roboscape.pipeline.ppo_run import ppo
from roboscape_core.errors import InvalidInputError


@dataclasses.dataclass
class PickleBox:
    method: Method


def test_a_method_read_back_by_its_name_is_the_same_method():
    kl = LEVERS["kl"].method
    assert Method.named(str(kl)) is kl and Method.named("RL w. World Model, KL to SFT").tag == "ppo_world_model_kl"
    assert kl == "RL w. World Model, KL to SFT" and {kl: 1} == {"RL w. World Model, KL to SFT": 1}  # a results key
    assert rl_dir("mlp", "RL w. World Model, done refreshed in the simulator") == Path(
        "rl/mlp/ppo_world_model_done_refresh"
    )
    assert [m.variant for m in REWARD_ABLATION] == ["sparse reward only", "dense reward only"]
    assert all(m.ood_only for m in (*REWARD_ABLATION, *(lever.method for lever in LEVERS.values())))
    assert not SFT.ood_only and not RL_WORLD_MODEL.ood_only
    with pytest.raises(KeyError, match="no method is named 'RL w. gravity'"):
        Method.named("RL w. gravity")
    with pytest.raises(ValueError, match="two methods are named 'Supervised finetune'"):
        Method("Supervised finetune", "sft_again")
    assert len({m.tag for m in Method._known.values()}) == len(Method._known)  # one folder per method
    # settings that hold a method are copied (dataclasses.asdict) and pickled (worker processes) whole
    assert copy.deepcopy(kl) is kl and pickle.loads(pickle.dumps(kl)) is kl and kl.tag == "ppo_world_model_kl"
    assert dataclasses.asdict(PickleBox(kl))["method"] is kl


@pytest.fixture
def context(tmp_path) -> LeverContext:
    return LeverContext(
        PipelineConfig(output_dir=str(tmp_path)),
        tmp_path,
        DatasetConfig(repo_id="local/demos", root=str(tmp_path / "demos")),
        tmp_path / "tokenizer",
        RoboscapeWorldModelEnvConfig(episode_length=30),
        RoboscapeManiSkillEnvConfig(),
        members=["member_1", "member_2"],
    )


def test_each_lever_makes_its_run_from_its_own_settings(context):
    cfg = parse_config(
        ExperimentConfig,
        [
            "--levers=[kl,ensemble,branched,refresh]",
            "--lever.kl.coef=0.3",
            "--lever.ensemble.disagreement_penalty=2.0",
            "--lever.branched.episode_length=12",
            "--lever.refresh.rounds=4",
            "--lever.refresh.initial_scene_episodes=8",
            "--lever.refresh.branched=true",
        ],
        "pipeline.",
    )
    runs = lever_runs(cfg.levers, context, cfg.lever)
    kl, ensemble, branched, refresh = (runs[LEVERS[name].method] for name in cfg.levers)
    assert kl.env == context.world_model and kl.settings == {"kl_coef": 0.3} and kl.runner is ppo
    assert ensemble.env.ensemble == ["member_1", "member_2"] and ensemble.env.disagreement_penalty == 2.0
    assert (branched.env.episode_length, branched.env.branches_per_episode) == (12, 4)
    assert context.world_model.episode_length == 30  # the plain run's env is left as it was
    assert isinstance(refresh.runner, partial) and refresh.runner.func is ppo_with_done_refresh
    refit = refresh.runner.keywords["refresh"]
    assert refit.rounds == 4 and refit.sim is context.simulator
    assert (refit.focus_scenes, refit.focus_episodes) == ([initial_scene()], 8)
    assert refresh.env == branched.env  # its PPO plays the branched lever's episodes
    described = lever_descriptions(runs, cfg.lever)
    assert described[LEVERS["kl"].method] == "KL to the SFT policy x 0.3"
    assert described[LEVERS["refresh"].method] == (
        "the done head refitted 4 times on 16 simulator episodes of the current policy (and 8 in the initial scene); "
        "branched: 4 starts per demonstration, episodes of 12 steps"
    )


def test_the_levers_settings_are_checked_where_they_are_given():
    with pytest.raises(ParsingError) as parsing:  # the command line's one-line error gives the cause
        parse_config(ExperimentConfig, ["--lever.refresh.rounds=0"], "pipeline.")
    assert str(parsing.value.__cause__) == "--lever.refresh.rounds must be >= 1, got 0"
    with pytest.raises(InvalidInputError, match="--lever.refresh.initial_scene_episodes must be >= 0, got -1"):
        RefreshSettings(initial_scene_episodes=-1)
    with pytest.raises(InvalidInputError, match="--lever.ensemble.steps_share must be in \\(0, 1\\], got 1.5"):
        EnsembleSettings(steps_share=1.5)
    with pytest.raises(ParsingError) as parsing:
        parse_config(ExperimentConfig, ["--lever.trust.target_kl=0"], "pipeline.")
    assert str(parsing.value.__cause__) == "--lever.trust.target_kl must be > 0, got 0.0"
    with pytest.raises(InvalidInputError, match="--levers=\\['refresh'\\] cannot run with --world_model_runs"):
        ExperimentConfig(levers=["kl", "refresh"], world_model_runs="elsewhere")
    assert ExperimentConfig(lever=LeverSettings()).lever.kl.coef == 0.1


def test_the_trust_lever_stops_each_update_at_its_target_kl(context):
    cfg = parse_config(ExperimentConfig, ["--levers=[trust]", "--lever.trust.target_kl=0.05"], "pipeline.")
    (run,) = lever_runs(cfg.levers, context, cfg.lever).values()
    assert run.env == context.world_model and run.settings == {"target_kl": 0.05} and run.runner is ppo
    method = LEVERS["trust"].method
    assert method.tag == "ppo_world_model_trust" and method.ood_only
    assert lever_descriptions([method], cfg.lever)[method].endswith("KL from the rollout's policy > 0.05")


def test_the_range_lever_halts_the_world_models_episodes_off_the_datas_states(context):
    cfg = parse_config(ExperimentConfig, ["--levers=[range]", "--lever.range.margin=0.25"], "pipeline.")
    (run,) = lever_runs(cfg.levers, context, cfg.lever).values()
    assert run.env == dataclasses.replace(context.world_model, state_margin=0.25)
    assert run.settings == {} and run.runner is ppo
    method = LEVERS["range"].method
    assert method.tag == "ppo_world_model_range" and method.ood_only
    assert lever_descriptions([method], cfg.lever)[method].endswith("widened by 25% of its span")
    with pytest.raises(ParsingError) as parsing:
        parse_config(ExperimentConfig, ["--lever.range.margin=-0.1"], "pipeline.")
    assert str(parsing.value.__cause__) == "--lever.range.margin must be >= 0, got -0.1"


def test_the_ensemble_takes_members_trained_elsewhere(context):
    context = dataclasses.replace(context, members=None)  # not a pack's run: members come from the settings
    cfg = parse_config(
        ExperimentConfig, ["--levers=[ensemble]", "--lever.ensemble.trained=[gpu/seed1,gpu/seed2]"], "pipeline."
    )
    assert cfg.lever.ensemble.members == 2
    ensemble = lever_runs(cfg.levers, context, cfg.lever)[LEVERS["ensemble"].method]
    assert ensemble.env.ensemble == ["gpu/seed1", "gpu/seed2"] and ensemble.env.disagreement_penalty == 1.0
    described = lever_descriptions({LEVERS["ensemble"].method: ensemble}, cfg.lever)[LEVERS["ensemble"].method]
    assert described == (
        "the run's action model and 2 more trained elsewhere (gpu/seed1, gpu/seed2); reward - 1.0 x their disagreement"
    )
    with pytest.raises(InvalidInputError, match="--lever.ensemble.trained is empty"):
        EnsembleSettings(trained=[])


def test_rl_runs_only_the_methods_asked_for(context, tmp_path):
    ran = []

    def runner(ppo_cfg, fresh):
        ran.append(ppo_cfg.output_dir)
        return Path(ppo_cfg.output_dir) / "final"

    kl = LEVERS["kl"].method
    levers = {kl: RLRun(context.world_model, {"kl_coef": 0.3}, runner)}
    sft = {"mlp": tmp_path / "sft"}
    rl = policy_stages.rl(context.pipeline, tmp_path, context.demonstrations, None, sft, levers, only=[kl])
    assert list(rl["mlp"]) == [kl] and [Path(r).name for r in ran] == ["ppo_world_model_kl"]


def test_the_plain_run_and_each_lever_repeat_at_another_ppo_seed(context, tmp_path):
    """`kl_seed1` is the KL lever's run with PPO's seed 1, in its own folder and row; `plain_seed1` the plain run's."""
    settings = LeverSettings(kl=dataclasses.replace(LeverSettings().kl, coef=0.3))
    runs = lever_runs(["kl", "kl_seed1", "plain_seed1"], context, settings)
    kl, kl_again, plain_again = (LEVERS[name].method for name in ("kl", "kl_seed1", "plain_seed1"))
    assert runs[kl].settings == {"kl_coef": 0.3} and runs[kl_again].settings == {"kl_coef": 0.3, "seed": 1}
    assert runs[plain_again].env == context.world_model and runs[plain_again].settings == {"seed": 1}
    assert str(kl_again) == "RL w. World Model, KL to SFT, seed 1" and kl_again.ood_only
    assert lever_descriptions([kl_again], settings)[kl_again] == "KL to the SFT policy x 0.3; PPO's seed 1"
    built = {}

    def runner(ppo_cfg, fresh):
        built[Path(ppo_cfg.output_dir).name] = ppo_cfg.seed
        return Path(ppo_cfg.output_dir) / "final"

    levers = {method: dataclasses.replace(run, runner=runner) for method, run in runs.items()}
    policy_stages.rl(
        context.pipeline, tmp_path, context.demonstrations, None, {"mlp": tmp_path / "sft"}, levers, only=list(levers)
    )
    assert built == {"ppo_world_model_kl": 0, "ppo_world_model_kl_seed1": 1, "ppo_world_model_seed1": 1}
