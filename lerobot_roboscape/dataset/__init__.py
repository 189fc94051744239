from lerobot_roboscape.dataset.writer import EPISODES_SIDECAR, read_episode_info, write_dataset

__all__ = ["EPISODES_SIDECAR", "read_episode_info", "write_dataset"]
