"""Reinforcement learning of policies in the roboscape envs (PPO); the contract a policy meets to be trained here is
`lerobot_roboscape.rl.actor_critic`."""
