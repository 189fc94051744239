"""PPO for LeRobot policies in the roboscape envs (paper Algorithm 1), on Accelerate, read top to bottom:
config -> GAE and the losses -> rollout -> update -> the training loop with checkpoints.

One iteration runs one episode in each of the batched envs (all start together: N scenes at once), scores it
with GAE, and updates the policy for a few epochs of minibatches. A process of `accelerate launch` steps its own
share of the envs; Accelerate averages the gradients.
"""

import json
import logging
import math
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import NamedTuple

import draccus
import numpy as np
import torch
from accelerate import Accelerator
from lerobot.envs.configs import EnvConfig
from lerobot.optim.optimizers import load_optimizer_state, save_optimizer_state
from torch import Tensor, nn
from tqdm import tqdm

from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.rl.policy_loading import PolicyIO, check_actor_critic, check_policy_fits_env, load_policy
from lerobot_roboscape.training import CHECKPOINTS, FINAL, _make_tmp_dir, last_checkpoint, resolve_mixed_precision

logger = logging.getLogger(__name__)

# Per policy type: RL4VLA's settings for OpenVLA; ours (tuned on the tiny tasks) for the MLP.
PPO_DEFAULTS = {
    "openvla": dict(policy_lr=1e-4, value_lr=3e-3, update_epochs=1, minibatch_size=8, grad_accum_steps=20,
                    max_grad_norm=10.0, huber_delta=10.0, vf_coef=1.0),
    "roboscape_mlp": dict(policy_lr=3e-4, value_lr=1e-3, update_epochs=4, minibatch_size=64, grad_accum_steps=1,
                          max_grad_norm=0.5, huber_delta=None, vf_coef=0.5),
}  # fmt: skip


@dataclass
class PPOConfig:
    """Args:
    policy_path: the policy to start from (an SFT checkpoint's pretrained_model directory or a Hub repo id).
    env: the env to train in (`--env.type=roboscape_wm` or `roboscape_maniskill`, with its options).
    output_dir: checkpoints (output_dir/checkpoints/NNNNNNNN/pretrained_model), logs and videos.
    num_envs: parallel episodes per iteration, over all processes.
    iterations: PPO iterations (one episode per env each).
    gamma: discount.
    gae_lambda: GAE lambda.
    clip_coef: policy ratio clipping.
    value_clip_coef: value clipping around the rollout's values (null: none).
    ent_coef: entropy bonus.
    norm_adv: normalise advantages over the iteration's samples.
    policy_lr: learning rate of the policy's parameters (LoRA for OpenVLA); null: the policy type's default.
    value_lr: learning rate of the value head; null: default.
    update_epochs: passes over the iteration's samples; null: default.
    minibatch_size: samples per gradient computation; null: default.
    grad_accum_steps: minibatches per optimiser step; null: default.
    max_grad_norm: gradient-norm clipping; null: default.
    huber_delta: Huber value loss with this delta instead of squared error; null: default (0 forces squared).
    vf_coef: value loss coefficient; null: default.
    device: "auto" (cuda when present), "cpu" or "cuda"; Accelerate picks the GPU of each process.
    mixed_precision: "auto" (bf16 on GPUs that support it), "bf16" or "no".
    seed: seed of the env resets, the action sampling and the minibatches (one stream per iteration).
    save_freq: iterations between checkpoints (the last iteration always saves).
    video_freq: iterations between rollout videos (0: none).
    resume: continue from the last checkpoint in output_dir.
    wandb: also log to Weights & Biases (when installed).
    """

    policy_path: str = ""
    env: EnvConfig = field(default_factory=RoboscapeWorldModelEnvConfig)
    output_dir: Path = Path("outputs/ppo")
    num_envs: int = 16
    iterations: int = 100
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_coef: float = 0.2
    value_clip_coef: float | None = 0.2
    ent_coef: float = 0.0
    norm_adv: bool = True
    policy_lr: float | None = None
    value_lr: float | None = None
    update_epochs: int | None = None
    minibatch_size: int | None = None
    grad_accum_steps: int | None = None
    max_grad_norm: float | None = None
    huber_delta: float | None = None
    vf_coef: float | None = None
    device: str = "auto"
    mixed_precision: str = "auto"
    seed: int = 0
    save_freq: int = 10
    video_freq: int = 0
    resume: bool = False
    wandb: bool = False

    def __post_init__(self):
        if not self.policy_path:
            raise ValueError("--policy_path is required: the SFT checkpoint (or Hub repo id) PPO starts from")
        if self.num_envs < 1 or self.iterations < 1 or self.save_freq < 1:
            raise ValueError(f"num_envs, iterations and save_freq must be >= 1, got {self.num_envs}, "
                             f"{self.iterations}, {self.save_freq}")
        self.output_dir = Path(self.output_dir)

    def with_policy_defaults(self, policy_type: str) -> "PPOConfig":
        """Fill the fields left null with the defaults of `policy_type`."""
        defaults = PPO_DEFAULTS.get(policy_type, PPO_DEFAULTS["roboscape_mlp"])
        for name, value in defaults.items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        if self.huber_delta == 0:
            self.huber_delta = None
        return self


