"""What a generation holds at the end of its prompt's pass: the prompt's keys and values still referenced (with the
tensors they are views of) and the cache's rings, by the bytes of their storages, for a world-model preset.

The reference is the code before the cache was filled block by block: run the same script with that commit's
package first on the path, e.g.

    git worktree add /tmp/before da043e0
    PYTHONPATH=/tmp/before python scripts/benchmarks/benchmark_cache_memory.py --batch 1
    python scripts/benchmarks/benchmark_cache_memory.py --batch 1

It counts tensors, not an allocator: on a GPU the allocator's peak adds the pass's activations and fragmentation.
"""

import argparse

import torch

from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from lerobot_roboscape.world_model.robot_state import UNIT_STATE_STATS
from lerobot_roboscape.world_model.st_transformer import KVCache


def storage_bytes(tensors) -> int:
    """Bytes of the distinct storages behind `tensors` (a view keeps its whole base alive)."""
    return sum({t.untyped_storage().data_ptr(): t.untyped_storage().nbytes() for t in tensors}.values())


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="paper")
    parser.add_argument("--batch", type=int, default=1)
    args = parser.parse_args()
    torch.manual_seed(0)
    cfg = WorldModelConfig.get_choice_class(args.preset)(
        control="action", text_encoder=None, action_mean=[0.0] * 7, action_std=[1.0] * 7, **UNIT_STATE_STATS
    )
    model = STWorldModel(cfg).eval()
    device = "cuda" if torch.cuda.is_available() else "cpu"
    model.to(device)
    frames = cfg.window - 1  # a full prompt
    tokens = torch.randint(0, cfg.vocab_size, (args.batch, frames, cfg.tokens_per_frame), device=device)
    actions = torch.zeros(args.batch, (frames - 1) * cfg.frame_skip, cfg.action_dim, device=device)
    states = torch.zeros(args.batch, frames, cfg.state_dim, device=device)
    with torch.no_grad(), torch.autocast(torch.device(device).type, torch.bfloat16):
        control = model.episode_control(actions)
        if "fill" in STWorldModel.compute_hidden.__code__.co_varnames:  # filled block by block
            cache = KVCache(cfg.n_layer, cfg.window)
            model.compute_hidden(tokens, control, fill=cache, states=states)
            held = 0
        else:  # every layer's prompt keys and values returned, then copied into the rings
            _, kvs = model.compute_hidden(tokens, control, states=states)
            held = storage_bytes([t for kv in kvs for t in kv])
            cache = KVCache(kvs, cfg.window)
    rings = storage_bytes([t for ring in cache.layers for t in (ring.k, ring.v)])
    print(
        f"{args.preset} preset, {cfg.tokens_per_frame} tokens a frame, batch {args.batch}, {frames} prompt frames, "
        f"{device}: prompt keys/values held {held / 2**30:.3f} GiB + rings {rings / 2**30:.3f} GiB "
        f"({cache.layers[0].k.dtype}) = {(held + rings) / 2**30:.3f} GiB at the end of the prompt's pass"
    )


if __name__ == "__main__":
    main()
