"""A tiny OpenVLA of the 7B's layout and a batch for it: what the OpenVLA tests build on."""

from pathlib import Path

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot_policy_openvla import OpenVLAConfig, OpenVLAPolicy

from tests.conftest import IMAGE_SIZE

CAMERA = "observation.images.third_view"


FIXTURES = Path(__file__).parents[1] / "fixtures"


TASKS = ["push the can forward", "pick up the red apple and place it in the bowl", "pull the mug back"]


def make_policy(**overrides) -> OpenVLAPolicy:
    features = {
        CAMERA: PolicyFeature(FeatureType.VISUAL, (3, IMAGE_SIZE, IMAGE_SIZE)),
        "observation.images.wrist": PolicyFeature(FeatureType.VISUAL, (3, IMAGE_SIZE, IMAGE_SIZE)),
        "observation.state": PolicyFeature(FeatureType.STATE, (16,)),
    }
    kwargs = dict(
        device="cpu",
        base_model="tiny",
        input_features=features,
        gradient_checkpointing=False,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (7,))},
    )
    torch.manual_seed(0)
    return OpenVLAPolicy(OpenVLAConfig(**{**kwargs, **overrides}))


def make_batch(tasks=TASKS):
    generator = torch.Generator().manual_seed(1)
    return {
        CAMERA: torch.rand(len(tasks), 3, IMAGE_SIZE, IMAGE_SIZE, generator=generator),
        "task": list(tasks),
        "action": torch.rand(len(tasks), 7, generator=generator) * 2 - 1,
    }
