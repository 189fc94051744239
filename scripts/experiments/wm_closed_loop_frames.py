"""What the world model shows a policy in closed loop, and what each refitted done head reads there (issue 100).

A done-refresh run (`ppo_sim_levers.py --protocol scene --lever std_kl_refresh`) refits the done head 3 times; its
heads fired in 0%, 50-81% and 0-6% of PPO's world-model episodes by slice. This plays one of the run's checkpoints
in `roboscape_wm` (its first refit's model: the refits change the done head only, never generation) on the
scene's 16 starts, reads every round's head on each generated frame, and draws the episodes' frames over time and
their last frames titled by each head's highest done.

    python scripts/experiments/wm_closed_loop_frames.py \
        outputs/ppo_wm_scene/std_kl_refresh_seed0 17 docs/results/ppo_wm_scene
"""

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import matplotlib
import numpy as np
import torch

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
import ppo_sim_levers as levers  # noqa: E402

from lerobot_roboscape.envs.world_model_env import RoboscapeWorldModelEnv  # noqa: E402
from lerobot_roboscape.experiments.done_refresh import REFRESH_DIR  # noqa: E402
from lerobot_roboscape.rl.policy_loading import PolicyIO, load_policy  # noqa: E402
from lerobot_roboscape.training.checkpoints import CHECKPOINTS, FINAL  # noqa: E402
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel  # noqa: E402

EPISODES = 16  # the scene's starts
SHOWN = [0, 3, 8, 11]  # the episodes drawn over time: two of each family


@torch.no_grad()
def play(run: Path, checkpoint: int) -> tuple[list[np.ndarray], dict[int, np.ndarray], list[str]]:
    """The third view of every generated frame (each (B, H, W, 3)), each round's highest done per episode, tasks."""
    rounds = sorted(int(p.name.split("_")[1]) for p in (run / REFRESH_DIR).glob("round_*"))
    heads = {r: STWorldModel.from_pretrained(str(run / REFRESH_DIR / f"round_{r}" / FINAL)).done_head for r in rounds}
    model = (run / REFRESH_DIR / f"round_{rounds[0]}" / FINAL).resolve()
    env = RoboscapeWorldModelEnv(
        replace(levers.env_config("scene", 1), action_world_model=str(model), device="cpu"), num_envs=EPISODES
    )
    policy, preprocessor, postprocessor = load_policy(run / CHECKPOINTS / f"{checkpoint:08d}" / FINAL, "cpu")
    policy.eval()
    io = PolicyIO(preprocessor, postprocessor)
    observation, _ = env.reset(seed=0)
    policy.reset()
    tasks = list(env.tasks())
    frames, highest = [observation["pixels"]["third_view"].copy()], {r: np.zeros(EPISODES) for r in heads}
    for _ in range(levers.HORIZON):
        action = io.env_action(policy.select_action(io.batch(observation["pixels"], tasks)))
        observation, *_ = env.step(action)
        if env._substep == 0:  # a frame was generated: the head's input is the rollout's pooled features
            features = env._rollout.features.float()
            for r, head in heads.items():
                highest[r] = np.maximum(highest[r], torch.sigmoid(head(features).squeeze(-1)).numpy())
            frames.append(observation["pixels"]["third_view"].copy())
    env.close()
    return frames, highest, tasks


def draw(frames, highest, tasks, out: Path, checkpoint: int) -> None:
    fig, axes = plt.subplots(2, EPISODES // 2, figsize=(16, 4.6))
    for i, ax in enumerate(axes.flat):
        ax.imshow(frames[-1][i])
        ax.axis("off")
        heads = " ".join(f"r{r} {h[i]:.2f}" for r, h in highest.items())
        ax.set_title(f"{tasks[i][:18]}\n{heads}", fontsize=6)
    fig.suptitle(f"checkpoint {checkpoint}: last generated frame, each refit's highest done", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "closed_loop_last_frames.png", dpi=100)
    times = range(0, len(frames), 4)
    fig, axes = plt.subplots(len(SHOWN), len(times), figsize=(11, 6.6))
    for row, i in zip(axes, SHOWN, strict=True):
        for ax, t in zip(row, times, strict=True):
            ax.imshow(frames[t][i])
            ax.axis("off")
            ax.set_title(f"{tasks[i][:16]} frame {t}", fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "closed_loop_frames.png", dpi=100)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("checkpoint", type=int)
    parser.add_argument("out", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(2)
    frames, highest, tasks = play(args.run, args.checkpoint)
    args.out.mkdir(parents=True, exist_ok=True)
    draw(frames, highest, tasks, args.out, args.checkpoint)
    for r, h in highest.items():
        print(
            f"round {r} head: fires (>= {levers.THETA:.3f}) in {np.mean(h >= levers.THETA):.0%} of {EPISODES} "
            f"episodes; highest done quartiles {np.quantile(h, [0.25, 0.5, 0.75]).round(3).tolist()}"
        )


if __name__ == "__main__":
    main()
