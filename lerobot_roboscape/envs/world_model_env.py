"""`roboscape_wm`: the world models as a batched reinforcement-learning environment (paper Algorithm 1).

B episodes run side by side on one device, stepped by one batched call of the action world model.

- **reset** draws each episode's initial frame and instruction from the episodes of a LeRobot dataset, across
  the scenes and task families selected, so one env covers many scenes at once. The goal frame of each start is
  generated once by the text world model (the first frame whose done >= theta) and cached. A reset can also start
  from given frames (`options={"frames": ..., "task": ..., "horizon": ...}`, another env's first observation, as
  the paired evaluation does with the simulator's), their goals made then (or given as `goal_frames`).
- **step** takes one action, as LeRobot steps every env. The action world model steps once per k = `frame_skip`
  actions (a model frame per executed action chunk, k saved with the model): the k-th action of a chunk predicts
  the next frame and done from the chunk, and is paid the reward of that frame, `WorldModelReward` (sparse done
  term + similarity to the goal); the steps between observe the last frame and are paid 0. A policy that executes
  k-action chunks so decides once per model frame; one that acts every step (OpenVLA) looks k times at each frame.
  `render()` and videos run at the model's frame rate: a frame repeats for its k steps. As in Algorithm 1, an
  episode runs its fixed horizon in control steps (by default the longest successful demonstration of its task
  family) and does not terminate at done; `is_success` is true once done crossed theta
  at any step. `terminate_on_success` ends episodes at success instead, with a terminal bonus (see `EpisodeBook`).
  A finished episode stays frozen (same frame, reward 0) until the next reset, which restarts all of them.
- With an **ensemble** of action models (`envs/ensemble.py`), each frame's disagreement is reported, and penalised
  (MOPO) or halts the episode (MOReL) where the world models no longer know what follows.
- With a **state margin**, an episode halts, unpaid and unsuccessful, at the first frame whose predicted robot state
  has left the range of the action model's training data: PPO learned to drive the arm there, where the frames
  break down into texture that the done head reads as success (docs/results/claim72_gpuwm).
"""

import logging
from pathlib import Path

import gymnasium as gym
import numpy as np
import psutil
import torch

from lerobot_roboscape.envs.batched import BatchedEnv, EpisodeBook, start_groups
from lerobot_roboscape.envs.ensemble import Ensemble
from lerobot_roboscape.envs.goal_bank import GoalBank
from lerobot_roboscape.envs.loading import load_ensemble, load_models, load_rewards, model_refs
from lerobot_roboscape.envs.starts import checked_frames, dataset_starts, file_starts, given_starts
from lerobot_roboscape.world_model.robot_state import STATE_STD_FLOOR
from lerobot_roboscape.world_model.rollout import Rollout
from roboscape_core.errors import InvalidInputError

logger = logging.getLogger(__name__)


def free_memory_bytes(device: str) -> int:
    """Bytes free for new tensors on `device`: the GPU's free memory, or the host's available memory."""
    if torch.device(device).type == "cuda":
        return torch.cuda.mem_get_info(torch.device(device))[0]
    return psutil.virtual_memory().available


