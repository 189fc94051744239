"""Generation speed of the action world model: frames/s with the key/value cache against recomputing the window.

The reference is the paper code's way of generating: every MaskGIT step re-reads the whole window of past frames
(`use_cache=False` here, same model and weights). Both start from a full window (window - 1 prompt frames), so the
figures are the steady state of a long rollout.

    python scripts/benchmark_world_model.py                  # tiny preset at window 16 on CPU (and paper on a GPU)
    python scripts/benchmark_world_model.py --batch-sizes 1 16 64 --frames 8
"""

import argparse
import time

import torch

from lerobot_roboscape.world_model.configuration_world_model import PaperWorldModelConfig, TinyWorldModelConfig
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel


def frames_per_second(
    model: STWorldModel, batch: int, frames: int, use_cache: bool, device: str, dtype: torch.dtype
) -> float:
    cfg = model.config
    prompt_len = cfg.window - 1
    g = torch.Generator(device="cpu").manual_seed(0)
    prompt = torch.randint(0, cfg.vocab_size, (batch, prompt_len, cfg.tokens_per_frame), generator=g).to(device)
    actions = (torch.rand(batch, prompt_len + frames - 1, cfg.action_dim, generator=g) * 2 - 1).to(device)
    with torch.autocast(device_type=device, dtype=dtype, enabled=dtype != torch.float32):
        model.generate(prompt, 1, actions=actions[:, :prompt_len], use_cache=use_cache)  # warm-up
        if device == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        model.generate(prompt, frames, actions=actions, use_cache=use_cache)
        if device == "cuda":
            torch.cuda.synchronize()
    return batch * frames / (time.perf_counter() - start)


def run(name: str, cfg, device: str, dtype: torch.dtype, batch_sizes: list[int], frames: int) -> None:
    torch.manual_seed(0)
    model = STWorldModel(cfg).to(device).eval()
    params = sum(p.numel() for p in model.parameters()) / 1e6
    print(
        f"\n{name}: {params:.1f}M parameters, {cfg.n_layer} layers, d_model {cfg.d_model}, "
        f"{cfg.tokens_per_frame} tokens/frame, window {cfg.window}, {cfg.maskgit_steps} MaskGIT steps, "
        f"{device}, {str(dtype).removeprefix('torch.')}"
    )
    print(f"{'batch':>6} {'cached frames/s':>16} {'recompute frames/s':>19} {'speed-up':>9}")
    for batch in batch_sizes:
        cached = frames_per_second(model, batch, frames, True, device, dtype)
        recompute = frames_per_second(model, batch, frames, False, device, dtype)
        print(f"{batch:>6} {cached:>16.1f} {recompute:>19.1f} {cached / recompute:>8.1f}x")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 16, 64])
    parser.add_argument("--frames", type=int, default=8, help="generated frames per measurement")
    parser.add_argument("--window", type=int, default=16, help="window of the tiny preset (the paper's is 16)")
    parser.add_argument("--threads", type=int, default=None, help="CPU threads (default: torch's choice)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads")
    run("tiny preset", TinyWorldModelConfig(window=args.window), "cpu", torch.float32, args.batch_sizes, args.frames)
    if torch.cuda.is_available():
        print(f"GPU: {torch.cuda.get_device_name()}")
        run(
            "paper preset",
            PaperWorldModelConfig(text_encoder=None),
            "cuda",
            torch.bfloat16,
            args.batch_sizes,
            args.frames,
        )


if __name__ == "__main__":
    main()
