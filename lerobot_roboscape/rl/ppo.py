"""PPO for LeRobot policies in the roboscape envs (paper Algorithm 1), on Accelerate: the rollout (rollout.py), then
read top to bottom, the update and the training loop (GAE and the losses in ppo_losses.py; the settings in
configuration_ppo.py; the running return statistics that scale rewards, and the checkpoints, in ppo_state.py).

One iteration runs one episode of fixed horizon in each of the batched envs (all start together: N scenes at
once), scales its rewards by the running spread of the discounted return, scores it with GAE, and updates the
policy for a few epochs of minibatches. The first `critic_warmup_iterations` train
the value head only, so the critic of a freshly SFT'd policy catches up before its advantages steer the policy.
A process of `accelerate launch` steps its own share of the envs; Accelerate averages the gradients.
"""

import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from accelerate import Accelerator
from lerobot.optim.optimizers import load_optimizer_state
from torch import Tensor, nn
from tqdm import tqdm

from lerobot_roboscape.rl.configuration_ppo import PPOConfig
from lerobot_roboscape.rl.policy_loading import (
    PolicyIO,
    check_actor_critic,
    check_policy_fits_env,
    check_policy_fits_frame_skip,
    load_policy,
)
from lerobot_roboscape.rl.ppo_losses import compute_gae, group_advantages, kl_to_reference, ppo_losses
from lerobot_roboscape.rl.ppo_state import RunningReturnStats, load_checkpoint, save_checkpoint
from lerobot_roboscape.rl.rollout import Rollout, collect_rollout, rollout_metrics
from lerobot_roboscape.robot import CONTROL_FREQ
from lerobot_roboscape.training.checkpoints import CHECKPOINTS, FINAL, LOGS, last_checkpoint, publish_final
from lerobot_roboscape.training.loop import resolve_mixed_precision
from lerobot_roboscape.training.records import HISTORY, History, write_video
from roboscape_core.errors import InvalidInputError, OutputExistsError

logger = logging.getLogger(__name__)


class ActionScorer(nn.Module):
    """`evaluate_actions` behind `forward`, so Accelerate's DDP wrapper synchronises its gradients."""

    def __init__(self, policy):
        super().__init__()
        self.policy = policy

    def forward(self, batch: dict, raw_action: Tensor):
        return self.policy.evaluate_actions(batch, raw_action)


def update(
    cfg: PPOConfig,
    accelerator: Accelerator,
    scorer,
    optimizer,
    io: PolicyIO,
    rollout: Rollout,
    generator: torch.Generator,
    return_stats: RunningReturnStats,
    critic_only: bool,
    reference=None,
) -> dict[str, float]:
    """PPO's epochs over one rollout; with a `reference` policy (the SFT checkpoint), its KL penalty too. With
    advantage="group", GRPO's: every decision of an episode gets its episode's group-relative success, and the value
    head is not trained."""
    grouped = cfg.advantage == "group"
    advantages, returns, samples, keep = _advantages(cfg, rollout, return_stats)
    t_index, b_index = samples.nonzero(as_tuple=True)
    b_advantages = advantages[t_index, b_index]
    if cfg.norm_adv and not grouped and len(b_advantages) > 1:
        b_advantages = (b_advantages - b_advantages.mean()) / (b_advantages.std() + 1e-8)
    stats, n_samples, stopped = [], len(t_index), False
    for _ in range(cfg.update_epochs if n_samples else 0):  # GRPO's iteration with no mixed group: nothing to learn
        if stopped:
            break
        order = torch.randperm(n_samples, generator=generator).to(t_index.device)
        minibatches = order.split(cfg.minibatch_size)
        for k, minibatch in enumerate(minibatches):
            t, b = t_index[minibatch].cpu().numpy(), b_index[minibatch].cpu().numpy()
            batch = io.batch(rollout.pixels_at(t, b), [rollout.tasks[i] for i in b])
            with accelerator.autocast():
                losses, loss, kl_stats = _minibatch_loss(
                    cfg, scorer, batch, rollout, (t, b), b_advantages[minibatch], returns, critic_only, reference
                )
            stats.append(kl_stats)
            stats.append({f"losses/{name}": float(value.detach()) for name, value in losses._asdict().items()})
            if not critic_only and cfg.target_kl is not None and losses.approx_kl > cfg.target_kl:
                optimizer.zero_grad(set_to_none=True)  # the policy moved far enough: drop what is accumulated
                stopped = True
                break
            accelerator.backward(loss / cfg.grad_accum_steps)
            if (k + 1) % cfg.grad_accum_steps == 0 or k + 1 == len(minibatches):
                stats.append(_step(cfg, accelerator, optimizer, critic_only))
    summary = {key: float(np.mean([s[key] for s in stats if key in s])) for key in {k for s in stats for k in s}}
    if grouped:
        summary["charts/groups_kept"] = float(len(set(rollout.groups[keep.numpy()].tolist())))
    else:
        explained = 1 - (returns - rollout.values)[rollout.alive].var() / returns[rollout.alive].var().clamp(min=1e-8)
        summary["losses/explained_variance"] = float(explained)
    return {
        **summary,
        "charts/samples": n_samples,
        "charts/critic_only": float(critic_only),
        "charts/update_stopped_by_kl": float(stopped),
        "charts/return_std": math.sqrt(return_stats.var),
    }