# GAE and the PPO losses.


def compute_gae(rewards: Tensor, values: Tensor, terminated: Tensor, last_value: Tensor, gamma: float,
                gae_lambda: float) -> tuple[Tensor, Tensor]:
    """Advantages and returns (T, B). An episode that ends by termination bootstraps nothing; one still running
    at the last step (truncated by the time limit) bootstraps from `last_value` (B,). Steps after an episode's
    end never reach its earlier steps, since termination cuts the recursion."""
    advantages = torch.zeros_like(rewards)
    next_advantage = torch.zeros_like(last_value)
    next_value = last_value
    for t in reversed(range(len(rewards))):
        nonterminal = 1.0 - terminated[t].float()
        delta = rewards[t] + gamma * next_value * nonterminal - values[t]
        next_advantage = delta + gamma * gae_lambda * nonterminal * next_advantage
        advantages[t] = next_advantage
        next_value = values[t]
    return advantages, advantages + values


class PPOLosses(NamedTuple):
    policy: Tensor
    value: Tensor
    entropy: Tensor
    approx_kl: Tensor
    clip_fraction: Tensor


def ppo_losses(new_log_prob: Tensor, old_log_prob: Tensor, advantages: Tensor, new_value: Tensor,
               old_value: Tensor, returns: Tensor, entropy: Tensor, clip_coef: float,
               value_clip_coef: float | None, huber_delta: float | None) -> PPOLosses:
    """Clipped surrogate, (clipped) value loss and diagnostics, averaged over the samples."""
    log_ratio = new_log_prob - old_log_prob
    ratio = log_ratio.exp()
    policy_loss = torch.max(-advantages * ratio, -advantages * ratio.clamp(1 - clip_coef, 1 + clip_coef)).mean()

    def error_loss(error: Tensor) -> Tensor:
        if huber_delta is None:
            return 0.5 * error.pow(2)
        return nn.functional.huber_loss(error, torch.zeros_like(error), reduction="none", delta=huber_delta)

    value_loss = error_loss(new_value - returns)
    if value_clip_coef is not None:
        clipped = old_value + (new_value - old_value).clamp(-value_clip_coef, value_clip_coef)
        value_loss = torch.max(value_loss, error_loss(clipped - returns))
    with torch.no_grad():
        approx_kl = ((ratio - 1) - log_ratio).mean()
        clip_fraction = ((ratio - 1).abs() > clip_coef).float().mean()
    return PPOLosses(policy_loss, value_loss.mean(), entropy.mean(), approx_kl, clip_fraction)


# Rollout.


