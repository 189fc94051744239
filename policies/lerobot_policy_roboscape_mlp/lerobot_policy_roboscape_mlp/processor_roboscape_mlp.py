from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from lerobot_policy_roboscape_mlp.configuration_roboscape_mlp import RoboscapeMLPConfig


def make_roboscape_mlp_pre_post_processors(
    config: RoboscapeMLPConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """LeRobot's default pipelines: batch, device and min-max action (un)normalisation from the dataset's
    statistics. The instruction passes through untouched; the model hashes its words itself."""
    return make_default_pre_post_processors(config, dataset_stats)
