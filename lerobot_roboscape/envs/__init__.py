"""The LeRobot env types `roboscape_wm` and `roboscape_maniskill` (configs.py, registered by the plugin
`lerobot_env_roboscape`) and what they run on. The configs are read from here lazily: a simulator worker imports
`simulator_slots` without loading LeRobot's config stack (about 3 s of its start-up)."""

__all__ = ["RoboscapeManiSkillEnvConfig", "RoboscapeWorldModelEnvConfig"]


def __getattr__(name: str):
    if name in __all__:
        from lerobot_roboscape.envs import configs

        return getattr(configs, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
