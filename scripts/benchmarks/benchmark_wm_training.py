"""Training throughput of the world model: clips/s and MFU of the training path, against today's, in one run.

Both run `training/loop.py: fit` on the same model and the same batches (a token cache of random codes in the bench
layout: two 16x16 views, 1024 codes, 7-D actions, episodes of 80 control steps), for a few steps after a warm-up:
- `today`: the path the GPU lease of docs/results/world_model/report.md ran: clips gathered on the host and copied
  each step (ClipSampler), fp32 (`--train.mixed_precision=no`), no TF32, no torch.compile, and the logs read every
  step (as the loss's `.item()` calls did, each a wait on the device);
- `new`: the token cache held on the device and the clips sliced there (ResidentClips), bf16 autocast, TF32,
  the blocks compiled (on a GPU), the logs read once at the end of the timed steps.
Fused AdamW runs on both sides on a GPU.

Clips/s are read from the run's own training log (output_dir/train_log.jsonl) between the first step (compilation)
and the last; MFU against the card's dense bf16 peak (training/throughput.py), with the model's FLOPs per
clip (STWorldModel.training_flops_per_clip: matmuls, attention included, the backward pass twice the forward).

    # on the 2 CPU cores: a smoke figure of the bench preset, a code or 2x2 codes per position
    python scripts/benchmarks/benchmark_wm_training.py --presets bench --patches 1 2 --batch-sizes 4 --steps 6
    # on the 2 CPU cores: the head on every position (weighted) against the masked positions only
    python scripts/benchmarks/benchmark_wm_training.py --paths today --masked-heads false true --steps 12
    # on a GPU: both presets over a batch sweep
    python scripts/benchmarks/benchmark_wm_training.py --presets bench gpu --batch-sizes 16 64 256 --steps 40
"""

import argparse
import itertools
import json
import tempfile
from pathlib import Path

import numpy as np
import torch
from accelerate.state import AcceleratorState

from lerobot_roboscape.tokenizer.token_cache import TokenCache
from lerobot_roboscape.training.loop import TRAIN_LOG, fit
from lerobot_roboscape.training.throughput import peak_flops
from lerobot_roboscape.world_model.clips import ClipSampler, ResidentClips
from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from lerobot_roboscape.world_model.robot_state import UNIT_STATE_STATS
from lerobot_roboscape.world_model.train import WorldModelTrainingConfig

PATHS = {
    "today": dict(resident=False, mixed_precision="no", tf32=False, compile=False, read_logs_every_step=True),
    "new": dict(resident=True, mixed_precision="bf16", tf32=True, compile=None, read_logs_every_step=False),
}


def random_token_cache(episodes: int, length: int, cameras: int = 2, side: int = 16, vocab: int = 1024) -> TokenCache:
    """A token cache of random codes in the bench layout: what training reads, without a dataset."""
    rng = np.random.default_rng(0)
    N = episodes * length
    rows = [
        {"episode_index": e, "start": e * length, "length": length, "task": "push the cube", "optimal": True}
        for e in range(episodes)
    ]
    return TokenCache(
        root=Path("random"),
        manifest={"vocab_size": vocab, "cameras": [f"view{i}" for i in range(cameras)], "tokens_per_side": side},
        tokens=rng.integers(0, vocab, (N, cameras, side, side), dtype=np.uint16),
        actions=rng.uniform(-1, 1, (N, 7)).astype(np.float32),
        states=rng.normal(size=(N, UNIT_STATE_STATS["state_dim"])).astype(np.float32),
        done=np.zeros(N, np.float32),
        rewards=np.zeros(N, np.float32),
        episodes=rows,
    )