def _advantages(cfg: PPOConfig, rollout: Rollout, return_stats: RunningReturnStats):
    """(advantages, returns, samples, keep): GAE's on the (scaled) rewards; with advantage="group", each episode's
    group-relative success at every decision, the samples only of the groups kept and no critic's returns."""
    if cfg.advantage == "group":
        device = rollout.alive.device
        episode_advantages, keep = group_advantages(
            torch.as_tensor(rollout.successes), torch.as_tensor(rollout.groups), cfg.keep_mixed_groups
        )
        advantages = episode_advantages.to(device).expand_as(rollout.rewards)
        returns = rollout.values  # no critic: its loss is zero and left out
        return advantages, returns, rollout.alive & keep.to(device), keep
    rewards = rollout.rewards
    if cfg.normalize_reward:
        rewards = return_stats.scale_rewards(rewards, rollout.alive, cfg.gamma)
    advantages, returns = compute_gae(
        rewards, rollout.values, rollout.terminated, rollout.truncated, rollout.last_value, cfg.gamma, cfg.gae_lambda
    )
    return advantages, returns, rollout.alive, None


def _minibatch_loss(
    cfg: PPOConfig, scorer, batch: dict, rollout: Rollout, index, advantages, returns, critic_only, reference
):
    """The minibatch's PPO losses and the loss to step on: the value's only while the critic warms up, none with
    GRPO (no critic); with a `reference`, its KL penalty too (and its reading)."""
    t, b = index
    evaluation = scorer(batch, rollout.raw_actions[t, b])
    losses = ppo_losses(
        evaluation.log_prob,
        rollout.log_probs[t, b],
        advantages,
        evaluation.value,
        rollout.values[t, b],
        returns[t, b],
        evaluation.entropy,
        cfg.clip_coef,
        cfg.value_clip_coef,
        cfg.value_loss,
        cfg.huber_delta,
    )
    loss = losses.policy.new_zeros(()) if cfg.advantage == "group" else cfg.vf_coef * losses.value
    if not critic_only:
        loss = loss + losses.policy - cfg.ent_coef * losses.entropy
    kl_stats = {}
    if reference is not None:
        with torch.no_grad():
            reference_log_prob = reference.evaluate_actions(batch, rollout.raw_actions[t, b]).log_prob
        kl = kl_to_reference(evaluation.log_prob, reference_log_prob)
        kl_stats["losses/kl_to_reference"] = float(kl.detach())
        if not critic_only:
            loss = loss + cfg.kl_coef * kl
    return losses, loss, kl_stats


