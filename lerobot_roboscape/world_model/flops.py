"""The world model's FLOPs per training clip, for throughput and MFU: matmuls (2 per multiply-add), attention
included, counted from the config as nanoGPT's estimate_mfu counts them."""

from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig
from lerobot_roboscape.world_model.control_encoders import ACTION_TOKENS


def forward_flops_per_clip(c: WorldModelConfig, text_width: int | None = None) -> float:
    """Matmul FLOPs (2 per multiply-add) of the forward pass over one training clip of `window` frames, attention
    included, as nanoGPT's estimate_mfu counts them; a training step costs 3x (the backward pass twice the
    forward's). The frozen T5 is left out: its states are computed once per instruction. The output head is
    counted on every position, as where it reads them all (masked_head false); on the masked positions only it
    costs about half of that."""
    T, S, C, V = c.window, c.positions_per_frame, c.d_model, c.vocab_size
    L = ACTION_TOKENS if c.control == "action" else c.text_max_length
    L += S if c.anchor else 0  # the anchor frame's positions join the cross-attention's context
    per_token = 8 * C * C + 8 * C * C + 4 * C * C + 4 * c.mlp_ratio * C * C  # spatial, temporal, cross, MLP
    attention = T * 4 * S * S * C + S * 4 * T * T * C + T * 4 * S * L * C  # spatial, temporal, cross
    modulated = T if c.control == "action" else 1  # the text's pooled control is one per clip
    modulation = modulated * 24 * C * C if c.adaln != "none" else 0
    blocks = c.n_layer * (T * S * per_token + attention + T * 4 * C * C * L + modulation)  # + cross keys/values
    head = T * S * 2 * C * V * c.codes_per_position + T * 2 * (C * c.done_hidden + c.done_hidden)
    if c.state:  # the state's embedding in every frame, its head on every frame but the last (nothing follows)
        head += T * 2 * (c.state_dim * C + C * C)
        head += (T - 1) * 2 * ((2 * C + c.state_dim) * c.done_hidden + c.done_hidden * c.state_dim)
    if c.control == "action":
        control = T * 2 * (c.frame_skip * c.action_dim * C + C * ACTION_TOKENS * C)
    else:
        control = 2 * L * text_width * C  # the projection of the T5 states (text_width: T5's d_model)
    return float(blocks + head + control)