class Rollout(NamedTuple):
    pixels: dict[str, np.ndarray]  # camera -> (T, B, H, W, C) uint8
    tasks: list[str]  # (B,)
    raw_actions: Tensor  # (T, B, ...)
    log_probs: Tensor  # (T, B)
    values: Tensor  # (T, B)
    rewards: Tensor  # (T, B)
    terminated: Tensor  # (T, B) episode ended by termination at this step
    alive: Tensor  # (T, B) the episode was running at this step
    last_value: Tensor  # (B,) value after the last step
    returns: np.ndarray  # (B,) episode returns
    successes: np.ndarray  # (B,) success at any step
    frames: list[np.ndarray]  # render() per step, when recorded


@torch.no_grad()
def collect_rollout(env, policy, io: PolicyIO, seed: int, record: bool = False) -> Rollout:
    observation, _ = env.reset(seed=seed)
    tasks = list(env.call("task"))
    steps, n = env.call("_max_episode_steps")[0], env.num_envs
    pixels = {cam: np.zeros((steps, *image.shape), np.uint8) for cam, image in observation["pixels"].items()}
    columns = {name: [] for name in ("raw_actions", "log_probs", "values", "rewards", "terminated", "alive")}
    alive = np.ones(n, dtype=bool)
    returns, successes, frames = np.zeros(n), np.zeros(n, dtype=bool), []
    for t in range(steps):
        for cam, image in observation["pixels"].items():
            pixels[cam][t] = image
        sample = policy.sample_action(io.batch(observation["pixels"], tasks))
        observation, reward, terminated, truncated, info = env.step(io.env_action(sample.action))
        if record:
            frames.append(np.concatenate(env.render(), axis=1))
        returns += reward * alive
        successes |= np.asarray(info.get("is_success", np.zeros(n, dtype=bool)), dtype=bool) & alive
        for name, value in (("raw_actions", sample.raw_action), ("log_probs", sample.log_prob),
                            ("values", sample.value), ("rewards", reward), ("terminated", terminated & alive),
                            ("alive", alive.copy())):  # fmt: skip
            columns[name].append(torch.as_tensor(value))
        alive &= ~(terminated | truncated)
        if not alive.any():
            break
    last_value = policy.predict_value(io.batch(observation["pixels"], tasks))
    device = last_value.device
    stacked = {name: torch.stack(values).to(device) for name, values in columns.items()}
    stacked["rewards"] = stacked["rewards"].float()
    length = len(stacked["alive"])
    return Rollout({cam: array[:length] for cam, array in pixels.items()}, tasks, **stacked,
                   last_value=last_value, returns=returns, successes=successes, frames=frames)  # fmt: skip


# Update.


class ActionScorer(nn.Module):
    """`evaluate_actions` behind `forward`, so Accelerate's DDP wrapper synchronises its gradients."""

    def __init__(self, policy):
        super().__init__()
        self.policy = policy

    def forward(self, batch: dict, raw_action: Tensor):
        return self.policy.evaluate_actions(batch, raw_action)