def _step(cfg: PPOConfig, accelerator: Accelerator, optimizer, critic_only: bool) -> dict[str, float]:
    """One optimizer step on the accumulated gradients; returns the gradient norms of the policy and value groups."""
    policy_group, value_group = optimizer.param_groups  # see make_optimizer
    if critic_only:  # a shared trunk (OpenVLA's LLM) also got value gradients: drop them
        for p in policy_group["params"]:
            p.grad = None
    # Clipped apart: the value head's early, large gradients must not shrink the policy's step.
    grad_norms = {
        name: float(accelerator.clip_grad_norm_(group["params"], cfg.max_grad_norm))
        for name, group in (("policy", policy_group), ("value", value_group))
        if any(p.grad is not None for p in group["params"])
    }
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)
    return {f"grad_norm/{name}": norm for name, norm in grad_norms.items()}


# Training loop with checkpoints (ppo_state.py).


def make_optimizer(policy, cfg: PPOConfig) -> torch.optim.Optimizer:
    """AdamW with two groups, in this order: the policy's parameters, then the value head's."""
    value_head = [p for name, p in policy.named_parameters() if p.requires_grad and name.startswith("value_head.")]
    rest = [p for name, p in policy.named_parameters() if p.requires_grad and not name.startswith("value_head.")]
    return torch.optim.AdamW(
        [{"params": rest, "lr": cfg.policy_lr}, {"params": value_head, "lr": cfg.value_lr}], eps=1e-5, weight_decay=0.0
    )


@dataclass
class _Start:
    """Where a run starts (the SFT checkpoint, or its last when resuming); `reference`: the KL lever's, frozen."""

    policy: torch.nn.Module
    io: PolicyIO
    optimizer: torch.optim.Optimizer
    reference: torch.nn.Module | None
    path: str
    iteration: int
    return_stats: RunningReturnStats
    elapsed: float


def _start(cfg: PPOConfig, accelerator: Accelerator) -> _Start:
    device = str(accelerator.device)
    iteration, path, return_stats, elapsed = 0, cfg.policy_path, RunningReturnStats(), 0.0
    checkpoint = last_checkpoint(cfg.output_dir) if cfg.resume else None
    if checkpoint is not None:
        iteration, return_stats, elapsed = load_checkpoint(checkpoint)
        path = str(checkpoint / FINAL)
    elif (cfg.output_dir / CHECKPOINTS).exists() and not cfg.resume:
        raise OutputExistsError(
            f"{cfg.output_dir} already holds PPO checkpoints: pass --resume=true to continue "
            f"or choose another --output_dir"
        )
    policy, preprocessor, postprocessor = load_policy(path, device)
    check_actor_critic(policy, path)
    check_policy_fits_env(policy, cfg.env, path)
    cfg.with_policy_defaults(policy.name)
    if cfg.init_std is not None and checkpoint is None:
        if not hasattr(policy, "set_action_std"):
            raise InvalidInputError(f"--init_std sets a Gaussian's std: the {policy.name!r} policy at {path} has none")
        policy.set_action_std(cfg.init_std)
    reference = None
    if cfg.kl_coef > 0:  # always the starting policy, also when resuming from a later checkpoint
        reference = load_policy(cfg.policy_path, device)[0].eval().requires_grad_(False)
        if cfg.init_std is not None:  # the policy as PPO starts it: a KL to SFT's init std would pull the std back
            reference.set_action_std(cfg.init_std)
    optimizer = make_optimizer(policy, cfg)
    if checkpoint is not None:
        load_optimizer_state(optimizer, checkpoint / "training_state")
        logger.info("resumed from %s (iteration %d)", checkpoint, iteration)
    io = PolicyIO(preprocessor, postprocessor)
    return _Start(policy, io, optimizer, reference, path, iteration, return_stats, elapsed)


def _postfix(metrics: dict) -> dict[str, str]:
    """What the progress bar shows of an iteration."""
    return {
        "ret": f"{metrics['charts/episode_return']:.2f}",
        "success": f"{metrics['charts/success']:.0%}",
        "episodes_per_s": f"{metrics['charts/episodes_per_s']:.2f}",
    }


