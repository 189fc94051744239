"""Memory and speed of the OpenVLA policy: one SFT step and one PPO-style step (sample, then a forward/backward
of the clipped objective on the sampled tokens), LoRA r=32, 224 px, with and without gradient checkpointing.

On a GPU the default is the published 7B architecture with random weights (`random-7b`, nothing to download;
the same compute as openvla/openvla-7b) in bf16 at batch 8; on CPU the tiny preset in fp32.

    python scripts/benchmarks/benchmark_openvla.py [--base-model random-7b|tiny|openvla/openvla-7b] [--batch-size 8]
"""

import argparse
import resource
import time

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot_policy_openvla import OpenVLAConfig, OpenVLAPolicy

CAMERA = "observation.images.third_view"


def make_policy(base_model: str, device: str, image_size: int, gradient_checkpointing: bool) -> OpenVLAPolicy:
    config = OpenVLAConfig(
        device=device,
        base_model=base_model,
        gradient_checkpointing=gradient_checkpointing,
        input_features={CAMERA: PolicyFeature(FeatureType.VISUAL, (3, image_size, image_size))},
        output_features={"action": PolicyFeature(FeatureType.ACTION, (7,))},
    )
    return OpenVLAPolicy(config)


def sft_step(policy, optimizer, batch):
    loss, _ = policy.forward(batch)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()


def ppo_step(policy, optimizer, batch):
    with torch.no_grad():
        sample = policy.sample_action(batch)
    evaluation = policy.evaluate_actions(batch, sample.raw_action)
    advantage = torch.randn_like(sample.log_prob)
    ratio = (evaluation.log_prob - sample.log_prob).exp()
    policy_loss = -torch.min(ratio * advantage, ratio.clamp(0.8, 1.2) * advantage).mean()
    value_loss = (evaluation.value - torch.randn_like(evaluation.value)).pow(2).mean()
    optimizer.zero_grad(set_to_none=True)
    (policy_loss + value_loss).backward()
    optimizer.step()


def measure(step, policy, optimizer, batch, steps: int, device: str) -> tuple[float, float]:
    """(samples/s, peak GiB): GPU memory on CUDA, the process's peak resident memory on CPU."""
    step(policy, optimizer, batch)  # warm-up (allocator, kernels, optimiser state)
    if device.startswith("cuda"):
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    start = time.perf_counter()
    for _ in range(steps):
        step(policy, optimizer, batch)
    if device.startswith("cuda"):
        torch.cuda.synchronize()
        peak = torch.cuda.max_memory_allocated() / 2**30
    else:
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    return steps * len(batch["task"]) / (time.perf_counter() - start), peak


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    on_gpu = torch.cuda.is_available()
    parser.add_argument("--base-model", default="random-7b" if on_gpu else "tiny")
    parser.add_argument("--device", default="cuda" if on_gpu else "cpu")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--image-size", type=int, default=224)
    parser.add_argument("--steps", type=int, default=3)
    args = parser.parse_args()

    batch = {
        CAMERA: torch.rand(args.batch_size, 3, args.image_size, args.image_size, device=args.device),
        "task": ["pick up the red cube and place it in the plate"] * args.batch_size,
        "action": torch.rand(args.batch_size, 7, device=args.device) * 2 - 1,
    }
    print(f"OpenVLA {args.base_model} on {args.device}, batch {args.batch_size}, {args.image_size} px, LoRA r=32")
    print("| gradient checkpointing | step | samples/s | peak memory (GiB) |\n|---|---|---:|---:|")
    for checkpointing in (True, False):
        policy = make_policy(args.base_model, args.device, args.image_size, checkpointing)
        policy.train()
        optimizer = torch.optim.AdamW(policy.get_optim_params(), lr=1e-4)
        if checkpointing:
            trainable = sum(p.numel() for p in policy.parameters() if p.requires_grad)
            total = sum(p.numel() for p in policy.parameters())
            print(f"({trainable / 1e6:.1f}M trainable of {total / 1e6:.1f}M parameters)")
        for name, step in (("SFT", sft_step), ("PPO", ppo_step)):
            try:
                samples_per_s, peak = measure(step, policy, optimizer, batch, args.steps, args.device)
                print(f"| {checkpointing} | {name} | {samples_per_s:.2f} | {peak:.1f} |", flush=True)
            except torch.OutOfMemoryError:
                print(f"| {checkpointing} | {name} | out of memory | - |", flush=True)
                torch.cuda.empty_cache()
        del policy, optimizer
        if args.device.startswith("cuda"):
            torch.cuda.empty_cache()


if __name__ == "__main__":
    main()
