"""LeRobot env types of RoboScape-R. Importing this module registers them with `EnvConfig`."""

import os
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_IMAGE, OBS_IMAGES, OBS_STATE

from lerobot_roboscape.dataset.reader import read_layout
from lerobot_roboscape.robot import ACTION_NAMES, CAMERA_NAMES, CONTROL_FREQ, STATE_DIM
from lerobot_roboscape.training.loop import native_bf16, resolve_device
from roboscape_core.errors import InvalidInputError

CAMERAS = tuple(CAMERA_NAMES.values())
DONE_SOURCES = ("world_model", "classifier")
PRECISIONS = ("auto", "float32", "bfloat16")  # of the world-model env's forward passes


def check_episode_length(episode_length: int | None) -> None:
    if episode_length is not None and episode_length < 1:
        raise InvalidInputError(f"episode_length must be >= 1 or null (per-family horizons), got {episode_length}")


PIXELS = "pixels"  # LeRobot's observation key of an env's images


def camera_features(
    image_size: int, cameras=CAMERAS, keys: dict[str, str] | None = None, action_dim: int = len(ACTION_NAMES)
) -> tuple[dict, dict]:
    """LeRobot's env features: each camera's `pixels/<camera>`, mapped to its dataset key (`keys`: a dataset's own,
    as `read_layout` gives them; by default `observation.images.<camera>`), or one `pixels` for a lone camera under
    `observation.image`; and the action."""
    features = {ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(action_dim,))}
    features_map = {ACTION: ACTION}
    if keys is not None and list(keys.values()) == [OBS_IMAGE]:
        # LeRobot's one-camera layout (PushT): its envs give `pixels` as one array, which LeRobot reads as
        # observation.image (a dict of views it reads as observation.images.<camera>).
        features[PIXELS] = PolicyFeature(type=FeatureType.VISUAL, shape=(image_size, image_size, 3))
        return features, features_map | {PIXELS: OBS_IMAGE}
    for cam in cameras:
        features[f"pixels/{cam}"] = PolicyFeature(type=FeatureType.VISUAL, shape=(image_size, image_size, 3))
        features_map[f"pixels/{cam}"] = (keys or {}).get(cam, f"{OBS_IMAGES}.{cam}")
    return features, features_map


