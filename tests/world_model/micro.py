"""A micro world model (both controls, every variant of its control path) and random clips for it: the model tests' one
size."""

import torch

from lerobot_roboscape.world_model.configuration_world_model import TinyWorldModelConfig
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel

MICRO = dict(
    n_cameras=2,
    tokens_per_side=2,
    vocab_size=16,
    d_model=32,
    n_head=2,
    n_layer=2,
    window=4,
    prompt_frames=1,
    done_hidden=32,
    frame_skip=1,
    state_dim=3,
    state_mean=[0.2] * 3,
    state_std=[0.5] * 3,
)


TASKS = ["push the red cube forward", "pull the red cube back"]


STATS = dict(action_mean=[0.1] * 7, action_std=[0.3] * 7)


CONTROL_PATH = dict(adaln="one_plus", normalize_control=True, control_dropout=0.1, guidance_scale=2.0)


VARIANTS = [
    ("action", {"adaln": "none"}),
    ("action", {}),
    ("action", CONTROL_PATH),
    ("action", {"patch": 2, "maskgit_steps": 2}),
    ("text", {"adaln": "none"}),
    ("text", CONTROL_PATH),
    ("text", {"patch": 2}),
    ("action", {"anchor": True, "patch": 2}),
    ("text", {"anchor": True, **CONTROL_PATH}),
]


def make_model(control="action", **overrides):
    torch.manual_seed(0)
    stats = STATS if control == "action" else {}
    model = STWorldModel(TinyWorldModelConfig(control=control, **{**MICRO, **stats, **overrides})).eval()
    for name, param in model.named_parameters():  # zero-initialised control paths, made to act
        if "modulation" in name or name == "control_encoder.null":
            torch.nn.init.normal_(param, std=0.05)
    return model


def random_batch(B=2, T=4, S=8, V=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {
        "tokens": torch.randint(0, V, (B, T, S), generator=g),
        "done": (torch.rand(B, T, generator=g) > 0.5).float(),
        "actions": torch.rand(B, T, 1, 7, generator=g) * 2 - 1,  # frame t: the k = 1 action that led to it
        "no_action": torch.zeros(B, T, dtype=torch.bool),
        "state": torch.randn(B, T, 3, generator=g),
        "task": TASKS[:B],
    }


def control_kwargs(model, batch, n):
    """What generation from the batch's first frame reads besides it: its state, and its controls."""
    if model.config.control == "action":  # generation takes one action per control step
        return {"actions": batch["actions"][:, :n, 0], "states": batch["state"][:, :1]}
    return {"instructions": batch["task"], "states": batch["state"][:, :1]}
