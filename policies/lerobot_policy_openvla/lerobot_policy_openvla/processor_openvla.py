from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from lerobot_policy_openvla.configuration_openvla import OpenVLAConfig


def make_openvla_pre_post_processors(
    config: OpenVLAConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """LeRobot's default pipelines. Actions are normalised to [-1, 1] with the dataset's q01/q99 and
    un-normalised back (OpenVLA's formula: a = (x + 1) / 2 * (q99 - q01) + q01). The prompt and the image
    preprocessing belong to the model, which owns the tokenizer of its base checkpoint."""
    return make_default_pre_post_processors(config, dataset_stats)
