"""Run inside a virtual environment holding one policy plugin and what it declares, nothing of lerobot-roboscape:
build the plugin's tiny preset (gradient checkpointing on where the policy has it), take one SFT step and draw one
PPO sample. Usage: python plugin_alone.py {openvla,roboscape_mlp}"""

import importlib.util
import sys

import torch
from lerobot.configs.types import FeatureType, PolicyFeature

IMAGE_SIZE = 64
CAMERA = "observation.images.third_view"

absent = [name for name in ("mani_skill", "sapien", "lerobot_roboscape") if importlib.util.find_spec(name)]
assert not absent, f"the clean environment holds {absent}"

plugin = sys.argv[1]
features = {CAMERA: PolicyFeature(FeatureType.VISUAL, (3, IMAGE_SIZE, IMAGE_SIZE))}
action = {"action": PolicyFeature(FeatureType.ACTION, (7,))}
if plugin == "openvla":
    from lerobot_policy_openvla import OpenVLAConfig, OpenVLAPolicy

    config = OpenVLAConfig(
        device="cpu", base_model="tiny", gradient_checkpointing=True, input_features=features, output_features=action
    )
    policy = OpenVLAPolicy(config)
else:
    from lerobot_policy_roboscape_mlp import RoboscapeMLPConfig, RoboscapeMLPPolicy

    config = RoboscapeMLPConfig(device="cpu", hidden_dim=32, input_features=features, output_features=action)
    policy = RoboscapeMLPPolicy(config)

torch.manual_seed(0)
batch = {
    CAMERA: torch.rand(2, 3, IMAGE_SIZE, IMAGE_SIZE),
    "task": ["push the can forward", "pull the mug back"],
    "action": torch.rand(2, config.chunk_size if plugin == "roboscape_mlp" else 1, 7).squeeze(1) * 2 - 1,
}
policy.train()
loss, _ = policy.forward(batch)
loss.backward()
assert torch.isfinite(loss), loss
assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in policy.parameters() if p.requires_grad)
policy.eval()
with torch.no_grad():
    sample = policy.sample_action(batch)
assert torch.isfinite(sample.log_prob).all() and sample.value.shape == (2,)
print(f"{plugin}: SFT loss {loss.item():.3f}, PPO sample log-prob {sample.log_prob.tolist()}")
