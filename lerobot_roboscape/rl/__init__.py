"""Reinforcement learning of policies in the roboscape envs (PPO); the contract a policy meets to be trained here is
`roboscape_core.actor_critic`."""
