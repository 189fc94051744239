"""OpenVLA-7B (built natively on timm + transformers) with LoRA and a PPO value head, as the LeRobot policy type
`openvla`."""

from lerobot_policy_openvla.configuration_openvla import OpenVLAConfig
from lerobot_policy_openvla.modeling_openvla import OpenVLAPolicy
from lerobot_policy_openvla.processor_openvla import make_openvla_pre_post_processors

__all__ = ["OpenVLAConfig", "OpenVLAPolicy", "make_openvla_pre_post_processors"]
