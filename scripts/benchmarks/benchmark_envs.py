"""Env steps/s of `roboscape_wm` (world models) against `roboscape_maniskill` (the simulator) at equal batch and
image size, and where a world-model step's time goes: next-frame generation (MaskGIT), decoding the frame to
pixels (tokenizer), the reward (similarity to the goal, done) and, with `--done-source=classifier`, the success
classifier on the decoded frames.

Uses the models and dataset of a pipeline run (`roboscape-demo`: tiny models; --demo-dir=outputs/bench: the bench
scale's 16x16-grid models). `--random-preset bench --frame-skips 1 4` instead times untrained models of a preset at
each frame skip k (speed does not depend on the weights), on the run's dataset, goals from its last frames: env
steps are control steps, and the model makes a frame every k of them.

    python scripts/benchmarks/benchmark_envs.py --batch-sizes 1 16 --steps 20
    python scripts/benchmarks/benchmark_envs.py --demo-dir outputs/bench [--done-source classifier]
    python scripts/benchmarks/benchmark_envs.py --random-preset bench --frame-skips 1 4 --batch-sizes 1 16 --steps 40 \
        --precisions float32 bfloat16 [--patches 1 2]
    # the world model alone (no simulator) from batch 1 up to the largest that fits, with peak GPU memory
    python scripts/benchmarks/benchmark_envs.py --random-preset paper --no-simulator --batch-sizes 1 16 64 128 256 \
        --precisions bfloat16

A batch whose key/value cache cannot fit the device's free memory is refused by `roboscape_wm` at construction
(its message is printed) and ends the sweep: the batches after it are larger.
"""

import argparse
import dataclasses
import functools
import itertools
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from lerobot_roboscape.envs.configs import PRECISIONS, RoboscapeManiSkillEnvConfig, RoboscapeWorldModelEnvConfig
from lerobot_roboscape.envs.world_model_env import RoboscapeWorldModelEnv
from lerobot_roboscape.tokenizer.configuration_tokenizer import TokenizerConfig
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from lerobot_roboscape.world_model.robot_state import UNIT_STATE_STATS
from lerobot_roboscape.world_model.rollout import Rollout
from roboscape_core.errors import InvalidInputError


class Timed:
    """Wraps a callable (or a method, when set on a class) and adds up the seconds spent in it."""

    def __init__(self, fn):
        self.fn, self.seconds = fn, 0.0

    def __get__(self, instance, owner=None):
        return self if instance is None else functools.partial(self, instance)

    def __call__(self, *args, **kwargs):
        start = time.perf_counter()
        out = self.fn(*args, **kwargs)
        self.seconds += time.perf_counter() - start
        return out


def steps_per_second(env, steps: int, timers: list[Timed] = ()) -> tuple[float, float]:
    """Env steps/s (episodes x steps / s) and the seconds of the measured steps (`timers` count only those)."""
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))  # warm-up
    for timer in timers:
        timer.seconds = 0.0
    start = time.perf_counter()
    for _ in range(steps):
        env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
    seconds = time.perf_counter() - start
    return env.num_envs * steps / seconds, seconds


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--demo-dir", type=Path, default=Path("outputs/demo"))
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 16])
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument(
        "--done-source",
        choices=["world_model", "classifier"],
        default="world_model",
        help="classifier: the success classifier of --demo-dir/reward_success decides done",
    )
    parser.add_argument("--random-preset", choices=["tiny", "bench", "paper"], help="untrained models of a preset")
    parser.add_argument("--frame-skips", type=int, nargs="+", default=[4], help="with --random-preset")
    parser.add_argument(
        "--patches", type=int, nargs="+", default=[None], help="with --random-preset: codes per position side"
    )
    parser.add_argument(
        "--precisions", nargs="+", default=["auto"], choices=PRECISIONS, help="roboscape_wm's precision"
    )
    parser.add_argument("--no-simulator", action="store_true", help="roboscape_wm alone, with its peak GPU memory")
    args = parser.parse_args()
    demo = args.demo_dir
    torch.manual_seed(0)
    if args.random_preset:
        for k, patch in itertools.product(args.frame_skips, args.patches):
            with tempfile.TemporaryDirectory() as tmp:
                codes = "the preset's" if patch is None else f"{patch}x{patch}"
                print(f"\n{args.random_preset} preset, untrained, frame_skip k = {k}, codes a position: {codes}")
                measure(args, random_models_config(demo, args.random_preset, k, Path(tmp), patch))
        return
    if not (demo / "world_model_action" / "pretrained_model").is_dir():
        raise SystemExit(f"no demo models under {demo}: run `roboscape-demo` first (or pass --demo-dir)")
    wm_config = RoboscapeWorldModelEnvConfig(
        dataset_repo_id="local/roboscape_demos",
        dataset_root=str(demo / "datasets" / "roboscape_demos"),
        tokenizer=str(demo / "tokenizer" / "pretrained_model"),
        action_world_model=str(demo / "world_model_action" / "pretrained_model"),
        text_world_model=str(demo / "world_model_text" / "pretrained_model"),
        allow_random_lpips=True,
        episode_length=10_000,
        max_goal_steps=20,
        theta=1.0,  # no episode ends mid-run
        done_source=args.done_source,
        success_classifier=str(demo / "reward_success" / "pretrained_model")
        if args.done_source == "classifier"
        else None,
    )
    measure(args, wm_config)


