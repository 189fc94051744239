"""What PPO needs from a policy, shared by every policy plugin.

A policy reads a batch that went through its own preprocessor. Its actions are in the policy's normalised
space; the policy's postprocessor turns them into env actions. `raw_action` is whatever the policy needs to
score the same choice again later (a Gaussian sample, or OpenVLA's action token ids), so the log-prob of
`evaluate_actions` matches the one of `sample_action` exactly.
"""

from typing import NamedTuple, Protocol, runtime_checkable

from torch import Tensor


def scale_gradient(x: Tensor, scale: float) -> Tensor:
    """`x` unchanged forward; backward passes `scale` times its gradient (0: none). A value head reads its features
    through this, so that the critic's loss, large while it catches up after SFT, cannot wash out the features the
    policy learned by SFT."""
    if scale == 0:
        return x.detach()
    return x if scale == 1 else x.detach() + scale * (x - x.detach())


class PolicySample(NamedTuple):
    # (B, action_dim) normalised action, for the postprocessor; or (B, k, action_dim), k actions the env executes in
    # order before the policy looks again (an action chunk: PPO scores the k together as one choice)
    action: Tensor
    raw_action: Tensor  # (B, ...) passed back to evaluate_actions
    log_prob: Tensor  # (B,)
    value: Tensor  # (B,)


class ActionEvaluation(NamedTuple):
    log_prob: Tensor  # (B,)
    entropy: Tensor  # (B,)
    value: Tensor  # (B,)


@runtime_checkable
class ActorCritic(Protocol):
    def sample_action(self, batch: dict) -> PolicySample:
        """Draw an action from the policy's distribution, with its log-prob and the state value."""

    def evaluate_actions(self, batch: dict, raw_action: Tensor) -> ActionEvaluation:
        """Log-prob, entropy and value for actions drawn earlier by `sample_action`."""

    def predict_value(self, batch: dict) -> Tensor:
        """State value (B,)."""

    def select_action(self, batch: dict) -> Tensor:
        """Deterministic action (B, action_dim), for evaluation."""
