from lerobot_roboscape.dataset.writer import DATASET_FOLDERS, EPISODES_SIDECAR, read_episode_info, write_dataset

__all__ = ["DATASET_FOLDERS", "EPISODES_SIDECAR", "read_episode_info", "write_dataset"]
