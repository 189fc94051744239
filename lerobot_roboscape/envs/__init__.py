from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig

__all__ = ["RoboscapeWorldModelEnvConfig"]