def random_models_config(
    demo: Path, preset: str, frame_skip: int, out: Path, patch: int | None = None
) -> RoboscapeWorldModelEnvConfig:
    """An env config on untrained models of `preset` at `frame_skip` (with patch x patch codes per position), saved
    under `out`, and the run's dataset."""
    tokenizer = VisualTokenizer(TokenizerConfig.get_choice_class(preset)())
    tokenizer.save_pretrained(out / "tokenizer")
    wm = WorldModelConfig.get_choice_class(preset)(
        frame_skip=frame_skip,
        **({} if patch is None else {"patch": patch}),
        tokens_per_side=tokenizer.config.tokens_per_side,
        vocab_size=tokenizer.config.codebook_size,
        action_mean=[0.0] * 7,
        action_std=[0.3] * 7,
        **UNIT_STATE_STATS,
    )
    STWorldModel(wm).save_pretrained(out / "action_world_model")
    return RoboscapeWorldModelEnvConfig(
        dataset_repo_id="local/roboscape_demos",
        dataset_root=str(demo / "datasets" / "roboscape_demos"),
        tokenizer=str(out / "tokenizer"),
        action_world_model=str(out / "action_world_model"),
        goal_source="dataset_last_frame",
        allow_random_lpips=True,
        episode_length=10_000,
        theta=1.0,
        image_size=tokenizer.config.image_size,
    )


def measure(args, wm_config: RoboscapeWorldModelEnvConfig) -> None:
    image_size = wm_config.image_size
    ms_config = RoboscapeManiSkillEnvConfig(image_size=image_size, episode_length=10_000)
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads, {image_size} px, 2 cameras, "
        f"{args.steps} steps per measurement"
    )
    simulator = not args.no_simulator
    cuda = torch.device(wm_config.resolved_device).type == "cuda"
    print(
        f"{'batch':>6} {'precision':>9} {'roboscape_wm steps/s':>21} {'generate':>9} {'decode':>7} {'reward':>7} "
        f"{'done':>7}" + (f" {'peak GiB':>9}" if cuda else "")
        + (f" {'roboscape_maniskill steps/s':>28} {'ratio':>7}" if simulator else "")
    )  # fmt: skip
    predict_next_frame = Rollout.predict_next_frame
    for batch, precision in itertools.product(args.batch_sizes, args.precisions):
        if cuda:
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats()
        try:
            wm = RoboscapeWorldModelEnv(dataclasses.replace(wm_config, precision=precision), num_envs=batch)
        except InvalidInputError as refusal:  # the cache cannot fit: nor can any larger batch
            print(f"{batch:>6} {precision:>9} {refusal}")
            break
        timers = {
            "generate": Timed(predict_next_frame),
            "decode": Timed(wm.decode),
            "reward": Timed(wm.reward_fn.forward),
            "done": Timed(wm.done_of),
        }
        Rollout.predict_next_frame, wm.decode, wm.reward_fn.forward, wm.done_of = timers.values()
        wm_rate, wm_seconds = steps_per_second(wm, args.steps, list(timers.values()))
        Rollout.predict_next_frame = predict_next_frame
        widths = (9, 7, 7, 7)  # of the generate, decode, reward and done columns
        shares = " ".join(f"{t.seconds / wm_seconds:>{w}.0%}" for t, w in zip(timers.values(), widths, strict=True))
        line = f"{batch:>6} {wm.precision:>9} {wm_rate:>21.1f} {shares}"
        if cuda:
            line += f" {torch.cuda.max_memory_allocated() / 2**30:>9.1f}"
        del wm
        if simulator:
            from lerobot_roboscape.envs.maniskill_env import RoboscapeManiSkillEnv  # ManiSkill: only when timed

            ms = RoboscapeManiSkillEnv(ms_config, num_envs=batch)
            ms_rate, _ = steps_per_second(ms, args.steps)
            ms.close()
            line += f" {ms_rate:>28.1f} {wm_rate / ms_rate:>6.1f}x"
        print(line, flush=True)


if __name__ == "__main__":
    main()
