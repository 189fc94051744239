from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig, RoboscapeWorldModelEnvConfig

__all__ = ["RoboscapeManiSkillEnvConfig", "RoboscapeWorldModelEnvConfig"]
