"""Generation speed of the action world model: frames/s of `STWorldModel.generate` with its key/value cache, against
the paper code's way of generating (every MaskGIT step re-reads the whole window of past frames).

Two references, measured in the same run as ours:
- `recompute`: our model with `use_cache=False` (same weights, same work as the paper code's loop);
- `paper code`: 1xgpt's `STMaskGIT.generate` itself, the code base RoboScape-R builds on, when `--paper-code` points
  at a checkout of https://github.com/1x-technologies/1xgpt. It is built with the same layers, heads, width, grid
  and window, and run on its CPU path (`XFORMERS_DISABLED=true`: its plain attention). Its imports of xformers and
  mup are satisfied by empty modules, since neither is called on that path.

Each starts from a full window (window - 1 prompt frames for ours) and the rate is that of the frames after the first
(`marginal_rate`): the steady state of a long rollout, without the one-time reading of the prompt.

On a GPU the paper preset runs with one 16 x 16 view (1xgpt needs a square grid; `--views 2`: the env's frame, ours
alone), ours also replayed as CUDA graphs (`captured`), over the batches given and, with `max` among them, the largest
that fits (doubling until out of memory), each with its peak GPU memory; above batch 64 ours alone (the references
would take minutes a batch). `--memory-snapshot FILE` records one cached generation at the first batch (PyTorch's
memory snapshot, for https://pytorch.org/memory_viz) and prints what it held: weights, the key/value cache
(`cache_bytes`) and the rest.

    # the tiny preset at window 16 on CPU (and the paper preset on a GPU)
    python scripts/benchmarks/benchmark_world_model.py
    python scripts/benchmarks/benchmark_world_model.py --paper-code ~/1xgpt --batch-sizes 1 16 --config \
        '{"n_layer": 4, "n_head": 4, "d_model": 256, "n_cameras": 1, "tokens_per_side": 16, "window": 16}'
    # on a GPU: the race at the paper preset, one view
    python scripts/benchmarks/benchmark_world_model.py --paper-code ~/1xgpt --batch-sizes 1 16 64 max
"""

import argparse
import json
import os
import sys
import time
import types
from functools import partial
from pathlib import Path

import torch

from lerobot_roboscape.world_model.configuration_world_model import (
    PaperWorldModelConfig,
    TinyWorldModelConfig,
    WorldModelConfig,
)
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel

REFERENCE_MAX_BATCH = 64  # above it, ours alone


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def marginal_rate(generate, batch: int, frames: int, device: str, repeats: int = 3) -> float:
    """Frames/s of the frames after the first: (batch x frames) / (time of 1 + frames frames - time of 1 frame),
    each time the fastest of `repeats` (the slow references run once: their steps are long enough). What a
    generation costs once (reading the prompt, building the cache) cancels out: the steady state of a long rollout."""
    seconds = []
    for n in (1, 1 + frames):
        best = float("inf")
        for _ in range(repeats):
            _sync(device)
            start = time.perf_counter()
            generate(n)
            _sync(device)
            best = min(best, time.perf_counter() - start)
        seconds.append(best)
    return batch * frames / (seconds[1] - seconds[0])


def frames_per_second(
    model: STWorldModel, batch: int, frames: int, use_cache: bool, device: str, dtype, capture: bool = False
) -> float:
    cfg = model.config
    prompt_len = cfg.window - 1
    g = torch.Generator(device="cpu").manual_seed(0)
    prompt = torch.randint(0, cfg.vocab_size, (batch, prompt_len, cfg.tokens_per_frame), generator=g).to(device)
    k = cfg.frame_skip  # actions per frame
    actions = (torch.rand(batch, (prompt_len + frames) * k, cfg.action_dim, generator=g) * 2 - 1).to(device)
    states = torch.randn(batch, prompt_len, cfg.state_dim, generator=g).to(device) if cfg.state else None

    def generate(n: int):
        actions_n = actions[:, : (prompt_len + n - 1) * k]
        model.generate(prompt, n, actions=actions_n, use_cache=use_cache, capture=capture, states=states)

    with torch.autocast(device_type=device, dtype=dtype, enabled=dtype != torch.float32):
        generate(1)  # warm-up
        return marginal_rate(generate, batch, frames, device, repeats=3 if use_cache else 1)


