"""One PPO iteration's rollout: an episode of fixed horizon in each of the batched envs (all start together), the
policy's raw actions, log-probabilities and values at each decision, and what the iteration reports of it. A
policy that acts in chunks (k actions per look, as it is evaluated) makes one decision per k env steps and is paid
their summed reward."""

from typing import NamedTuple

import numpy as np
import torch
from accelerate import Accelerator
from torch import Tensor

from lerobot_roboscape.rl.policy_loading import PolicyIO
from roboscape_core.errors import InvalidInputError


class Rollout(NamedTuple):
    pixels: dict[str, np.ndarray] | np.ndarray  # camera -> (T, B, H, W, C) uint8; one array where the env gave one
    tasks: list[str]  # (B,)
    raw_actions: Tensor  # (T, B, ...)
    log_probs: Tensor  # (T, B)
    values: Tensor  # (T, B)
    rewards: Tensor  # (T, B)
    terminated: Tensor  # (T, B) episode ended by termination at this step
    truncated: Tensor  # (T, B) episode ended by its horizon at this step
    alive: Tensor  # (T, B) the episode was running at this step
    last_value: Tensor  # (B,) value after the last step
    returns: np.ndarray  # (B,) episode returns
    successes: np.ndarray  # (B,) success at any step
    frames: list[np.ndarray]  # render() per step, when recorded
    disagreement: np.ndarray | None  # (B,) an ensemble's disagreement summed over the episode; None: none reported
    halted: np.ndarray | None  # (B,) the episode ended by the env's halt; None: the env halts none
    groups: np.ndarray  # (B,) the start each episode shares with its group (reset's group_size; else its own)

    def pixels_at(self, t: np.ndarray, b: np.ndarray) -> dict[str, np.ndarray] | np.ndarray:
        """The observations' pixels at steps `t` of episodes `b`, in the form the env gave them."""
        if isinstance(self.pixels, dict):
            return {cam: array[t, b] for cam, array in self.pixels.items()}
        return self.pixels[t, b]


@torch.no_grad()
def collect_rollout(env, policy, io: PolicyIO, seed: int, record: bool = False, group_size: int = 1) -> Rollout:
    """One episode in each of the env's B slots; with `group_size` G, the env starts them in groups of G alike."""
    observation, reset_info = env.reset(seed=seed, options={"group_size": group_size} if group_size > 1 else None)
    if group_size > 1 and "group" not in reset_info:
        raise InvalidInputError(f"{type(env).__name__} cannot start episodes in groups (advantage=group)")
    groups = np.asarray(reset_info.get("group", np.arange(env.num_envs)))
    tasks = list(env.call("task"))
    steps, n = env.call("_max_episode_steps")[0], env.num_envs
    device = next(policy.parameters()).device
    # Storage for the whole horizon, (steps, num_envs, ...) as in CleanRL, cut to the decisions made at the end.
    bare = not isinstance(observation["pixels"], dict)  # LeRobot's one-camera layout: one array, no views
    views = lambda obs: {"": obs["pixels"]} if bare else obs["pixels"]  # noqa: E731
    pixels = {cam: np.zeros((steps, *image.shape), np.uint8) for cam, image in views(observation).items()}
    log_probs, values, rewards = (torch.zeros((steps, n), device=device) for _ in range(3))
    terminated, truncated, alive_at = (torch.zeros((steps, n), dtype=torch.bool, device=device) for _ in range(3))
    raw_actions = None  # shaped as the policy's choice: a Gaussian sample, or OpenVLA's action token ids
    alive = np.ones(n, dtype=bool)
    returns, successes, frames = np.zeros(n), np.zeros(n, dtype=bool), []
    disagreement, halted = np.zeros(n), None  # roboscape_wm reports its halts, and with an ensemble its disagreement
    reported = False
    for t in range(steps):
        for cam, image in views(observation).items():
            pixels[cam][t] = image
        sample = policy.sample_action(io.batch(observation["pixels"], tasks))
        if raw_actions is None:
            raw_actions = torch.zeros((steps, *sample.raw_action.shape), dtype=sample.raw_action.dtype, device=device)
        chunk = io.env_action(sample.action)
        chunk = chunk[:, None] if chunk.ndim == 2 else chunk  # (B, k, action_dim): k env steps per decision
        reward, ended_by_task, ended_by_time = np.zeros(n), np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        for k in range(chunk.shape[1]):
            running = alive & ~(ended_by_task | ended_by_time)
            if not running.any():
                break
            observation, step_reward, task_ended, time_ended, info = env.step(chunk[:, k])
            if record:
                frames.append(np.concatenate(env.render(), axis=1))
            reward += step_reward * running
            successes |= np.asarray(info.get("is_success", np.zeros(n, dtype=bool)), dtype=bool) & running
            if "disagreement" in info:
                reported = True
                disagreement += np.asarray(info["disagreement"]) * running
            if "halted" in info:
                halted = (np.zeros(n, dtype=bool) if halted is None else halted) | (info["halted"] & running)
            ended_by_task |= task_ended & running
            ended_by_time |= time_ended & running
        returns += reward
        raw_actions[t], log_probs[t], values[t] = sample.raw_action, sample.log_prob, sample.value
        rewards[t] = torch.as_tensor(reward, device=device)
        alive_at[t] = torch.as_tensor(alive, device=device)
        terminated[t] = torch.as_tensor(ended_by_task, device=device)
        truncated[t] = torch.as_tensor(ended_by_time, device=device)
        alive &= ~(ended_by_task | ended_by_time)
        if not alive.any():
            break
    last_value = policy.predict_value(io.batch(observation["pixels"], tasks))
    T = t + 1
    return Rollout(
        pixels[""][:T] if bare else {cam: array[:T] for cam, array in pixels.items()},
        tasks,
        raw_actions[:T],
        log_probs[:T],
        values[:T],
        rewards[:T],
        terminated[:T],
        truncated[:T],
        alive_at[:T],
        last_value,
        returns,
        successes,
        frames,
        disagreement if reported else None,
        halted,
        groups,
    )


# Update.


def rollout_metrics(accelerator: Accelerator, rollout: Rollout, seconds: float, rollout_seconds: float) -> dict:
    """The iteration's episodes over every process: return, success, length, speed and, where an ensemble guards
    the run, its disagreement per decision; the share of episodes the env halted, where it halts any."""
    device = accelerator.device
    episodes = accelerator.gather(torch.tensor(rollout.returns, device=device)).cpu().numpy()
    successes = accelerator.gather(torch.tensor(rollout.successes, device=device)).cpu().numpy()
    metrics = {
        "charts/episode_return": float(episodes.mean()),
        "charts/success": float(successes.mean()),
        "charts/episode_length": float(rollout.alive.sum(0).float().mean()),
        "charts/episodes_per_s": len(episodes) / seconds,
        "charts/env_steps_per_s": float(rollout.alive.sum()) / rollout_seconds,
    }
    if rollout.disagreement is not None:  # the guard's own reading: does the policy leave the data?
        disagreement = accelerator.gather(torch.tensor(rollout.disagreement, device=device)).sum()
        decisions = accelerator.gather(rollout.alive.sum(0).float()).sum().clamp_min(1)
        metrics["charts/disagreement"] = float(disagreement / decisions)  # nats per decision
    if rollout.halted is not None:
        metrics["charts/halted"] = float(accelerator.gather(torch.tensor(rollout.halted, device=device)).float().mean())
    return metrics