def update(cfg: PPOConfig, accelerator: Accelerator, scorer, optimizer, io: PolicyIO, rollout: Rollout,
           generator: torch.Generator) -> dict[str, float]:
    advantages, returns = compute_gae(rollout.rewards, rollout.values, rollout.terminated, rollout.last_value,
                                      cfg.gamma, cfg.gae_lambda)  # fmt: skip
    t_index, b_index = rollout.alive.nonzero(as_tuple=True)  # samples: the steps episodes were running
    b_advantages = advantages[t_index, b_index]
    if cfg.norm_adv and len(b_advantages) > 1:
        b_advantages = (b_advantages - b_advantages.mean()) / (b_advantages.std() + 1e-8)
    stats, n_samples = [], len(t_index)
    parameters = [p for group in optimizer.param_groups for p in group["params"]]
    for _ in range(cfg.update_epochs):
        order = torch.randperm(n_samples, generator=generator).to(t_index.device)
        minibatches = order.split(cfg.minibatch_size)
        for k, minibatch in enumerate(minibatches):
            t, b = t_index[minibatch].cpu().numpy(), b_index[minibatch].cpu().numpy()
            batch = io.batch({cam: array[t, b] for cam, array in rollout.pixels.items()},
                             [rollout.tasks[i] for i in b])  # fmt: skip
            with accelerator.autocast():
                evaluation = scorer(batch, rollout.raw_actions[t, b])
                losses = ppo_losses(evaluation.log_prob, rollout.log_probs[t, b], b_advantages[minibatch],
                                    evaluation.value, rollout.values[t, b], returns[t, b], evaluation.entropy,
                                    cfg.clip_coef, cfg.value_clip_coef, cfg.huber_delta)  # fmt: skip
                loss = losses.policy - cfg.ent_coef * losses.entropy + cfg.vf_coef * losses.value
            accelerator.backward(loss / cfg.grad_accum_steps)
            if (k + 1) % cfg.grad_accum_steps == 0 or k + 1 == len(minibatches):
                grad_norm = accelerator.clip_grad_norm_(parameters, cfg.max_grad_norm)
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)
                stats.append({"grad_norm": float(grad_norm)})
            stats.append({f"losses/{name}": float(value.detach()) for name, value in losses._asdict().items()})
    summary = {key: float(np.mean([s[key] for s in stats if key in s])) for key in {k for s in stats for k in s}}
    explained = 1 - (returns - rollout.values)[rollout.alive].var() / returns[rollout.alive].var().clamp(min=1e-8)
    return {**summary, "losses/explained_variance": float(explained), "charts/samples": n_samples}


# Training loop with checkpoints.


def make_optimizer(policy, cfg: PPOConfig) -> torch.optim.Optimizer:
    value_head = [p for name, p in policy.named_parameters() if p.requires_grad and name.startswith("value_head.")]
    rest = [p for name, p in policy.named_parameters() if p.requires_grad and not name.startswith("value_head.")]
    return torch.optim.AdamW([{"params": rest, "lr": cfg.policy_lr}, {"params": value_head, "lr": cfg.value_lr}],
                             eps=1e-5, weight_decay=0.0)  # fmt: skip


def save_checkpoint(output_dir: Path, iteration: int, policy, io: PolicyIO, optimizer, cfg: PPOConfig) -> Path:
    """checkpoints/NNNNNNNN/{pretrained_model (policy + processors, loadable by lerobot-eval), training_state},
    written to a temporary folder and moved into place; `checkpoints/last` names the newest."""
    root = output_dir / CHECKPOINTS
    name = f"{iteration:08d}"
    tmp = _make_tmp_dir(root, name)
    policy.save_pretrained(tmp / FINAL)
    io.preprocessor.save_pretrained(tmp / FINAL)
    io.postprocessor.save_pretrained(tmp / FINAL)
    (tmp / "training_state").mkdir()
    save_optimizer_state(optimizer, tmp / "training_state")
    (tmp / "training_state" / "iteration.json").write_text(json.dumps({"iteration": iteration}))
    with draccus.config_type("json"):
        draccus.dump(cfg, (tmp / "ppo_config.json").open("w"), indent=2)
    shutil.rmtree(root / name, ignore_errors=True)
    os.replace(tmp, root / name)
    pointer = root / ".last.tmp"
    pointer.write_text(name)
    os.replace(pointer, root / "last")
    return root / name


