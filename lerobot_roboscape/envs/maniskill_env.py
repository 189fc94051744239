"""`roboscape_maniskill`: the task suite in the ManiSkill simulator, laid out like `roboscape_wm`.

Same camera names, image size, 7-D actions and task strings, so one policy runs in both. Each of the B slots holds
one ManiSkill env of a task family (families are dealt to slots in turn) and is reset into a scene drawn from the
selected split/scenes. The slots' ManiSkill envs live in worker processes (`config.workers`, see
envs/simulator_slots.py) and the policy's whole batch steps them at once. The reward has the world-model reward's
shape, with the simulator in place of the models: alpha * sparse_reward while the task is accomplished + beta * the
task's normalised dense reward (the rule-based reward of the paper's baselines). As in `roboscape_wm`, episodes run
a fixed horizon and `is_success` is success at any step (`EpisodeBook`); an ended episode stays frozen until the
next reset, which restarts all slots.
"""

import gymnasium as gym
import numpy as np

from lerobot_roboscape.dataset.reader import family_horizons, open_dataset
from lerobot_roboscape.envs.batched import BatchedEnv, EpisodeBook, start_groups
from lerobot_roboscape.envs.simulator_slots import Slots, SlotSpec, SlotWorkers, make_slots
from lerobot_roboscape.reward.world_model_reward import max_step_reward
from lerobot_roboscape.robot import STATE_DIM
from lerobot_roboscape.tasks import ENV_IDS, TASK_FAMILIES, select_scenes
from roboscape_core.errors import InvalidInputError

# The slots' own time limit, above every horizon: episodes are cut by the env's horizons (EpisodeBook).
SLOT_TIME_LIMIT = 100_000


def task_horizons(config, families: list[str]) -> dict[str, int]:
    """The fixed horizon of each family: `episode_length`, else the longest successful demonstration of the family
    in the given dataset, else the task's registered time limit."""
    if config.episode_length:
        return dict.fromkeys(families, config.episode_length)
    from_dataset = {}
    if config.dataset_root or config.dataset_repo_id:
        from_dataset = family_horizons(open_dataset(config.dataset_repo_id, config.dataset_root))
    return {f: from_dataset.get(f) or gym.spec(ENV_IDS[f]).max_episode_steps for f in families}


def slot_families(config, num_envs: int) -> list[str]:
    """The task family of each parallel env: the config's families dealt in turn."""
    families = list(config.families) or list(TASK_FAMILIES)
    return [families[i % len(families)] for i in range(num_envs)]


def build_slots(config, num_envs: int) -> Slots | SlotWorkers:
    """The ManiSkill envs of a `RoboscapeManiSkillEnv` of `num_envs` episodes, to hand to several of them in turn
    (splits, checkpoints) when they share families and image size: built once, they save each env's start-up."""
    spec = SlotSpec(select_scenes("all")[0].id, config.image_size, SLOT_TIME_LIMIT, config.light_wrist_camera)
    return make_slots(slot_families(config, num_envs), spec, config.resolved_workers(num_envs))


class RoboscapeManiSkillEnv(BatchedEnv):
    def __init__(self, config, num_envs: int = 1, slots: Slots | SlotWorkers | None = None):
        """config: a `RoboscapeManiSkillEnvConfig` (see envs/configs.py). slots: envs made by `build_slots` with the
        same families, image size and num_envs, which this env uses and leaves open (default: its own)."""
        self.config, self.num_envs = config, num_envs
        families = list(config.families) or list(TASK_FAMILIES)
        self.scenes = select_scenes(config.split or "all", list(config.scenes) or None)
        if not self.scenes:
            raise InvalidInputError(f"no scene matches split={config.split!r} scenes={config.scenes}")
        self.slot_families = slot_families(config, num_envs)
        horizons = task_horizons(config, families)
        self.horizons = np.array([horizons[f] for f in self.slot_families])
        self._owns_slots = slots is None
        self.slots = build_slots(config, num_envs) if slots is None else slots
        size = config.image_size
        pixels = {cam: gym.spaces.Box(0, 255, (size, size, 3), np.uint8) for cam in config.cameras}
        spaces = {"pixels": gym.spaces.Dict(pixels)}
        if config.include_state:
            spaces["agent_pos"] = gym.spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float32)
        self.single_observation_space = gym.spaces.Dict(spaces)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.single_action_space = gym.spaces.Box(-1.0, 1.0, (7,), np.float32)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)
        self.render_mode = "rgb_array"
        self._max_episode_steps = int(self.horizons.max())
        self._max_step_reward = max_step_reward(config.alpha, config.beta, config.sparse_reward)
        self.reward_description = (
            f"simulator: {config.alpha} x {config.sparse_reward} while the task is accomplished "
            f"+ {config.beta} x the task's normalised dense reward"
        )
        self._rng = np.random.default_rng(config.seed)
        self._images = None

    def reset(self, *, seed=None, options=None):
        options = options or {}
        if (seed := self._seed_from(seed, options)) is not None:
            self._rng = np.random.default_rng(seed)
        groups = start_groups(self.slot_families, int(options.get("group_size", 1)))
        n_groups = int(groups.max()) + 1
        scene_ids = options.get("scene_id")
        scene_ids = (
            list(np.broadcast_to(scene_ids, (self.num_envs,)))
            if scene_ids is not None
            else [self.scenes[i].id for i in self._rng.integers(0, len(self.scenes), n_groups)[groups]]
        )
        episode_seeds = self._rng.integers(0, 2**31, n_groups)[groups]
        # The slots' latest observation (in-process slots update these arrays in place); `_observation` copies.
        self._images, self._state, self._tasks = self.slots.reset(episode_seeds, scene_ids)
        self._book = EpisodeBook(self.horizons, self.config.terminate_on_success, self._max_step_reward)
        return self._observation(), {"task": list(self._tasks), "scene_id": np.array(scene_ids), "group": groups}

    def step(self, actions):
        if self._images is None:
            raise RuntimeError("call reset() before step()")
        actions, clipped = self._check_actions(actions)
        # Ended episodes are not simulated any more.
        self._images, self._state, dense, success = self.slots.step(actions, ~self._book.finished)
        reward = self.config.alpha * self.config.sparse_reward * success + self.config.beta * dense
        reward = self._book.step(reward.astype(np.float32), success)
        info = {"is_success": self._book.succeeded.copy(), "clipped_actions": clipped}
        return self._observation(), reward, self._book.terminated.copy(), self._book.truncated.copy(), info

    def _observation(self) -> dict:
        obs = {"pixels": {cam: self._images[cam].copy() for cam in self.config.cameras}}
        if self.config.include_state:
            obs["agent_pos"] = self._state.copy()
        return obs

    def render(self) -> tuple[np.ndarray, ...]:
        """Per episode: its camera views stacked vertically."""
        return tuple(
            np.concatenate([self._images[cam][i] for cam in self.config.cameras]) for i in range(self.num_envs)
        )

    def tasks(self) -> tuple[str, ...]:
        return tuple(self._tasks) if self._images is not None else ("",) * self.num_envs

    def close_extras(self, **kwargs):
        if self._owns_slots:
            self.slots.close()
