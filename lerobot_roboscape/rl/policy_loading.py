"""Load a LeRobot policy checkpoint (local or Hub) with its processors, as an actor-critic for an env."""

from pathlib import Path

import numpy as np
from huggingface_hub import hf_hub_download
from huggingface_hub.constants import SAFETENSORS_SINGLE_FILE
from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import FeatureType
from lerobot.envs.configs import EnvConfig
from lerobot.envs.utils import preprocess_observation
from lerobot.policies.factory import get_policy_class, make_pre_post_processors
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.import_utils import register_third_party_plugins
from torch import Tensor

from lerobot_roboscape.io.weights import check_tensors
from roboscape_core.actor_critic import ActorCritic
from roboscape_core.errors import InvalidInputError, MissingInputError


def load_policy(path: str | Path, device: str):
    """(policy, preprocessor, postprocessor) of the checkpoint at `path`, on `device`."""
    register_third_party_plugins()  # the lerobot_policy_* distributions register their policy types
    try:
        config = PreTrainedConfig.from_pretrained(str(path))
    except Exception as error:
        raise MissingInputError(
            f"No LeRobot policy checkpoint at {path!r} ({type(error).__name__}: {error}). Pass the "
            f"pretrained_model directory of a lerobot-train or roboscape-ppo run, or a Hub repo id."
        ) from error
    config.device = device
    policy = get_policy_class(config.type).from_pretrained(str(path), config=config)
    if type(policy)._load_as_safetensor.__func__ is PreTrainedPolicy._load_as_safetensor.__func__:
        # LeRobot's loader is not strict: a policy missing tensors would run with their random initial values.
        local = Path(path) / SAFETENSORS_SINGLE_FILE
        check_tensors(policy, local if local.is_file() else hf_hub_download(str(path), SAFETENSORS_SINGLE_FILE))
    overrides = {"device_processor": {"device": device}}
    preprocessor, postprocessor = make_pre_post_processors(
        config, pretrained_path=str(path), preprocessor_overrides=overrides
    )
    return policy, preprocessor, postprocessor


def check_actor_critic(policy, path) -> None:
    if not isinstance(policy, ActorCritic):
        raise InvalidInputError(
            f"The {policy.name!r} policy at {path} cannot be trained by PPO: it lacks sample_action, "
            "evaluate_actions or predict_value (roboscape_core.actor_critic.ActorCritic). Use roboscape_mlp or "
            "openvla."
        )


def check_policy_fits_env(policy, env_cfg: EnvConfig, path) -> None:
    """Every camera the policy reads must come out of the env, at the same image shape."""
    env_images = {
        env_cfg.features_map[key]: tuple(feature.shape)
        for key, feature in env_cfg.features.items()
        if feature.type is FeatureType.VISUAL
    }
    for key, feature in policy.config.input_features.items():
        if feature.type is not FeatureType.VISUAL:
            raise InvalidInputError(
                f"The policy at {path} reads {key!r}, which the {env_cfg.type} env does not provide"
            )
        channels_first = tuple(feature.shape)
        if key not in env_images:
            raise InvalidInputError(
                f"The policy at {path} reads camera {key!r}; the {env_cfg.type} env gives {sorted(env_images)}"
            )
        height, width, channels = env_images[key]
        if channels_first != (channels, height, width):
            raise InvalidInputError(
                f"The policy at {path} expects {key} images of shape {channels_first} (C, H, W); the "
                f"{env_cfg.type} env renders {(channels, height, width)}: set --env.image_size={channels_first[-1]}"
            )


def check_policy_fits_frame_skip(policy, env, path) -> None:
    """A policy that executes action chunks must execute one world-model frame's worth (k actions) per look, so that
    each decision sees the frame its previous chunk made; a policy that acts every step (1 action) always fits."""
    k = getattr(env, "frame_skip", None)  # only the world-model env steps in frames
    if k is None:
        return
    executed = getattr(policy.config, "n_action_steps", 1)
    if executed > 1 and executed != k:
        raise InvalidInputError(
            f"The policy at {path} executes {executed} actions per look but the world model makes a frame every "
            f"{k} actions (frame_skip, saved with the model): train the policy with n_action_steps={k}, or the "
            f"world models with --wm.frame_skip={executed}"
        )


class PolicyIO:
    """Env observations -> the policy's batch (LeRobot's conversion, then the policy's preprocessor), and the
    policy's normalised actions -> env actions (its postprocessor)."""

    def __init__(self, preprocessor, postprocessor):
        self.preprocessor, self.postprocessor = preprocessor, postprocessor

    def batch(self, pixels: dict[str, np.ndarray] | np.ndarray, tasks: list[str]) -> dict:
        observation = preprocess_observation({"pixels": pixels})
        observation["task"] = list(tasks)
        return self.preprocessor(observation)

    def env_action(self, action: Tensor) -> np.ndarray:
        return self.postprocessor(action).to("cpu").numpy()
