"""The MLP baseline of RoboScape-R (paper Table 1, "MLP") as the LeRobot policy type `roboscape_mlp`."""

from lerobot_policy_roboscape_mlp.configuration_roboscape_mlp import RoboscapeMLPConfig
from lerobot_policy_roboscape_mlp.modeling_roboscape_mlp import RoboscapeMLPPolicy
from lerobot_policy_roboscape_mlp.processor_roboscape_mlp import make_roboscape_mlp_pre_post_processors

__all__ = ["RoboscapeMLPConfig", "RoboscapeMLPPolicy", "make_roboscape_mlp_pre_post_processors"]