class RoboscapeWorldModelEnv(BatchedEnv):
    """B episodes of the world models, side by side.

    **Observation:** {"pixels": {camera: (B, H, W, 3) uint8}} (a lone camera under `observation.image`: its array),
    the tokenizer's decoding of the current model frame, every view the dataset has.
    **Action:** (B, A) in [-1, 1], one control step; the action model reads a chunk of `frame_skip` of them.
    **Reward:** paid at the last step of each chunk, 0 between: alpha x `sparse_reward` while done >= theta_sps,
    plus beta x (1 - the similarity distance of the frame to its goal) (`WorldModelReward`); or a baseline reward
    model's (`reward_type`).
    **Episode end:** truncated at the start's horizon (its family's longest successful demonstration, or
    `episode_length`); `is_success` once done >= theta at any step; with `terminate_on_success`, terminated there.
    **Starts:** the first frames of a LeRobot dataset's episodes (filtered by family, split, scene, at most
    `starts_per_scene` each), or frames given to `reset` (another env's first observation).
    **Goals:** the goal bank's (`envs/goal_bank.py`): made once per start by the text model, or given to `reset`.
    """

    def __init__(self, config, num_envs: int = 1):
        """config: a `RoboscapeWorldModelEnvConfig` (see envs/configs.py)."""
        self.config, self.num_envs = config, num_envs
        self.device = config.resolved_device
        tokenizer, action_model, text_model, self.dataset_repo_id = model_refs(config)
        self.tokenizer, self.action_model, self.text_model = load_models(
            tokenizer, action_model, text_model, self.device
        )
        if self.action_model.config.control != "action":
            raise InvalidInputError(
                f"{action_model} is a {self.action_model.config.control} world model, not an action world model"
            )
        self.frame_skip = self.action_model.config.frame_skip
        self.ensemble = (
            Ensemble(list(load_ensemble(config.ensemble, self.action_model, self.device))) if config.ensemble else None
        )
        self.precision = config.resolved_precision
        bf16 = self.precision == "bfloat16"
        self.autocast = lambda: torch.autocast(torch.device(self.device).type, torch.bfloat16, enabled=bf16)
        self._check_cache_fits(torch.bfloat16 if bf16 else torch.float32)
        self._state_bounds = self._bounds_of_the_data(action_model) if config.state_margin is not None else None
        if self.text_model is not None and self.text_model.config.frame_skip != self.frame_skip:
            raise InvalidInputError(
                f"the text world model {text_model} steps every {self.text_model.config.frame_skip} control steps but "
                f"the action world model {action_model} every {self.frame_skip}: train both with the same "
                "--wm.frame_skip"
            )
        rewards = load_rewards(config, self.tokenizer, self.device)
        self.reward_fn, self.reward_model, self.success_classifier = rewards.paid, rewards.model, rewards.classifier
        self.similarity, self.reward_description = self.reward_fn.distance.name, rewards.description
        logger.info("roboscape_wm reward: %s", self.reward_description)
        n_cameras = self.action_model.config.n_cameras
        if config.starts_file:
            self.starts, self.cameras, self.action_range, self.starts_source = file_starts(config, n_cameras)
        else:
            self.starts, self.cameras, self.action_range = dataset_starts(
                config, self.dataset_repo_id, n_cameras, self.encode
            )
            self.starts_source = f"{self.dataset_repo_id} at {config.dataset_root}"
        self.goal_bank = GoalBank(
            config, self.text_model, self.frame_skip, self.device, self.done_of, self.autocast, self._goal_settings()
        )
        if config.goal_file and config.goal_source == "text_model":
            self.goal_bank.use_file(Path(config.goal_file), self.starts)

        # A lone camera under LeRobot's `observation.image` (PushT) is one array, as LeRobot's own envs give it.
        self._bare_pixels = "pixels" in config.features
        self._make_spaces()
        self.render_mode = "rgb_array"
        self._max_episode_steps = max(s.horizon for s in self.starts)
        self._n_cameras = len(self.cameras)
        self._rng = np.random.default_rng(config.seed)
        self._generator = torch.Generator(self.device).manual_seed(config.seed)
        self._rollout = None

    def _make_spaces(self) -> None:
        """Each camera's pixels (and the robot's state as `agent_pos` with include_state); actions in [-1, 1]."""
        size, config = self.tokenizer.config.image_size, self.config
        pixels = {cam: gym.spaces.Box(0, 255, (size, size, 3), np.uint8) for cam in self.cameras}
        observation = {"pixels": next(iter(pixels.values())) if self._bare_pixels else gym.spaces.Dict(pixels)}
        if config.include_state:
            if not self.action_model.config.state:
                raise InvalidInputError(
                    f"include_state: the action world model {config.action_world_model} carries no robot state "
                    "(trained with --wm.state=false)"
                )
            state_dim = self.action_model.config.state_dim
            observation["agent_pos"] = gym.spaces.Box(-np.inf, np.inf, (state_dim,), np.float32)
        self.single_observation_space = gym.spaces.Dict(observation)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        action_dim = self.action_model.config.action_dim
        self.single_action_space = gym.spaces.Box(-1.0, 1.0, (action_dim,), np.float32)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)

    # ---- starts and goals ----------------------------------------------------------------------------------

    def _check_cache_fits(self, dtype: torch.dtype) -> None:
        """Refuse a batch whose key/value cache cannot fit in the device's free memory, before any generation."""
        needed, free = self.action_model.cache_bytes(self.num_envs, dtype), free_memory_bytes(self.device)
        if needed > free:
            c = self.action_model.config
            raise InvalidInputError(
                f"roboscape_wm: {self.num_envs} episodes at once need {needed / 2**30:.2f} GiB of key/value cache "
                f"(window {c.window}, {c.n_layer} layers, {c.tokens_per_frame} tokens a frame, {dtype}) but "
                f"{free / 2**30:.2f} GiB are free on {self.device}: lower the number of envs"
            )

    def _checked_frames(self, frames: dict) -> dict[str, np.ndarray]:
        size = self.tokenizer.config.image_size
        return checked_frames(frames, self.cameras, (self.num_envs, size, size, 3))

    def encode(self, frames: dict[str, np.ndarray]) -> torch.Tensor:
        """camera -> (k, H, W, 3) uint8 to (k, S) tokens, views side by side."""
        return self.tokenizer.encode_frames(list(frames.values()))

    def decode(self, tokens_BS: torch.Tensor) -> torch.Tensor:
        """(B, S) tokens to (B, n_cameras, 3, H, W) images in [0, 1]."""
        with self.autocast():
            return self.tokenizer.decode_views(tokens_BS, self._n_cameras).float()

    @torch.no_grad()
    def done_of(self, tokens_BS: torch.Tensor, model_done: torch.Tensor, images=None) -> torch.Tensor:
        """The done probability (B,) of frames, from the configured source: the world model's own head
        (`model_done`, what it said when it made or read the frames) or the success classifier on the decoded
        frames (`images`, when already decoded)."""
        if self.success_classifier is None:
            return model_done
        return self.success_classifier.success_probability(self.decode(tokens_BS) if images is None else images)

    def _goal_settings(self) -> dict:
        """What a start's generated goal depends on, besides the start (the goal bank adds the text model's weights)."""
        cfg = self.config
        return {
            "text_world_model": str(cfg.text_world_model),
            "tokenizer": str(cfg.tokenizer),
            "dataset": self.starts_source,
            "done_source": cfg.done_source,
            "success_classifier": str(cfg.success_classifier),
            "theta": cfg.theta,
            "max_goal_steps": cfg.max_goal_steps,
            "frame_skip": self.frame_skip,
            "precision": self.precision,
        }

    # ---- gymnasium API -------------------------------------------------------------------------------------

    def reset(self, *, seed=None, options=None):
        options = options or {}
        if (seed := self._seed_from(seed, options)) is not None:
            self._rng = np.random.default_rng(seed)
            self._generator.manual_seed(seed)  # world-model sampling; in place: a CUDA graph holds this generator
        groups = start_groups([""] * self.num_envs, int(options.get("group_size", 1)))
        if groups.max() + 1 < self.num_envs and ("frames" in options or "episode_index" in options):
            raise ValueError("group_size repeats the starts the env draws: pass it without frames or episode_index")
        if "frames" in options:  # new starts: their goals are made now (or given), not cached
            horizons = self._max_episode_steps if options.get("horizon") is None else options["horizon"]
            state_dim = self.action_model.config.state_dim if self.action_model.config.state else None
            tokens = self.encode(self._checked_frames(options["frames"]))
            starts = given_starts(self.config, tokens, options.get("task"), horizons, options.get("states"), state_dim)
            if options.get("goal_frames") is not None:
                goal_tokens, reached = self.encode(self._checked_frames(options["goal_frames"])), [True] * len(starts)
            else:
                goals = self.goal_bank.generate(starts)
                goal_tokens, reached = torch.stack([g.tokens for g in goals]), [g.reached for g in goals]
        else:
            if "episode_index" in options:
                wanted = list(np.broadcast_to(options["episode_index"], (self.num_envs,)))
                by_index = {s.episode_index: s for s in self.starts if s.frame == 0}
                if missing := sorted(set(int(i) for i in wanted) - set(by_index)):
                    raise ValueError(f"episodes {missing} are not among this env's starts")
                starts = [by_index[int(i)] for i in wanted]
            else:
                drawn = self._rng.integers(0, len(self.starts), int(groups.max()) + 1)[groups]
                starts = [self.starts[i] for i in drawn]
            goal_tokens, reached = self.goal_bank.goals_for(starts)
        first = torch.stack([s.first_tokens for s in starts])
        first_states = None
        if self.action_model.config.state:
            first_states = torch.stack([s.first_state for s in starts]).to(self.device)[:, None]
        control = self.action_model.episode_control(
            torch.zeros(self.num_envs, 0, self.action_model.config.action_dim, device=self.device)
        )
        with self.autocast():
            self._rollout = Rollout.start(
                self.action_model,
                first[:, None],
                control,
                # The ensemble's eager passes read the rollout's cache between frames: no graph then.
                capture=self.config.cuda_graphs and torch.device(self.device).type == "cuda" and not self.ensemble,
                reuse=self._rollout,  # its cache's rings and CUDA graphs, when the shapes match
                states=first_states,
            )
            if self.ensemble is not None:
                self.ensemble.start(first[:, None], first_states)
        self._chunk = np.zeros((self.num_envs, self.frame_skip, self.action_model.config.action_dim), np.float32)
        self._substep = 0  # actions of the current chunk taken so far
        self._done = np.zeros(self.num_envs, np.float32)  # the latest frame's done probability, read every step
        self._starts = starts
        self._frames = self.decode(first)
        self._goals = self.decode(goal_tokens)
        with self.autocast():
            start_parts = self.reward_fn(self._frames, self._goals, torch.zeros(self.num_envs, device=self.device))
        self._distance = start_parts.distance.cpu().numpy()  # to the goal, of the frame shown
        self._book = EpisodeBook(
            np.array([s.horizon for s in starts]), self.config.terminate_on_success, self.reward_fn.max_step_reward
        )
        info = {
            "task": [s.task for s in starts],
            "episode_index": np.array([s.episode_index for s in starts]),
            "start_frame": np.array([s.frame for s in starts]),
            "goal_from_text_model": np.array(reached),
            "goal": self._pixels(self._goals),
            "group": groups,
        }
        return self._observation(), info

    def step(self, actions):
        """Take the action; at a chunk's last action, in lifecycle order: generate the next frame, decode it, read
        its done (`done_of`), pay it (`compute_reward`, the one place the reward is chosen), then book the episode."""
        if self._rollout is None:
            raise RuntimeError("call reset() before step()")
        actions, clipped = self._check_actions(actions)
        if self.config.clip_actions:
            actions = np.clip(actions, *self.action_range)
        self._chunk[:, self._substep] = actions
        self._substep += 1
        live = ~self._book.finished
        halt, off_data = None, np.zeros(self.num_envs, dtype=bool)
        if self._substep < self.frame_skip:  # within a chunk: the last frame stays, nothing is paid
            zeros = np.zeros(self.num_envs, np.float32)
            reward = zeros
            parts = {"reward_sparse": zeros, "reward_dense": zeros, "distance_to_goal": self._distance}
            disagreement = zeros
        else:
            self._substep = 0
            tokens, model_done, disagreement = self._generate(live)
            frames = self.decode(tokens)
            done = self.done_of(tokens, model_done, frames)
            self._done = done.cpu().numpy()  # once per frame: the steps between read it without a device sync
            self._frames = torch.where(
                torch.from_numpy(live).to(self.device)[:, None, None, None, None], frames, self._frames
            )
            reward, parts = self.compute_reward(frames, done, disagreement, live)
            halt, off_data = self._halts(disagreement)
            reward = reward * ~off_data  # a frame off the data pays nothing and is no success
        reward = self._book.step(reward, self._succeeding() & ~off_data, halt)
        info = {
            "is_success": self._book.succeeded.copy(),
            "halted": self._book.halted.copy(),
            "done_probability": self._done.copy(),
            **parts,
            "clipped_actions": clipped,
            "goal": self._pixels(self._goals),
        }
        if self.ensemble is not None:
            info["disagreement"] = disagreement
        # Ended episodes stay frozen and keep reporting how they ended until the next reset.
        return self._observation(), reward, self._book.terminated.copy(), self._book.truncated.copy(), info

    def _generate(self, live: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
        """The next frame's tokens (B, S) under the chunk just completed, the action model's done (B,), and the
        ensemble's disagreement on it (B,; 0 without an ensemble, or for a finished episode)."""
        chunk = torch.from_numpy(self._chunk).to(self.device)[:, None]  # (B, 1, k, A)
        control = self.action_model.encode_control(chunk)
        disagreement = np.zeros(self.num_envs, np.float32)
        with self.autocast():
            if self.ensemble is not None:  # every model's prediction, before the env's model decodes
                disagreement = self.ensemble.disagreement(self._rollout, chunk).cpu().numpy() * live
            tokens, done = self._rollout.predict_next_frame(control, self.config.temperature, self._generator)
            if self.ensemble is not None:
                self.ensemble.observe(tokens, chunk, self._rollout.state)
        return tokens, done, disagreement

    def _halts(self, disagreement: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The episodes that halt at the frame just generated (B,), and those among them whose predicted robot state
        has left the data's range (B,)."""
        off_data = np.zeros(self.num_envs, dtype=bool)
        if self._state_bounds is not None:
            low, high = self._state_bounds
            state = self._rollout.state.float()
            off_data = ((state < low) | (state > high)).any(-1).cpu().numpy()
        halt = off_data.copy()
        if self.config.disagreement_threshold is not None:
            halt |= disagreement > self.config.disagreement_threshold
        return halt, off_data

    def _bounds_of_the_data(self, name: str) -> tuple[torch.Tensor, torch.Tensor]:
        """The range of the action model's training states, widened on each side by state_margin x its span (a
        span floored as the states' spread is, so that a dimension the data never moved is not a wall)."""
        config = self.action_model.config
        if not config.state or config.state_min is None:
            raise InvalidInputError(
                f"state_margin: the action world model {name} carries no range of its training data's states "
                "(trained with --wm.state=false, or before the range was recorded): retrain it, or leave "
                "state_margin null"
            )
        low, high = (torch.tensor(v, device=self.device) for v in (config.state_min, config.state_max))
        widen = self.config.state_margin * (high - low).clamp(min=STATE_STD_FLOOR)
        return low - widen, high + widen

    def _succeeding(self) -> np.ndarray:
        return self._done >= self.config.theta

    @torch.no_grad()
    def compute_reward(
        self, frames: torch.Tensor, done: torch.Tensor, disagreement: np.ndarray, live: np.ndarray
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The reward (B,) of the frames just generated, of the configured type (the paper's, or a baseline reward
        model's), less the ensemble's disagreement penalty; and its parts for `info`."""
        with self.autocast():
            paid = self.reward_fn(frames, self._goals, done)
        if self.config.reward_type == "embedding":
            reward = self.reward_model(self._rollout.features)
        elif self.config.reward_type == "proxy":
            reward = self.reward_model(frames)
        else:
            reward = paid.reward
        self._distance = paid.distance.cpu().numpy()
        parts = {
            "reward_sparse": paid.sparse.cpu().numpy() * live,
            "reward_dense": paid.dense.cpu().numpy() * live,
            "distance_to_goal": self._distance,
        }
        return reward.cpu().numpy() - self.config.disagreement_penalty * disagreement, parts

    def _pixels(self, images: torch.Tensor) -> dict[str, np.ndarray]:
        uint8 = (images.clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 1, 3, 4, 2).cpu().numpy()
        return {cam: uint8[:, i] for i, cam in enumerate(self.cameras)}

    def _observation(self) -> dict:
        pixels = self._pixels(self._frames)
        observation = {"pixels": next(iter(pixels.values())) if self._bare_pixels else pixels}
        if self.config.include_state:
            observation["agent_pos"] = self._rollout.state.float().cpu().numpy()
        return observation

    def render(self) -> tuple[np.ndarray, ...]:
        """Per episode: its views stacked vertically, the current frame left and the goal right."""
        current, goal = self._pixels(self._frames), self._pixels(self._goals)
        column = lambda views: np.concatenate([views[c] for c in self.cameras], axis=1)  # noqa: E731
        return tuple(np.concatenate([column(current), column(goal)], axis=2))

    def tasks(self) -> tuple[str, ...]:
        return tuple(s.task for s in self._starts) if self._rollout is not None else ("",) * self.num_envs