def train_ppo(cfg: PPOConfig) -> Path:
    """Run PPO; returns the final checkpoint's pretrained_model directory."""
    accelerator = Accelerator(mixed_precision=resolve_mixed_precision(cfg.mixed_precision),
                              cpu=cfg.device == "cpu", log_with=["tensorboard"] + (["wandb"] if cfg.wandb else []),
                              project_dir=cfg.output_dir)  # fmt: skip
    device = str(accelerator.device)
    start_iteration, start_path = 0, cfg.policy_path
    checkpoint = last_checkpoint(cfg.output_dir) if cfg.resume else None
    if checkpoint is not None:
        start_iteration = json.loads((checkpoint / "training_state" / "iteration.json").read_text())["iteration"]
        start_path = str(checkpoint / FINAL)
    elif (cfg.output_dir / CHECKPOINTS).exists() and not cfg.resume:
        raise FileExistsError(f"{cfg.output_dir} already holds PPO checkpoints: pass --resume=true to continue "
                              f"or choose another --output_dir")
    policy, preprocessor, postprocessor = load_policy(start_path, device)
    check_actor_critic(policy, start_path)
    check_policy_fits_env(policy, cfg.env, start_path)
    cfg.with_policy_defaults(policy.name)
    io = PolicyIO(preprocessor, postprocessor)
    optimizer = make_optimizer(policy, cfg)
    if checkpoint is not None:
        load_optimizer_state(optimizer, checkpoint / "training_state")
        logger.info("resumed from %s (iteration %d)", checkpoint, start_iteration)
    scorer, optimizer = accelerator.prepare(ActionScorer(policy), optimizer)

    envs_here = math.ceil(cfg.num_envs / accelerator.num_processes)
    env = cfg.env.create_envs(envs_here)[cfg.env.type][0]
    accelerator.init_trackers("ppo", config={k: str(v) for k, v in asdict(cfg).items()})
    progress = tqdm(range(start_iteration, cfg.iterations), initial=start_iteration, total=cfg.iterations,
                    desc="PPO", disable=not accelerator.is_main_process)  # fmt: skip
    final = None
    for iteration in progress:
        # One random stream per (iteration, process): a resumed run draws what an uninterrupted one would.
        stream = cfg.seed + 1_000_003 * iteration + accelerator.process_index
        torch.manual_seed(stream)
        record = cfg.video_freq > 0 and iteration % cfg.video_freq == 0 and accelerator.is_main_process
        started = time.perf_counter()
        policy.eval()
        rollout = collect_rollout(env, policy, io, seed=stream % 2**31, record=record)
        rollout_seconds = time.perf_counter() - started
        policy.train()  # dropout is 0 in both policies; train mode keeps OpenVLA's gradient checkpointing on
        metrics = update(cfg, accelerator, scorer, optimizer, io, rollout, torch.Generator().manual_seed(stream))
        episodes = accelerator.gather(torch.tensor(rollout.returns, device=device)).cpu().numpy()
        successes = accelerator.gather(torch.tensor(rollout.successes, device=device)).cpu().numpy()
        seconds = time.perf_counter() - started
        metrics |= {"charts/episode_return": float(episodes.mean()), "charts/success": float(successes.mean()),
                    "charts/episode_length": float(rollout.alive.sum(0).float().mean()),
                    "charts/episodes_per_s": len(episodes) / seconds,
                    "charts/env_steps_per_s": float(rollout.alive.sum()) / rollout_seconds}  # fmt: skip
        accelerator.log(metrics, step=iteration + 1)
        progress.set_postfix(ret=f"{episodes.mean():.2f}", success=f"{successes.mean():.0%}",
                             episodes_per_s=f"{len(episodes) / seconds:.2f}")  # fmt: skip
        if record:
            write_video(cfg.output_dir / "videos" / f"iteration_{iteration + 1:06d}.mp4", rollout.frames,
                        env.metadata.get("render_fps", 20))  # fmt: skip
        done = iteration + 1 == cfg.iterations
        if (done or (iteration + 1) % cfg.save_freq == 0) and accelerator.is_main_process:
            final = save_checkpoint(cfg.output_dir, iteration + 1, accelerator.unwrap_model(scorer).policy, io,
                                    optimizer, cfg) / FINAL  # fmt: skip
        accelerator.wait_for_everyone()
    accelerator.end_training()
    env.close()
    return final if final is not None else last_checkpoint(cfg.output_dir) / FINAL


def write_video(path: Path, frames: list[np.ndarray], fps: int) -> None:
    import imageio.v3 as iio

    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, np.stack(frames), plugin="pyav", codec="libx264", fps=fps)
