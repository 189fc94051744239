"""The pipeline's config: the stages' settings under their stages' own names, and scales that are files of them."""

from dataclasses import fields, replace

import pytest
from lerobot.configs.default import EvalConfig as LeRobotEval
from lerobot.configs.train import TrainPipelineConfig

from lerobot_roboscape.demos.collect import CollectConfig
from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.evaluation.success_rate import EvalConfig
from lerobot_roboscape.pipeline import config
from lerobot_roboscape.rl.configuration_ppo import PPOConfig
from roboscape_core.errors import InvalidInputError


def names(config_class) -> set[str]:
    return {f.name for f in fields(config_class)}


def test_every_setting_carries_its_stage_s_own_name():
    """A field the pipeline hands to a stage is named as that stage names it (no `wm_steps` for `train.steps`)."""
    # no stage has these
    pipeline_own = {"explore_episodes_per_scene", "initial_scene_episodes", "heldout_scenes", "report_episodes"}
    pipeline_own |= {"ind_control_starts"}
    assert names(config.DataConfig) - pipeline_own <= names(CollectConfig)
    assert names(config.PPOSettings) <= names(PPOConfig)
    assert names(config.EnvSettings) <= names(RoboscapeWorldModelEnvConfig)
    assert names(config.EvalSettings) <= names(EvalConfig)
    assert {"steps", "batch_size", "num_workers"} <= names(TrainPipelineConfig)
    assert {"n_episodes"} <= names(LeRobotEval) and "episode_length" in names(RoboscapeWorldModelEnvConfig)
    assert not hasattr(config, "SCALES") and not hasattr(config, "BENCH_ON_GPU")


@pytest.mark.parametrize("scale", config.scales())
def test_every_scale_file_is_a_typed_config_whose_flags_win(scale):
    cfg = config.scale_config(scale, ("--wm_train.steps=7", "--data.max_scenes=3"))
    assert cfg.scale == scale and cfg.wm_train.steps == 7 and cfg.data.max_scenes == 3
    assert config.settings_flags(cfg)[-2:] == ["--data.max_scenes=3", "--wm_train.steps=7"] or scale == "paper"


def test_a_gpu_is_a_scale_the_user_names():
    bench, gpu = config.scale_config("bench"), config.scale_config("bench_gpu")
    assert bench.device == "auto" and gpu.device == "cuda"  # never merged in because a GPU happens to be there
    assert (gpu.wm_train.steps, gpu.ppo.time_budget_s) == (6000, 900) and (
        bench.wm_train.steps,
        bench.ppo.time_budget_s,
    ) == (7500, 480)
    assert gpu.data == bench.data and gpu.eval == bench.eval and type(gpu.wm) is type(bench.wm)
    assert (bench.wm.patch, gpu.wm.patch) == (2, 1)  # 2x2 codes a position on the CPU, as its curves chose


def test_a_negative_count_of_ind_controllability_starts_is_refused():
    bench = config.scale_config("bench")
    with pytest.raises(InvalidInputError, match="--data.ind_control_starts must be >= 0, got -1"):
        replace(bench, data=replace(bench.data, ind_control_starts=-1))
    assert config.scale_config("bench", ("--data.ind_control_starts=0",)).data.ind_control_starts == 0
