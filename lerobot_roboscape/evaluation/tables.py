"""The paper's tables: success rates of each policy after SFT, after PPO in ManiSkill and after PPO in the world
model, IND and OOD, per task family (Table 1: one RL run per family; Table 2: one multi-task run), printed as
markdown and drawn as a bar chart. `scripts/reproduce_tables.py` and `roboscape-demo` run it."""

import json
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib
import numpy as np

from lerobot_roboscape.dataset.reader import open_dataset, successful_episodes
from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig, RoboscapeWorldModelEnvConfig
from lerobot_roboscape.evaluation.success_rate import EvalConfig, evaluate_success
from lerobot_roboscape.rl.ppo import PPOConfig, train_ppo
from lerobot_roboscape.tasks import TASK_FAMILIES

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

SFT, RL_MANISKILL, RL_WORLD_MODEL = "Supervised finetune", "RL w. ManiSkill", "RL w. World Model"
SHORT = {"pick_place": "P.&P.", "push": "Push", "pull": "Pull", "move_to_aim": "M.A."}


@dataclass
class TablesConfig:
    """Args:
    dataset_repo_id: the demonstrations (LeRobotDataset) for SFT and the world-model env's initial frames.
    dataset_root: their local root.
    tokenizer: tokenizer directory or Hub repo id.
    action_world_model: action world model.
    text_world_model: text world model.
    policies: LeRobot policy types, with extra lerobot-train arguments after a space
        (e.g. "openvla --policy.base_model=tiny").
    families: task families of the table.
    per_task: one RL run per family (Table 1); false: one multi-task run over all of them (Table 2).
    sft_steps: lerobot-train steps.
    sft_batch_size: lerobot-train batch size.
    ppo_iterations: PPO iterations per run.
    critic_warmup_iterations: PPO's first iterations that train the critic only; null: the policy type's default.
    num_envs: parallel episodes in PPO.
    episode_length: PPO's fixed horizon; null: per task family, its longest successful demonstration.
    max_goal_steps: frames the text world model may generate while looking for a goal.
    eval_episodes: evaluation episodes per (split, family).
    eval_batch_size: parallel evaluation episodes.
    eval_episode_length: evaluation episode length; null: per task family, as episode_length.
    image_size: camera image side.
    allow_random_lpips: let the world-model env use a random LPIPS trunk (tests, offline demo).
    output_dir: everything, plus tables.md, tables.json and tables.png.
    device: "auto", "cpu" or "cuda".
    """

    dataset_repo_id: str = ""
    dataset_root: str | None = None
    tokenizer: str = ""
    action_world_model: str = ""
    text_world_model: str = ""
    policies: list[str] = field(default_factory=lambda: ["roboscape_mlp"])
    families: list[str] = field(default_factory=lambda: list(TASK_FAMILIES))
    per_task: bool = True
    sft_steps: int = 5000
    sft_batch_size: int = 32
    ppo_iterations: int = 100
    critic_warmup_iterations: int | None = None
    num_envs: int = 16
    episode_length: int | None = None
    eval_episodes: int = 50
    eval_batch_size: int = 16
    max_goal_steps: int = 100
    eval_episode_length: int | None = None
    image_size: int = 64
    allow_random_lpips: bool = False
    output_dir: Path = Path("outputs/tables")
    device: str = "auto"

    def __post_init__(self):
        self.output_dir = Path(self.output_dir)


def run_lerobot(script: str, args: list[str]) -> None:
    """A LeRobot command line (`lerobot_train`, `lerobot_eval`) in a subprocess with its own progress display."""
    result = subprocess.run([sys.executable, "-m", f"lerobot.scripts.{script}", *args], stdout=subprocess.DEVNULL)
    if result.returncode != 0:
        raise RuntimeError(f"{script} {' '.join(args)} failed with exit code {result.returncode}")


def sft_episodes(dataset_repo_id: str, dataset_root: str | None) -> list[int]:
    """The episodes SFT imitates: the successful ones (the failed attempts are there for the world model)."""
    episodes = successful_episodes(open_dataset(dataset_repo_id, dataset_root))
    if not episodes:
        raise ValueError(f"no successful episode in dataset {dataset_root or dataset_repo_id} to imitate")
    return episodes


def lerobot_sft(output_dir: Path, dataset_repo_id: str, dataset_root: str | None, policy_args: list[str],
                steps: int, batch_size: int, num_workers: int = 2, episodes: list[int] | None = None) -> Path:
    """SFT with `lerobot-train` on `episodes` (None: all); returns the final pretrained_model directory."""
    shutil.rmtree(output_dir, ignore_errors=True)
    root = [f"--dataset.root={dataset_root}"] if dataset_root else []
    selection = [f"--dataset.episodes=[{','.join(map(str, episodes))}]"] if episodes is not None else []
    run_lerobot("lerobot_train", [
        f"--dataset.repo_id={dataset_repo_id}", *root, *selection, *policy_args, "--policy.push_to_hub=false",
        f"--steps={steps}", f"--batch_size={batch_size}", f"--save_freq={steps}", f"--log_freq={max(steps // 5, 1)}",
        f"--num_workers={num_workers}", f"--output_dir={output_dir}",
    ])  # fmt: skip
    return output_dir / "checkpoints" / "last" / "pretrained_model"