def train_ppo(cfg: PPOConfig) -> Path:
    """Run PPO; returns its final model's directory, output_dir/pretrained_model (its newest checkpoint's)."""
    accelerator = Accelerator(
        mixed_precision=resolve_mixed_precision(cfg.mixed_precision),
        cpu=cfg.device == "cpu",
        log_with=["tensorboard"] + (["wandb"] if cfg.wandb else []),
        project_dir=cfg.output_dir,
    )
    run = _start(cfg, accelerator)
    scorer, optimizer = accelerator.prepare(ActionScorer(run.policy), run.optimizer)
    envs_here = math.ceil(cfg.num_envs / accelerator.num_processes)
    torch.manual_seed(cfg.seed)  # whatever an env draws at construction, the same in every run
    env = cfg.env.create_envs(envs_here)[cfg.env.type][0]
    check_policy_fits_frame_skip(run.policy, env, run.path)
    reward = getattr(env, "reward_description", "the env's own")
    logger.info("PPO reward: %s", reward)
    accelerator.init_trackers(LOGS, config={k: str(v) for k, v in asdict(cfg).items()})
    history = History(cfg.output_dir / HISTORY, run.iteration) if accelerator.is_main_process else None
    progress = tqdm(
        range(run.iteration, cfg.iterations),
        initial=run.iteration,
        total=cfg.iterations,
        desc="PPO",
        disable=not accelerator.is_main_process,
    )
    for iteration in progress:
        # One random stream per (iteration, process): a resumed run draws what an uninterrupted one would.
        stream = cfg.seed + 1_000_003 * iteration + accelerator.process_index
        torch.manual_seed(stream)
        record = cfg.video_freq > 0 and iteration % cfg.video_freq == 0 and accelerator.is_main_process
        started = time.perf_counter()
        run.policy.eval()
        group_size = cfg.group_size if cfg.advantage == "group" else 1
        rollout = collect_rollout(env, run.policy, run.io, seed=stream % 2**31, record=record, group_size=group_size)
        rollout_seconds = time.perf_counter() - started
        run.policy.train()  # dropout is 0 in both policies; train mode keeps OpenVLA's gradient checkpointing on
        critic_only = cfg.advantage == "gae" and iteration < cfg.critic_warmup_iterations
        generator = torch.Generator().manual_seed(stream)
        metrics = update(
            cfg,
            accelerator,
            scorer,
            optimizer,
            run.io,
            rollout,
            generator,
            run.return_stats,
            critic_only,
            run.reference,
        )
        seconds = time.perf_counter() - started
        metrics |= rollout_metrics(accelerator, rollout, seconds, rollout_seconds)
        run.elapsed += seconds
        accelerator.log(metrics, step=iteration + 1)
        if history is not None:
            history.append({"iteration": iteration + 1, "seconds": run.elapsed} | metrics)
        progress.set_postfix(_postfix(metrics))
        if record:
            fps = env.metadata.get("render_fps", CONTROL_FREQ)
            write_video(cfg.output_dir / "videos" / f"iteration_{iteration + 1:06d}.mp4", rollout.frames, fps)
        out_of_time = cfg.time_budget_s is not None and run.elapsed >= cfg.time_budget_s
        done = iteration + 1 == cfg.iterations or out_of_time
        if (done or (iteration + 1) % cfg.save_freq == 0) and accelerator.is_main_process:
            policy = accelerator.unwrap_model(scorer).policy
            save_checkpoint(
                cfg.output_dir, iteration + 1, policy, run.io, optimizer, cfg, run.return_stats, reward, run.elapsed
            )
        accelerator.wait_for_everyone()
        if out_of_time:
            logger.info("time budget of %.0f s spent after %d iterations", cfg.time_budget_s, iteration + 1)
            break
    if accelerator.is_main_process:
        publish_final(cfg.output_dir)
    accelerator.wait_for_everyone()
    accelerator.end_training()
    env.close()
    return Path(cfg.output_dir) / FINAL