def peak_gib(device: str) -> float | None:
    return torch.cuda.max_memory_allocated() / 2**30 if device == "cuda" else None


def largest_batch(model: STWorldModel, start: int, frames: int, device: str, dtype) -> int:
    """The largest batch, doubling from `start`, whose cached generation runs without running out of memory."""
    batch = start
    while True:
        try:
            frames_per_second(model, batch * 2, 1, True, device, dtype)
        except torch.OutOfMemoryError:
            torch.cuda.empty_cache()
            return batch
        batch *= 2


def memory_snapshot(model: STWorldModel, batch: int, frames: int, dtype, path: Path) -> None:
    """One cached generation at `batch` recorded by PyTorch's allocator history; prints weights, the cache's bytes
    as `cache_bytes` counts them and the peak, in GiB."""
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats()
    weights = sum(p.numel() * p.element_size() for p in model.parameters())
    torch.cuda.memory._record_memory_history(max_entries=200_000)
    frames_per_second(model, batch, frames, True, "cuda", dtype)
    torch.cuda.memory._dump_snapshot(str(path))
    torch.cuda.memory._record_memory_history(enabled=None)
    peak, cache = torch.cuda.max_memory_allocated(), model.cache_bytes(batch, dtype)
    print(
        f"memory at batch {batch}: peak {peak / 2**30:.2f} GiB = weights {weights / 2**30:.2f} + key/value cache "
        f"{cache / 2**30:.2f} + the rest {(peak - weights - cache) / 2**30:.2f} (snapshot: {path})"
    )


def load_paper_code(checkout: Path):
    """1xgpt's STMaskGIT from a checkout, on its xformers-free path."""
    os.environ["XFORMERS_DISABLED"] = "true"
    for name in ("xformers", "xformers.ops", "mup"):
        sys.modules.setdefault(name, types.ModuleType(name))
    ops, mup = sys.modules["xformers.ops"], sys.modules["mup"]
    ops.LowerTriangularMask = ops.memory_efficient_attention = ops.unbind = None
    mup.MuReadout = torch.nn.Linear
    sys.path.insert(0, str(checkout))
    from genie.config import GenieConfig
    from genie.st_mask_git import STMaskGIT

    return GenieConfig, STMaskGIT


def paper_frames_per_second(paper, cfg: WorldModelConfig, batch: int, frames: int, device: str, dtype) -> float:
    """1xgpt generates into a fixed window of T frames: T - n prompt frames, then n new ones, each MaskGIT step
    computing all T."""
    GenieConfig, STMaskGIT = paper
    genie = GenieConfig(
        num_layers=cfg.n_layer,
        num_heads=cfg.n_head,
        d_model=cfg.d_model,
        T=cfg.window,
        S=cfg.tokens_per_frame,
        image_vocab_size=cfg.vocab_size,
        qk_norm=False,  # as its published config (genie/configs/magvit_n32_h8_d256.json)
        mlp_ratio=cfg.mlp_ratio,
    )
    torch.manual_seed(0)
    model = STMaskGIT(genie).to(device).eval()
    model.init_weights()
    if frames + 1 >= cfg.window:
        raise SystemExit(f"--frames must be below window - 1 = {cfg.window - 1} for the paper code's fixed window")

    def generate(n: int):
        prompt = torch.randint(0, cfg.vocab_size, (batch, (cfg.window - n) * cfg.tokens_per_frame))
        model.generate(
            prompt.to(device), None, max_new_tokens=n * cfg.tokens_per_frame, maskgit_steps=cfg.maskgit_steps
        )

    with torch.no_grad(), torch.autocast(device_type=device, dtype=dtype, enabled=dtype != torch.float32):
        generate(1)  # warm-up
        return marginal_rate(generate, batch, frames, device, repeats=1)