@EnvConfig.register_subclass("roboscape_wm")
@dataclass
class RoboscapeWorldModelEnvConfig(EnvConfig):
    """The world models as an environment (see envs/world_model_env.py).

    Args:
        world_models: a world-models repo (Hub repo id or local folder, made by `roboscape-push
            --artifact=world_models`) holding the tokenizer and both world models; it replaces the next three and
            names the dataset they were trained on.
        dataset_repo_id: LeRobot dataset whose episodes give the initial frames and instructions (default: the one
            named by world_models).
        dataset_root: its local directory (default: the LeRobot cache / Hub).
        starts_file: the starts saved from that dataset (envs/starts.py: export_starts, with this config's families,
            split, scenes, starts_per_scene, branches_per_episode and episode_length), read instead of it: the env
            then runs where the dataset is not (a GPU machine without its videos). Null: read the dataset.
        tokenizer: trained tokenizer, local directory or Hub repo id.
        action_world_model: action world model, local directory or Hub repo id.
        text_world_model: text world model that generates the goal frames (goal_source=text_model).
        families: task families whose episodes are used (empty: all).
        split: "ind", "ood" or "" (all).
        scenes: scene ids to use (empty: all).
        goal_source: "text_model" (the paper) or "dataset_last_frame" (the episode's own last frame).
        reward_type: "world_model" (the paper's reward), or a baseline: "embedding" (a head on the action model's
            hidden state, as iVideoGPT) or "proxy" (an image-to-reward network, as DiWA), fitted to the rule-based
            reward by roboscape-train-reward.
        reward_model: the baseline reward model (local directory or Hub repo id).
        done_source: what says the task is done: "world_model" (the action and text models' done heads, the
            paper's) or "classifier" (a success classifier on the decoded frames, `success_classifier`).
        success_classifier: the success classifier (`roboscape-train-reward --reward.kind=success`), local
            directory or Hub repo id.
        theta: done threshold of the goal and of success (choose it on validation episodes: roboscape-eval-done
            reports the threshold that separates their success from failure best).
        theta_sps: done threshold of the sparse reward.
        alpha: weight of the sparse reward.
        beta: weight of the dense (similarity) reward.
        sparse_reward: value of the sparse reward, paid at every step while done >= theta_sps.
        similarity: the dense reward's distance to the goal: "lpips" (the paper's), "tokenizer" (features of the
            project's own tokenizer encoder, needs no download), "pixel" (mean squared pixel difference, a
            baseline) or "auto" (lpips when its trunk weights are present, else tokenizer).
        episode_length: the fixed horizon of every episode; null: per task family, the longest successful
            episode of that family in the dataset.
        terminate_on_success: end an episode when done >= theta, paying the rest of its horizon at the most a step
            can earn (the default runs the fixed horizon, as Algorithm 1).
        clip_actions: clip actions to the per-dimension range seen in the dataset (`env.action_range`).
        ensemble: more action world models (local directories or Hub repo ids), trained as `action_world_model`
            was but apart (another seed): with them, each frame's disagreement of all the action models (their
            mutual information per token, in nats: envs/ensemble.py) is reported, and penalised or halts the
            episode as the next two say. Each member costs about two passes of its model per frame.
        disagreement_penalty: MOPO's lambda: each frame's reward minus this x its disagreement (0: none).
        disagreement_threshold: MOReL's halt: an episode ends (terminated, nothing paid after it) at the first frame
            whose disagreement passes this, where the world models no longer know what follows (null: never).
        state_margin: an episode halts (terminated, that frame unpaid and no success) at the first frame whose
            predicted robot state leaves the range of the action model's training states, widened by this share of
            its span on each side: past it the model has seen nothing of what follows (null: never).
        max_goal_steps: control steps the text model may generate while looking for the goal (a frame per frame_skip).
        goal_file: a file of generated goals (safetensors): the env reads it when made, generates every start's
            missing goal then (once, before any episode) and writes them back. A file made with other models or
            settings is an error. Null: each goal is generated when its start first comes up.
        starts_per_scene: the episodes whose first frames are the starts, per task family and scene (the first
            ones in the dataset; null: all).
        branches_per_episode: starts per dataset episode: its first frame and, evenly along its recorded frames, the
            real frames after it (MBPO's branched rollouts: with a short `episode_length`, every episode begins in
            a real state and ends before the world model drifts far from the data). Each start of an episode
            shares the episode's goal. 1: the first frame only.
        temperature: sampling temperature of the world model (0: greedy, deterministic).
        image_size: camera image side (must match the tokenizer).
        lpips_weights: torchvision trunk weights for LPIPS (default: the torch hub cache).
        allow_random_lpips: with similarity=lpips, run with a random trunk when no weights are found (tests only:
            not a perceptual metric).
        device: "auto", "cpu" or "cuda".
        precision: "bfloat16" runs the world models, the tokenizer and the reward's distance under bf16 autocast,
            "float32" without it; "auto": bfloat16 where the device computes it natively (a CUDA GPU that supports
            it, a CPU with AVX512-BF16 or AMX), else float32. On 2 CPU cores with AVX512-BF16, bf16 makes about
            1.35x the env steps/s at batch 16, and a trained model's rollouts keep 99.9% of their float32 tokens
            (docs/results/world_model/control_levers.md).
        cuda_graphs: on a CUDA device, replay each frame's generation as a CUDA graph (one launch a frame instead
            of hundreds: world_model/rollout.py); off, or on a CPU, every kernel is launched as it comes.
        include_state: also return the robot's state the action model carries (`agent_pos` -> observation.state,
            as roboscape_maniskill's): real at a start, the model's prediction after. The MLP and OpenVLA read
            images only by default (the paper's).
        seed: seed of the start sampling when reset() gets none.
    """

    task: str | None = None
    fps: int = CONTROL_FREQ
    world_models: str | None = None
    dataset_repo_id: str | None = None
    dataset_root: str | None = None
    starts_file: str | None = None
    tokenizer: str = "outputs/tokenizer/pretrained_model"
    action_world_model: str = "outputs/world_model_action/pretrained_model"
    text_world_model: str | None = "outputs/world_model_text/pretrained_model"
    families: list[str] = field(default_factory=list)
    split: str = ""
    scenes: list[str] = field(default_factory=list)
    goal_source: str = "text_model"
    reward_type: str = "world_model"
    reward_model: str | None = None
    done_source: str = "world_model"
    success_classifier: str | None = None
    theta: float = 0.9
    theta_sps: float = 0.9
    alpha: float = 0.5
    beta: float = 0.5
    sparse_reward: float = 10.0
    similarity: str = "auto"
    episode_length: int | None = None
    terminate_on_success: bool = False
    clip_actions: bool = False
    ensemble: list[str] = field(default_factory=list)
    disagreement_penalty: float = 0.0
    disagreement_threshold: float | None = None
    state_margin: float | None = None
    max_goal_steps: int = 100
    goal_file: str | None = None
    starts_per_scene: int | None = None
    branches_per_episode: int = 1
    temperature: float = 0.0
    image_size: int = 64
    lpips_weights: str | None = None
    allow_random_lpips: bool = False
    device: str = "auto"
    precision: str = "auto"
    cuda_graphs: bool = True
    include_state: bool = False
    seed: int = 0
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(default_factory=dict)

    def __post_init__(self):
        from lerobot_roboscape.envs.goal_bank import GOAL_SOURCES
        from lerobot_roboscape.tokenizer.similarity import SIMILARITIES

        if self.similarity not in SIMILARITIES:
            raise InvalidInputError(f"similarity must be one of {SIMILARITIES}, got {self.similarity!r}")
        if self.precision not in PRECISIONS:
            raise InvalidInputError(f"precision must be one of {PRECISIONS}, got {self.precision!r}")
        check_episode_length(self.episode_length)
        if self.goal_source not in GOAL_SOURCES:
            raise InvalidInputError(f"goal_source must be one of {GOAL_SOURCES}, got {self.goal_source!r}")
        if self.reward_type not in ("world_model", "embedding", "proxy"):
            raise InvalidInputError(f"reward_type must be world_model, embedding or proxy, got {self.reward_type!r}")
        if self.reward_type != "world_model" and not self.reward_model:
            raise InvalidInputError(
                f"reward_type={self.reward_type} needs reward_model (train one with roboscape-train-reward)"
            )
        if self.done_source not in DONE_SOURCES:
            raise InvalidInputError(f"done_source must be one of {DONE_SOURCES}, got {self.done_source!r}")
        if self.done_source == "classifier" and not self.success_classifier:
            raise InvalidInputError(
                "done_source=classifier needs success_classifier (train one with roboscape-train-reward "
                "--reward.kind=success)"
            )
        if self.goal_source == "text_model" and not self.text_world_model:
            raise InvalidInputError("goal_source=text_model needs text_world_model")
        if self.branches_per_episode < 1:
            raise InvalidInputError(f"branches_per_episode must be >= 1, got {self.branches_per_episode}")
        threshold = self.disagreement_threshold
        if self.disagreement_penalty < 0 or (threshold is not None and threshold <= 0):
            raise InvalidInputError(
                f"disagreement_penalty must be >= 0 and disagreement_threshold > 0 (or null), got "
                f"{self.disagreement_penalty}, {self.disagreement_threshold}"
            )
        if (self.disagreement_penalty or self.disagreement_threshold is not None) and not self.ensemble:
            raise InvalidInputError(
                "disagreement_penalty and disagreement_threshold need ensemble: more action world models "
                "(roboscape-train-wm --wm.control=action with other --train.seed values, or --init_from the env's "
                "model with --retrain_blocks)"
            )
        if self.state_margin is not None and self.state_margin < 0:
            raise InvalidInputError(f"state_margin must be >= 0 (or null), got {self.state_margin}")
        if not 0 < self.theta <= 1 or not 0 < self.theta_sps <= 1:
            raise InvalidInputError(f"theta and theta_sps must be in (0, 1], got {self.theta}, {self.theta_sps}")
        state_dim = STATE_DIM
        if self.dataset_root and (Path(self.dataset_root) / "meta" / "info.json").is_file():
            # A user's dataset: its cameras, their keys, its image size and its action and state widths.
            layout = read_layout(self.dataset_root)
            self.image_size, state_dim = layout.image_size, layout.state_dim
            self.features, self.features_map = camera_features(
                layout.image_size, tuple(layout.cameras), layout.cameras, layout.action_dim
            )
        else:
            self.features, self.features_map = camera_features(self.image_size)
        if self.include_state:
            self.features["agent_pos"] = PolicyFeature(type=FeatureType.STATE, shape=(state_dim,))
            self.features_map["agent_pos"] = OBS_STATE

    @property
    def resolved_device(self) -> str:
        return resolve_device(self.device)

    @property
    def resolved_precision(self) -> str:
        if self.precision != "auto":
            return self.precision
        return "bfloat16" if native_bf16(self.resolved_device) else "float32"

    @property
    def gym_kwargs(self) -> dict:
        return {}

    def create_envs(self, n_envs: int, use_async_envs: bool = False) -> dict[str, dict[int, gym.vector.VectorEnv]]:
        """One batched env of `n_envs` episodes (async workers would each hold a copy of the models)."""
        from lerobot_roboscape.envs.world_model_env import RoboscapeWorldModelEnv

        return {self.type: {0: RoboscapeWorldModelEnv(self, num_envs=n_envs)}}


