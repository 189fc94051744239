"""OpenVLA's action (un)normalisation as LeRobot processor steps.

OpenVLA scales each action dimension from [q01, q99] to [-1, 1] before binning, except the dimensions its
statistics mask out (the gripper, `mask[6] = False` in every dataset of the published checkpoint), which pass
through unchanged. `predict_action` inverts it in float64 numpy:

    actions = np.where(mask, 0.5 * (x + 1) * (q99 - q01) + q01, x)

The statistics come from the LeRobot dataset for a fine-tuned policy (q01/q99 of `action`, the gripper masked
as OpenVLA's fine-tuning masks it), or from the base checkpoint's `norm_stats` with `--policy.unnorm_key` to
run the published model zero-shot. They are saved in the pipelines' JSON, so a checkpoint keeps its own.
"""

from abc import abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from lerobot.configs import NormalizationMode, PipelineFeatureType, PolicyFeature
from lerobot.lerobot_types import EnvTransition, TransitionKey
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, ProcessorStep, ProcessorStepRegistry
from lerobot.processor.factory import make_default_policy_processor_steps, make_policy_processor_pipelines
from lerobot.utils.constants import ACTION
from torch import Tensor

from lerobot_policy_openvla.checkpoint import read_config, select_action_stats
from lerobot_policy_openvla.configuration_openvla import OpenVLAConfig
from roboscape_core.errors import InvalidInputError

GRIPPER = 6  # index of the gripper in OpenVLA's 7-D end-effector action
NORMALIZE_EPS = 1e-8  # OpenVLA's in normalize_action_and_proprio


