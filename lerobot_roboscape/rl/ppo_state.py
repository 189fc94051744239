"""What a PPO run carries from one iteration to the next and across a kill: the running statistics of the
discounted return that scale its rewards, and its checkpoints (the policy with its processors, the optimizer, the
iteration and PPO's clock)."""

import json
import math
from pathlib import Path

import draccus
import numpy as np
import torch
from lerobot.optim.optimizers import save_optimizer_state
from torch import Tensor

from lerobot_roboscape.rl.configuration_ppo import PPOConfig
from lerobot_roboscape.rl.policy_loading import PolicyIO
from lerobot_roboscape.training.checkpoints import FINAL, PPO_CONFIG_JSON, begin_checkpoint, publish_checkpoint

CLOCK_JSON = "clock.json"


class RunningReturnStats:
    """Running mean and variance of the discounted return (Chan et al.'s parallel update, as gymnasium's
    NormalizeReward). Its state is checkpointed, so a resumed run scales rewards as an uninterrupted one. Under
    `accelerate launch` each process keeps its own, from its share of the envs (the checkpoint holds the main
    process's)."""

    def __init__(self, mean: float = 0.0, var: float = 1.0, count: float = 1e-4):
        self.mean, self.var, self.count = mean, var, count

    def update(self, values: np.ndarray) -> None:
        batch_mean, batch_var, batch_count = float(values.mean()), float(values.var()), len(values)
        delta, total = batch_mean - self.mean, self.count + batch_count
        m2 = self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / total
        self.mean, self.var, self.count = self.mean + delta * batch_count / total, m2 / total, total

    def scale_rewards(self, rewards: Tensor, alive: Tensor, gamma: float) -> Tensor:
        """Update with the discounted returns accumulated along this rollout (T, B), then divide its rewards by
        their standard deviation."""
        returns = torch.zeros_like(rewards, dtype=torch.float64)
        running = torch.zeros_like(returns[0])
        for t in range(len(rewards)):
            running = gamma * running + rewards[t]
            returns[t] = running
        self.update(returns[alive].cpu().numpy())
        return rewards / math.sqrt(self.var + 1e-8)

    def state_dict(self) -> dict:
        return {"mean": self.mean, "var": self.var, "count": self.count}


def save_checkpoint(
    output_dir: Path,
    iteration: int,
    policy,
    io: PolicyIO,
    optimizer,
    cfg: PPOConfig,
    return_stats: RunningReturnStats,
    reward: str,
    seconds: float,
) -> Path:
    """checkpoints/NNNNNNNN/{pretrained_model (policy + processors, loadable by lerobot-eval), training_state,
    ppo_config.json, reward.txt (the reward it was trained on, its similarity resolved)}, written to a temporary
    folder and moved into place; `checkpoints/last` names the newest (lerobot_roboscape.training.checkpoints)."""
    tmp = begin_checkpoint(output_dir, iteration)
    policy.save_pretrained(tmp / FINAL)
    io.preprocessor.save_pretrained(tmp / FINAL)
    io.postprocessor.save_pretrained(tmp / FINAL)
    (tmp / "training_state").mkdir()
    save_optimizer_state(optimizer, tmp / "training_state")
    # json writes floats by repr, which reads back bit for bit.
    state = {"iteration": iteration, "return_stats": return_stats.state_dict()}
    (tmp / "training_state" / "iteration.json").write_text(json.dumps(state))
    # Wall-clock apart from the state, which is the same bytes in every run with the same flags.
    (tmp / "training_state" / CLOCK_JSON).write_text(json.dumps({"seconds": seconds}))
    with draccus.config_type("json"):
        draccus.dump(cfg, (tmp / PPO_CONFIG_JSON).open("w"), indent=2)
    (tmp / "reward.txt").write_text(reward + "\n")
    return publish_checkpoint(output_dir, iteration, tmp)


def load_checkpoint(checkpoint: Path) -> tuple[int, RunningReturnStats, float]:
    """What `save_checkpoint` wrote that a resumed run continues from: (its iteration, the running return
    statistics, the seconds of PPO so far). The policy loads from checkpoint/pretrained_model, the optimizer state
    from checkpoint/training_state."""
    state = json.loads((checkpoint / "training_state" / "iteration.json").read_text())
    return state["iteration"], RunningReturnStats(**state["return_stats"]), checkpoint_seconds(checkpoint)


def checkpoint_seconds(checkpoint: Path) -> float:
    """Seconds of PPO's clock (rollouts and updates) when `checkpoint` was saved."""
    return json.loads((Path(checkpoint) / "training_state" / CLOCK_JSON).read_text())["seconds"]


def trained_world_model(pretrained_model: Path) -> str | None:
    """The action model a roboscape-ppo checkpoint last trained in (a lever such as the done refresh swaps it
    during the run), or None where its flags name none (PPO in the simulator, SFT)."""
    saved = Path(pretrained_model).parent / PPO_CONFIG_JSON
    if not saved.is_file():
        return None
    return json.loads(saved.read_text())["env"].get("action_world_model")
