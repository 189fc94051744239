"""The disagreement of an ensemble of action world models, model-based offline RL's guard against a policy that
games its model (issue 49): MOPO pays the reward minus lambda x the ensemble's disagreement; MOReL halts the episode
where the disagreement passes a threshold. Where the data reached, members trained apart agree; where a policy leads
the rollout off the data, they part, and it earns less there.

Every member follows the env's rollout: before each frame it predicts the frame from the same past frames and
actions (the logits of the all-masked frame, MaskGIT's first pass), then reads the frame the env's own model
generated. The disagreement of a frame is the ensemble's mutual information per token (BALD: the entropy of the
members' mean prediction minus their mean entropy), averaged over the frame's tokens, in nats: 0 when every model
predicts the same distribution, log M at most for M models.
"""

import torch

from lerobot_roboscape.world_model.rollout import Rollout


def mutual_information(logits: list[torch.Tensor]) -> torch.Tensor:
    """The models' disagreement (B,) from their logits, each (B, S, V): the mutual information between which model
    predicts and the token, averaged over the S tokens."""
    log_p = torch.stack([x.float().log_softmax(-1) for x in logits])  # (M, B, S, V)
    p = log_p.exp()
    mean = p.mean(0)
    entropy_of_mean = -(mean * mean.clamp_min(1e-30).log()).sum(-1)
    mean_entropy = -(p * log_p).sum(-1).mean(0)
    return (entropy_of_mean - mean_entropy).clamp_min(0).mean(-1)


class Ensemble:
    """Members (action world models beside the env's) that follow the env's rollout and say how much all of them
    disagree on each next frame."""

    def __init__(self, members: list):
        self.members, self.rollouts = members, []

    def start(self, first_B1S: torch.Tensor, states_B1D: torch.Tensor | None = None) -> None:
        """Every member reads the episodes' first frames (and states, for members with a state channel)."""
        B, A = first_B1S.shape[0], self.members[0].config.action_dim
        no_actions = torch.zeros(B, 0, A, device=first_B1S.device)
        self.rollouts = [
            Rollout.start(m, first_B1S, m.episode_control(no_actions), states=states_B1D) for m in self.members
        ]

    @torch.no_grad()
    def disagreement(self, rollout: Rollout, chunk_B1KA: torch.Tensor) -> torch.Tensor:
        """Disagreement (B,) of the env's model (its `rollout`) and the members on the next frame under the action
        chunk, before the env's model generates it."""
        logits = [r.next_frame_logits(r.model.encode_control(chunk_B1KA)) for r in [rollout, *self.rollouts]]
        return mutual_information(logits)

    @torch.no_grad()
    def observe(self, tokens_BS: torch.Tensor, chunk_B1KA: torch.Tensor, state_BD: torch.Tensor | None = None) -> None:
        """Every member reads the frame the env's model generated, under the same actions, with its state."""
        for r in self.rollouts:
            r.observe(tokens_BS[:, None], r.model.encode_control(chunk_B1KA), state_BD)