def run_tables(cfg: TablesConfig, sft_checkpoints: dict[str, Path] | None = None) -> dict:
    """SFT (unless a checkpoint is given per policy type), PPO in both envs, evaluation; writes the tables."""
    results = {}
    for spec in cfg.policies:
        policy_type, *extra = spec.split()
        name = policy_type
        sft = (sft_checkpoints or {}).get(policy_type) or lerobot_sft(
            cfg.output_dir / name / "sft", cfg.dataset_repo_id, cfg.dataset_root,
            [f"--policy.type={policy_type}", *extra], cfg.sft_steps, cfg.sft_batch_size,
            episodes=sft_episodes(cfg.dataset_repo_id, cfg.dataset_root))  # fmt: skip
        results[name] = {SFT: evaluate(cfg, sft, cfg.families, cfg.output_dir / name / "eval_sft")}
        groups = [[family] for family in cfg.families] if cfg.per_task else [list(cfg.families)]
        for method, env_type in ((RL_MANISKILL, "maniskill"), (RL_WORLD_MODEL, "world_model")):
            merged = {"ind": {}, "ood": {}}
            for group in groups:
                tag = f"{env_type}_{'-'.join(group)}"
                ppo = train_ppo(PPOConfig(policy_path=str(sft), env=make_env_config(cfg, env_type, group),
                                          output_dir=cfg.output_dir / name / f"ppo_{tag}", num_envs=cfg.num_envs,
                                          iterations=cfg.ppo_iterations, save_freq=cfg.ppo_iterations,
                                          critic_warmup_iterations=cfg.critic_warmup_iterations,
                                          device=cfg.device))  # fmt: skip
                evaluation = evaluate(cfg, ppo, group, cfg.output_dir / name / f"eval_{tag}")
                for split in merged:
                    merged[split].update({f: evaluation[split][f] for f in group})
            results[name][method] = merged
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    (cfg.output_dir / "tables.json").write_text(json.dumps(results, indent=2))
    title = "Table 1, one RL run per task family" if cfg.per_task else "Table 1 layout, one multi-task RL run each"
    (cfg.output_dir / "tables.md").write_text(format_table(results, cfg.families, title))
    bar_chart(results, cfg.families, cfg.output_dir / "tables.png", title)
    return results


def make_env_config(cfg: TablesConfig, env_type: str, families: list[str]):
    if env_type == "maniskill":
        return RoboscapeManiSkillEnvConfig(families=families, split="ind", image_size=cfg.image_size,
                                           episode_length=cfg.episode_length, dataset_repo_id=cfg.dataset_repo_id,
                                           dataset_root=cfg.dataset_root)  # fmt: skip
    return RoboscapeWorldModelEnvConfig(
        dataset_repo_id=cfg.dataset_repo_id, dataset_root=cfg.dataset_root, tokenizer=cfg.tokenizer,
        action_world_model=cfg.action_world_model, text_world_model=cfg.text_world_model, families=families,
        split="ind", image_size=cfg.image_size, episode_length=cfg.episode_length,
        max_goal_steps=cfg.max_goal_steps, allow_random_lpips=cfg.allow_random_lpips, device=cfg.device,
    )  # fmt: skip


def evaluate(cfg: TablesConfig, checkpoint: Path, families: list[str], output_dir: Path) -> dict:
    """{split: {family: success rate}} in the simulator."""
    results = evaluate_success(EvalConfig(
        policy_path=str(checkpoint), families=families, episodes=cfg.eval_episodes, batch_size=cfg.eval_batch_size,
        episode_length=cfg.eval_episode_length, dataset_repo_id=cfg.dataset_repo_id, dataset_root=cfg.dataset_root,
        image_size=cfg.image_size, videos=1, output_dir=output_dir,
        device=cfg.device,
    ))  # fmt: skip
    return {split: {f: cells[f]["success_rate"] for f in families} for split, cells in results["splits"].items()}


def format_table(results: dict, families: list[str], title: str) -> str:
    """The paper's layout: rows policy x method, columns IND families then OOD families (success %)."""
    names = [SHORT.get(f, f) for f in families]
    header = "| Policy | Training method | " + " | ".join(f"IND {n}" for n in names) + " | " + \
        " | ".join(f"OOD {n}" for n in names) + " |"  # fmt: skip
    lines = [f"{title}: success rate (%) in the ManiSkill simulator", "", header,
             "|---|---|" + "---:|" * (2 * len(families))]  # fmt: skip
    for policy, methods in results.items():
        for method, splits in methods.items():
            cells = [f"{100 * splits[split][f]:.1f}" for split in ("ind", "ood") for f in families]
            lines.append(f"| {policy} | {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def bar_chart(results: dict, families: list[str], path: Path, title: str) -> None:
    """Mean success over the families, IND and OOD, one bar per (policy, method)."""
    labels, ind, ood = [], [], []
    for policy, methods in results.items():
        for method, splits in methods.items():
            labels.append(f"{policy}\n{method}")
            ind.append(100 * np.mean([splits["ind"][f] for f in families]))
            ood.append(100 * np.mean([splits["ood"][f] for f in families]))
    x = np.arange(len(labels))
    fig, ax = plt.subplots(figsize=(max(6, 1.6 * len(labels)), 3.5))
    ax.bar(x - 0.2, ind, 0.4, label="IND")
    ax.bar(x + 0.2, ood, 0.4, label="OOD")
    ax.set_xticks(x, labels, fontsize=7)
    ax.set_ylabel("success rate (%)")
    ax.set_ylim(0, 100)
    ax.set_title(title, fontsize=9)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
