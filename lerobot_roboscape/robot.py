"""The robot's interface, as datasets record it, envs serve it and policies see it: its cameras, its state, its
actions and its control rate. Kept apart from the task suite (tasks/), which needs the simulator, so that what only
reads or writes this layout (datasets, the world-model env, the policies) imports without ManiSkill."""

# ManiSkill sensor uid -> camera name used in datasets and env observations.
CAMERA_NAMES: dict[str, str] = {"third_view": "third_view", "hand_camera": "wrist"}
# `observation.state`: joint positions (7 arm + 2 fingers), then the TCP pose (position, quaternion wxyz).
STATE_NAMES = (
    [f"joint_{i}" for i in range(7)]
    + ["finger_left", "finger_right"]
    + ["tcp_x", "tcp_y", "tcp_z", "tcp_qw", "tcp_qx", "tcp_qy", "tcp_qz"]
)
STATE_DIM = len(STATE_NAMES)
TCP_POSITION = slice(STATE_NAMES.index("tcp_x"), STATE_NAMES.index("tcp_z") + 1)  # metres, in `observation.state`
TCP_QUATERNION = slice(STATE_NAMES.index("tcp_qw"), STATE_NAMES.index("tcp_qz") + 1)  # q and -q: one orientation
# `action` of the pd_ee_delta_pose controller, each in [-1, 1]: position and rotation deltas, gripper.
ACTION_NAMES = ["dx", "dy", "dz", "drx", "dry", "drz", "gripper"]
CONTROL_FREQ = 20  # Hz, ManiSkill's tabletop default: the fps of datasets, envs and videos