def make_openvla_pre_post_processors(
    config: OpenVLAConfig,
    dataset_stats: dict[str, dict[str, Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """LeRobot's default pipelines (whose normaliser leaves the action alone: `normalization_mapping` has it as
    IDENTITY) plus OpenVLA's masked action (un)normalisation. The prompt and the image preprocessing belong to
    the model, which owns the tokenizer of its base checkpoint."""
    if config.normalization_mapping.get("ACTION") is not NormalizationMode.IDENTITY:
        raise ValueError(
            f"openvla normalises actions itself (masked, as OpenVLA): normalization_mapping['ACTION'] must be "
            f"IDENTITY, got {config.normalization_mapping.get('ACTION')!r}"
        )
    stats = openvla_action_stats(config, dataset_stats)
    s = make_default_policy_processor_steps(config, dataset_stats)
    return make_policy_processor_pipelines(
        input_steps=[s.rename_observations, s.add_batch_dim, s.to_device, s.normalize, OpenVLANormalizeAction(**stats)],
        output_steps=[OpenVLAUnnormalizeAction(**stats), s.unnormalize, s.to_cpu],
    )


def openvla_action_stats(config: OpenVLAConfig, dataset_stats: dict | None) -> dict[str, list | None]:
    """{"q01", "q99", "mask"} for the action steps: the base checkpoint's `norm_stats[unnorm_key]` when
    `unnorm_key` is set, else the dataset's quantiles with the gripper masked, else the base checkpoint's only
    dataset (several need `unnorm_key`); all None (actions left as they are) for a base without statistics."""
    if config.unnorm_key is None and dataset_stats and ACTION in dataset_stats:
        action = dataset_stats[ACTION]
        if "q01" not in action or "q99" not in action:
            raise InvalidInputError(
                f"openvla normalises actions with their 1% and 99% quantiles, but the dataset's action stats have "
                f"only {sorted(action)}: recompute them with LeRobot's augment_dataset_quantile_stats.py"
            )
        q01, q99 = (np.asarray(action[q], dtype=np.float64).reshape(-1).tolist() for q in ("q01", "q99"))
        return {"q01": q01, "q99": q99, "mask": [i != GRIPPER for i in range(len(q01))]}
    norm_stats = read_config(config.base_model, config.base_revision).get("norm_stats") or {}
    if not norm_stats and config.unnorm_key is None:
        return {"q01": None, "q99": None, "mask": None}
    source = f"the base checkpoint {config.base_model!r}"
    action = select_action_stats(norm_stats, config.unnorm_key, source)
    mask = action.get("mask", [True] * len(action["q01"]))  # OpenVLA's default: every dimension
    return {"q01": list(action["q01"]), "q99": list(action["q99"]), "mask": [bool(m) for m in mask]}


def unnormalize_action(x: Tensor, q01: Tensor, q99: Tensor, mask: Tensor) -> Tensor:
    """[-1, 1] -> [q01, q99] where `mask`, as `predict_action` (same float64 operations, same order)."""
    return torch.where(mask, 0.5 * (x + 1) * (q99 - q01) + q01, x)


def normalize_action(a: Tensor, q01: Tensor, q99: Tensor, mask: Tensor) -> Tensor:
    """[q01, q99] -> [-1, 1] (clipped) where `mask`, as OpenVLA's data pipeline (BOUNDS_Q99)."""
    return torch.where(mask, (2 * (a - q01) / (q99 - q01 + NORMALIZE_EPS) - 1).clamp(-1, 1), a)


@dataclass
class OpenVLAActionStats(ProcessorStep):
    """The statistics of one dataset's actions (lists of floats, kept in float64) and the transform they
    define; None everywhere: actions pass through."""

    q01: list[float] | None = None
    q99: list[float] | None = None
    mask: list[bool] | None = None

    def __post_init__(self):
        given = [value is not None for value in (self.q01, self.q99, self.mask)]
        if any(given) and not all(given):
            raise ValueError(f"q01, q99 and mask come together, got {self.q01=}, {self.q99=}, {self.mask=}")
        if all(given) and not len(self.q01) == len(self.q99) == len(self.mask):
            raise ValueError(f"q01, q99 and mask differ in length: {self.q01}, {self.q99}, {self.mask}")

    def __call__(self, transition: EnvTransition) -> EnvTransition:
        action = transition.get(TransitionKey.ACTION)
        if action is None or self.q01 is None:
            return transition
        if not isinstance(action, Tensor):
            raise ValueError(f"openvla's actions are tensors, got {type(action)}")
        if action.shape[-1] != len(self.q01):
            raise ValueError(f"actions of shape {tuple(action.shape)} for statistics of {len(self.q01)} dimensions")
        stats = [torch.tensor(v, dtype=torch.float64, device=action.device) for v in (self.q01, self.q99)]
        mask = torch.tensor(self.mask, dtype=torch.bool, device=action.device)
        return {**transition, TransitionKey.ACTION: self.transform(action, *stats, mask)}

    @abstractmethod
    def transform(self, action: Tensor, q01: Tensor, q99: Tensor, mask: Tensor) -> Tensor:
        """The normalisation (or its inverse) that the subclass applies with these statistics."""

    def get_config(self) -> dict[str, Any]:
        return {"q01": self.q01, "q99": self.q99, "mask": self.mask}

    def transform_features(
        self, features: dict[PipelineFeatureType, dict[str, PolicyFeature]]
    ) -> dict[PipelineFeatureType, dict[str, PolicyFeature]]:
        return features


@dataclass
@ProcessorStepRegistry.register(name="openvla_normalize_action")
class OpenVLANormalizeAction(OpenVLAActionStats):
    """Dataset actions -> OpenVLA's [-1, 1] (computed in float64, returned in the action's dtype)."""

    def transform(self, action: Tensor, q01: Tensor, q99: Tensor, mask: Tensor) -> Tensor:
        return normalize_action(action.double(), q01, q99, mask).to(action.dtype)


@dataclass
@ProcessorStepRegistry.register(name="openvla_unnormalize_action")
class OpenVLAUnnormalizeAction(OpenVLAActionStats):
    """The policy's [-1, 1] actions -> env actions. In float64, like `predict_action`: given the policy's
    float64 bin centres, the result is bit-identical to OpenVLA's."""

    def transform(self, action: Tensor, q01: Tensor, q99: Tensor, mask: Tensor) -> Tensor:
        return unnormalize_action(action.double(), q01, q99, mask)