@EnvConfig.register_subclass("roboscape_maniskill")
@dataclass
class RoboscapeManiSkillEnvConfig(EnvConfig):
    """The task suite in the ManiSkill simulator (see envs/maniskill_env.py), for evaluation and the "RL in
    ManiSkill" baseline. Observations, actions, task strings and the reward's shape are laid out as in
    `roboscape_wm`: reward = alpha * sparse_reward * success + beta * the task's normalised dense reward (in [0, 1]).

    Args:
        families: task families, dealt to the parallel envs in turn (empty: all four).
        split: "ind", "ood" or "" (all scenes).
        scenes: scene ids (empty: every scene of the split).
        alpha: weight of the success term.
        beta: weight of the normalised dense reward.
        sparse_reward: value of the success term, paid at every step while the task is accomplished.
        episode_length: the fixed horizon of every episode; null: per task family, the longest successful episode
            of that family in `dataset_root` when given, else the task's registered time limit.
        terminate_on_success: end an episode at its first success, paying the rest of its horizon at the most a
            step can earn (evaluation uses it to save simulation; PPO runs the fixed horizon by default).
        dataset_repo_id: demonstrations whose episode lengths set the per-family horizons.
        dataset_root: their local directory.
        image_size: camera image side.
        cameras: camera names (the dataset's).
        include_state: also return the robot's proprioception (`agent_pos` -> observation.state: joint positions and
            TCP pose, as in the collected datasets), for policies trained with it. roboscape_wm has no such
            observation, so policies meant for both envs read images only.
        workers: processes the parallel envs are spread over (the simulator renders on one core per process);
            null: one per CPU core, at most one per env; 1: all in this process. The episodes are the same for
            any number.
        light_wrist_camera: render the wrist camera's body with a light mesh (3.5x faster without a GPU; the
            frames differ only on its outline); false renders ManiSkill's own mesh.
        seed: seed of the scene and initial-state sampling when reset() gets none.
    """

    task: str | None = None
    fps: int = CONTROL_FREQ
    families: list[str] = field(default_factory=list)
    split: str = "ind"
    scenes: list[str] = field(default_factory=list)
    alpha: float = 0.5
    beta: float = 0.5
    sparse_reward: float = 10.0
    episode_length: int | None = None
    terminate_on_success: bool = False
    dataset_repo_id: str | None = None
    dataset_root: str | None = None
    image_size: int = 64
    cameras: tuple[str, ...] = CAMERAS
    include_state: bool = False
    workers: int | None = None
    light_wrist_camera: bool = True
    seed: int = 0
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(default_factory=dict)

    def __post_init__(self):
        if self.workers is not None and self.workers < 1:
            raise InvalidInputError(f"workers must be >= 1 or null (one per CPU core), got {self.workers}")
        if self.split not in ("", "ind", "ood"):
            raise InvalidInputError(f"split must be 'ind', 'ood' or '', got {self.split!r}")
        check_episode_length(self.episode_length)
        self.cameras = tuple(self.cameras)
        self.features, self.features_map = camera_features(self.image_size, self.cameras)
        if self.include_state:
            self.features["agent_pos"] = PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,))
            self.features_map["agent_pos"] = OBS_STATE

    @property
    def gym_kwargs(self) -> dict:
        return {}

    def resolved_workers(self, num_envs: int) -> int:
        return min(num_envs, self.workers or os.cpu_count() or 1)

    def create_envs(self, n_envs: int, use_async_envs: bool = False) -> dict[str, dict[int, gym.vector.VectorEnv]]:
        """One batched env of `n_envs` episodes, spread over `workers` processes (whatever `use_async_envs`)."""
        from lerobot_roboscape.envs.maniskill_env import RoboscapeManiSkillEnv

        return {self.type: {0: RoboscapeManiSkillEnv(self, num_envs=n_envs)}}