def run(
    preset: str,
    patch: int | None,
    batch: int,
    path: str,
    steps: int,
    cache: TokenCache,
    device: torch.device,
    masked_head: bool | None = None,
) -> dict:
    settings = PATHS[path]
    patched = {} if patch is None else {"patch": patch}  # the preset's own by default, checked as any --wm.patch
    config = WorldModelConfig.get_choice_class(preset)(
        control="action",
        action_mean=[0.0] * 7,
        action_std=[1.0] * 7,
        masked_head=masked_head,
        **UNIT_STATE_STATS,
        **patched,
    )
    torch.manual_seed(0)
    model = STWorldModel(config)
    batches = ClipSampler(cache, cache.episodes, config.window, batch, seed=0, frame_skip=config.frame_skip)
    if settings["resident"]:
        batches = ResidentClips(batches, device)
    train = WorldModelTrainingConfig(
        steps=steps,
        batch_size=batch,
        warmup_steps=1,
        log_freq=1 if settings["read_logs_every_step"] else steps - 1,
        save_freq=10**9,
        mixed_precision=settings["mixed_precision"],
        tf32=settings["tf32"],
        compile=settings["compile"],
    )
    AcceleratorState._reset_state(reset_partial_state=True)  # each run picks its own precision
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)
    with tempfile.TemporaryDirectory() as out:
        try:
            fit(model, lambda m, b: m(b), batches, train, out, {}, desc=f"{preset} p{patch} {path} b{batch}",
                flops_per_sample=model.training_flops_per_clip())  # fmt: skip
        except torch.OutOfMemoryError:
            return {"error": "out of memory"}
        except RuntimeError as error:  # a kernel that refuses the shape: say which, go on with the sweep
            return {"error": str(error).splitlines()[0][:120]}
        lines = [json.loads(line) for line in (Path(out) / TRAIN_LOG).read_text().splitlines()]
    # From the first step (compilation) on: each logged line covers the steps since the one before.
    timed = [(b["step"] - a["step"], b["samples_per_s"]) for a, b in zip(lines, lines[1:], strict=False)]
    seconds = sum(n * batch / samples_per_s for n, samples_per_s in timed)
    clips_per_s = sum(n for n, _ in timed) * batch / seconds
    flops = clips_per_s * model.training_flops_per_clip()
    figures = {"clips_per_s": clips_per_s, "tflops": flops / 1e12}
    if peak := peak_flops(device, train.peak_tflops):
        figures["mfu"] = flops / peak
    if device.type == "cuda":
        figures["peak_gib"] = torch.cuda.max_memory_allocated(device) / 2**30
    return figures


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--presets", nargs="+", default=["bench"])
    parser.add_argument(
        "--patches", nargs="+", type=int, default=[None], help="codes per position side (default: the preset's)"
    )
    parser.add_argument("--batch-sizes", nargs="+", type=int, default=[4])
    parser.add_argument("--steps", type=int, default=6, help="steps per run; the first (compilation) is not timed")
    parser.add_argument("--episodes", type=int, default=64, help="episodes of the random token cache")
    parser.add_argument("--paths", nargs="+", default=list(PATHS), choices=list(PATHS))
    parser.add_argument(
        "--masked-heads",
        nargs="+",
        type=lambda v: {"null": None, "true": True, "false": False}[v.lower()],
        default=[None],
        help="--wm.masked_head values (null: by device)",
    )
    parser.add_argument("--json", type=Path, help="also write the figures here")
    args = parser.parse_args()
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    cache = random_token_cache(args.episodes, 80)
    print(f"device: {name}, torch {torch.__version__}; {args.steps} steps per run, the first not timed")
    print("| preset | patch | batch | masked head | path | clips/s | speed-up | MFU | TFLOP/s | GiB |")
    print("|---|---:|---:|---|---|---:|---:|---:|---:|---:|")
    rows = []
    for preset, patch, batch in itertools.product(args.presets, args.patches, args.batch_sizes):
        reference = None  # the first run of each (preset, patch, batch): the speed-ups are against it
        for masked_head, path in itertools.product(args.masked_heads, args.paths):
            figures = run(preset, patch, batch, path, args.steps, cache, device, masked_head)
            rows.append(
                {"preset": preset, "patch": patch, "batch": batch, "masked_head": masked_head, "path": path}
                | {"device": name, **figures}
            )
            reference = reference or figures

            def cell(key, fmt, figures=figures):
                return figures.get("error", "-") if key not in figures else format(figures[key], fmt)

            ok = "error" not in reference | figures
            ratio = f"{figures['clips_per_s'] / reference['clips_per_s']:.2f}x" if ok else "-"
            print(
                f"| {preset} | {patch} | {batch} | {masked_head} | {path} | {cell('clips_per_s', '.3g')} | {ratio} | "
                f"{cell('mfu', '.1%')} | {cell('tflops', '.3g')} | {cell('peak_gib', '.1f')} |",
                flush=True,
            )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
