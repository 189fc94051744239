"""GAE and the PPO losses (CleanRL's, on LeRobot policies' log-probs), and the KL to a reference policy."""

from typing import NamedTuple

import torch
from torch import Tensor, nn


def compute_gae(
    rewards: Tensor,
    values: Tensor,
    terminated: Tensor,
    truncated: Tensor,
    last_value: Tensor,
    gamma: float,
    gae_lambda: float,
) -> tuple[Tensor, Tensor]:
    """Advantages and returns (T, B). An episode that ends by termination bootstraps nothing; one truncated by its
    horizon bootstraps from the value of the observation after its last step (`values[t + 1]`, or `last_value`
    (B,) after the rollout's last step). Either way the recursion stops there, so the steps after an episode's end
    never reach its earlier steps."""
    advantages = torch.zeros_like(rewards)
    next_advantage = torch.zeros_like(last_value)
    next_value = last_value
    for t in reversed(range(len(rewards))):
        nonterminal = 1.0 - terminated[t].float()
        continues = nonterminal * (1.0 - truncated[t].float())
        delta = rewards[t] + gamma * next_value * nonterminal - values[t]
        next_advantage = delta + gamma * gae_lambda * continues * next_advantage
        advantages[t] = next_advantage
        next_value = values[t]
    return advantages, advantages + values


def group_advantages(successes: Tensor, groups: Tensor, keep_mixed: bool) -> tuple[Tensor, Tensor]:
    """GRPO's advantages (B,) of B episodes in groups that started alike: an episode's success (0 or 1) minus its
    group's mean, over the group's std (1e-6 added), and which episodes to train on: all, or with `keep_mixed`
    only those of groups with both outcomes (a group that all succeeded or all failed has no advantage to give)."""
    outcome = successes.float()
    n_groups = int(groups.max()) + 1
    count = torch.zeros(n_groups).index_add_(0, groups, torch.ones_like(outcome))
    mean = torch.zeros(n_groups).index_add_(0, groups, outcome) / count
    var = torch.zeros(n_groups).index_add_(0, groups, (outcome - mean[groups]) ** 2) / count
    advantages = (outcome - mean[groups]) / (var[groups].sqrt() + 1e-6)
    mixed = (mean > 0) & (mean < 1)
    keep = mixed[groups] if keep_mixed else torch.ones_like(outcome, dtype=torch.bool)
    return advantages, keep


class PPOLosses(NamedTuple):
    policy: Tensor
    value: Tensor
    entropy: Tensor
    approx_kl: Tensor
    clip_fraction: Tensor


def ppo_losses(
    new_log_prob: Tensor,
    old_log_prob: Tensor,
    advantages: Tensor,
    new_value: Tensor,
    old_value: Tensor,
    returns: Tensor,
    entropy: Tensor,
    clip_coef: float,
    value_clip_coef: float | None,
    value_loss: str = "mse",
    huber_delta: float = 10.0,
) -> PPOLosses:
    """Clipped surrogate, (clipped) value loss and diagnostics, averaged over the samples."""
    log_ratio = new_log_prob - old_log_prob
    ratio = log_ratio.exp()
    policy_loss = torch.max(-advantages * ratio, -advantages * ratio.clamp(1 - clip_coef, 1 + clip_coef)).mean()

    def error_loss(error: Tensor) -> Tensor:
        if value_loss == "mse":
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


def kl_to_reference(log_prob: Tensor, reference_log_prob: Tensor) -> Tensor:
    """KL(policy || reference) estimated on actions the rollout's policy sampled: Schulman's k3, `r - 1 - log r` with
    r = reference / policy, non-negative per sample (so no sample rewards drifting) and unbiased when the samples
    are the policy's own. Averaged over the samples."""
    log_ratio = reference_log_prob - log_prob
    return (log_ratio.exp() - 1 - log_ratio).mean()