def run(
    name: str, cfg, device: str, dtype, batch_sizes: list[str], frames: int, paper=None, snapshot: Path | None = None
) -> None:
    torch.manual_seed(0)
    model = STWorldModel(cfg).to(device).eval()
    params = sum(p.numel() for p in model.parameters()) / 1e6
    print(
        f"\n{name}: {params:.1f}M parameters, {cfg.n_layer} layers, {cfg.n_head} heads, d_model {cfg.d_model}, "
        f"{cfg.tokens_per_frame} tokens/frame, vocabulary {cfg.vocab_size}, window {cfg.window}, "
        f"{cfg.maskgit_steps} MaskGIT steps, greedy, {device}, {str(dtype).removeprefix('torch.')}"
    )
    gpu = device == "cuda"
    if snapshot is not None and gpu:
        memory_snapshot(model, int(batch_sizes[0]), frames, dtype, snapshot)
    header = f"{'batch':>6} {'ours frames/s':>14}"
    header += f" {'captured':>9} {'peak GiB':>9}" if gpu else ""
    header += f" {'recompute frames/s':>19} {'speed-up':>9}"
    if paper:
        header += f" {'paper code frames/s':>20} {'speed-up':>9}"
    print(header)
    batches = [int(b) for b in batch_sizes if b != "max"]
    if "max" in batch_sizes:
        batches.append(largest_batch(model, max(batches, default=1), frames, device, dtype))
    for batch in batches:
        if gpu:
            torch.cuda.reset_peak_memory_stats()
        ours = frames_per_second(model, batch, frames, True, device, dtype)
        best = ours
        line = f"{batch:>6} {ours:>14.2f}"
        if gpu:
            peak = peak_gib(device)
            best = max(ours, captured := frames_per_second(model, batch, frames, True, device, dtype, capture=True))
            line += f" {captured:>9.2f} {peak:>9.2f}"
        if batch > REFERENCE_MAX_BATCH:  # the references recompute the window: minutes a batch up there
            print(line, flush=True)
            continue
        line += reference_columns(partial(frames_per_second, model, batch, frames, False, device, dtype), best, 19)
        if paper:
            paper_code = partial(paper_frames_per_second, paper, cfg, batch, frames, device, dtype)
            line += reference_columns(paper_code, best, 20)
        print(line, flush=True)


def reference_columns(measure, best: float, width: int) -> str:
    """A reference's frames/s and our speed-up over it; "OOM" where the reference does not fit the GPU at this batch
    (it recomputes the whole window: more memory than ours), so the rows after it are still measured."""
    try:
        reference = measure()
    except torch.OutOfMemoryError:
        torch.cuda.empty_cache()
        return f" {'OOM':>{width}} {'':>9}"
    return f" {reference:>{width}.2f} {best / reference:>8.1f}x"


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--batch-sizes", nargs="+", default=["1", "16", "64"], help="batches; `max`: the largest that fits (GPU)"
    )
    parser.add_argument("--frames", type=int, default=8, help="generated frames per measurement")
    parser.add_argument(
        "--config", type=json.loads, default=None, help="WorldModelConfig fields as JSON (default: the tiny preset)"
    )
    parser.add_argument("--window", type=int, default=16, help="window of the tiny preset (the paper's is 16)")
    parser.add_argument("--paper-code", type=Path, default=None, help="a checkout of 1xgpt, measured beside ours")
    parser.add_argument("--threads", type=int, default=None, help="CPU threads (default: torch's choice)")
    parser.add_argument("--memory-snapshot", type=Path, default=None, help="GPU: record one generation's memory")
    parser.add_argument("--gpu-only", action="store_true", help="skip the CPU figures")
    parser.add_argument("--views", type=int, default=1, help="GPU: camera views of the paper preset's frame")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    paper = load_paper_code(args.paper_code) if args.paper_code else None
    print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads")
    if not args.gpu_only:
        cpu_cfg = WorldModelConfig(**args.config) if args.config else TinyWorldModelConfig(window=args.window)
        cpu_batches = [b for b in args.batch_sizes if b != "max"]
        run("config" if args.config else "tiny preset", cpu_cfg, "cpu", torch.float32, cpu_batches, args.frames, paper)
    if torch.cuda.is_available():
        print(f"GPU: {torch.cuda.get_device_name()}")
        # One 16 x 16 view: the grid 1xgpt can build; --views 2, the env's frame, races ours alone.
        gpu_cfg = PaperWorldModelConfig(text_encoder=None, n_cameras=args.views)
        run(
            f"paper preset, {args.views} view(s)",
            gpu_cfg,
            "cuda",
            torch.bfloat16,
            args.batch_sizes,
            args.frames,
            paper if args.views == 1 else None,
            args.memory_snapshot,
        )


if __name__ == "__main__":
    main()
