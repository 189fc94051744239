"""Imported by LeRobot at start-up; registering the env configs is all it does."""

import lerobot_roboscape.envs.configs  # noqa: F401
