"""Reinforcement learning of policies in the roboscape envs."""

from lerobot_roboscape.rl.actor_critic import ActionEvaluation, ActorCritic, PolicySample, scale_gradient

__all__ = ["ActionEvaluation", "ActorCritic", "PolicySample", "scale_gradient"]
