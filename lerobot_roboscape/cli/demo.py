"""`roboscape-demo`: the whole pipeline built so far, on CPU, in minutes, on an embedded default.

Stages: collect planner demonstrations in the task suite -> record a ManiSkill trajectory file and convert it
(a held-out episode: another seed) -> train the image tokenizer -> train the action and the text world models ->
write the world model's fidelity report on the held-out episode -> roll out random actions in the `roboscape_wm`
environment built from those models -> SFT of the MLP policy with `lerobot-train` -> `lerobot-eval` of it in
`roboscape_maniskill` and `roboscape_wm` -> PPO of it in both envs and the small Table 1 (success in the
simulator, IND/OOD) -> optionally SFT of the tiny OpenVLA and its evaluation in the simulator. Each stage prints
where its results are.
"""

import json
import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import av
import draccus
import imageio.v3 as iio
import matplotlib
import numpy as np
from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.cli.collect import CollectConfig, collect
from lerobot_roboscape.cli.convert import ConvertConfig, convert
from lerobot_roboscape.demos.record import record_maniskill_trajectories
from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.envs.world_model_env import RoboscapeWorldModelEnv
from lerobot_roboscape.evaluation.tables import TablesConfig, lerobot_sft, run_lerobot, run_tables
from lerobot_roboscape.tasks import TASK_FAMILIES, select_scenes
from lerobot_roboscape.tokenizer.configuration_tokenizer import TinyTokenizerConfig
from lerobot_roboscape.tokenizer.train import TokenizerTrainingConfig, TrainTokenizerConfig, train_tokenizer
from lerobot_roboscape.training import FINAL
from lerobot_roboscape.world_model.configuration_world_model import TinyWorldModelConfig
from lerobot_roboscape.world_model.fidelity import FidelityConfig, evaluate_fidelity
from lerobot_roboscape.world_model.train import TrainWorldModelConfig, WorldModelTrainingConfig, train_world_model

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HELDOUT_SEED = 1000  # the recorded episode gets an initial state that the collected episodes do not have


@dataclass
class DemoConfig:
    """Args:
    output_dir: where every artifact goes (replaced if it holds an earlier demo run).
    families: task families to collect.
    scenes: number of IND scenes per family.
    episodes_per_scene: planner episodes per (family, scene).
    image_size: camera resolution.
    workers: ManiSkill worker processes.
    tokenizer_steps: training steps of the tiny tokenizer.
    wm_steps: training steps of the tiny action world model.
    text_wm_steps: training steps of the tiny text world model.
    mlp_steps: lerobot-train steps of the MLP policy.
    openvla_steps: lerobot-train steps of the tiny OpenVLA; 0 (the default, to keep the demo short) skips it,
        60 adds about 4 minutes on 2 cores.
    eval_episodes: episodes per lerobot-eval run.
    eval_episode_length: steps per evaluation episode.
    ppo_iterations: PPO iterations in each env (one episode per parallel env each).
    ppo_envs: parallel episodes of PPO.
    ppo_episode_length: steps per PPO episode.
    table_episodes: simulator episodes per (split, family) behind each cell of the small Table 1.
    """

    output_dir: str = "outputs/demo"
    families: list[str] = field(default_factory=lambda: list(TASK_FAMILIES))
    scenes: int = 2
    episodes_per_scene: int = 1
    image_size: int = 64
    workers: int = 2
    tokenizer_steps: int = 300
    wm_steps: int = 300
    text_wm_steps: int = 150
    mlp_steps: int = 600
    openvla_steps: int = 0
    eval_episodes: int = 4
    eval_episode_length: int = 80
    ppo_iterations: int = 3
    ppo_envs: int = 8
    ppo_episode_length: int = 40
    table_episodes: int = 1


def _stage(name: str):
    print(f"\n=== {name} ===", flush=True)
    return time.time()


def run_demo(cfg: DemoConfig) -> dict[str, Path]:
    stages = 11 if cfg.openvla_steps else 10
    out = Path(cfg.output_dir).resolve()
    for stale in ("tokenizer", "world_model_action", "world_model_text"):  # a new demo run trains from scratch
        shutil.rmtree(out / stale, ignore_errors=True)
    artifacts: dict[str, Path] = {}

    start = _stage(f"1/{stages} collect planner demonstrations (ManiSkill, both cameras)")
    demos = out / "datasets" / "roboscape_demos"
    ds = collect(CollectConfig(repo_id="local/roboscape_demos", root=str(demos), families=cfg.families,
                               max_scenes=cfg.scenes, episodes_per_scene=cfg.episodes_per_scene,
                               image_size=cfg.image_size, workers=cfg.workers, overwrite=True, keep_failed=True))
    print(f"{ds.meta.total_episodes} episodes, {ds.meta.total_frames} frames in {time.time() - start:.0f}s")
    artifacts["demonstrations (LeRobotDataset)"] = demos

    start = _stage(f"2/{stages} record a held-out ManiSkill trajectory file and convert it")
    scene = select_scenes("ind")[0]
    h5 = record_maniskill_trajectories(out / "maniskill_trajectories", cfg.families[0], scene.id, episodes=1,
                                       image_size=cfg.image_size, seed=HELDOUT_SEED)
    converted = out / "datasets" / "maniskill_converted"
    ds = convert(ConvertConfig(h5=str(h5), root=str(converted), repo_id="local/maniskill_converted",
                               overwrite=True))
    print(f"{ds.meta.total_episodes} episodes, {ds.meta.total_frames} frames in {time.time() - start:.0f}s")
    artifacts["ManiSkill trajectory file"] = h5
    artifacts["converted dataset (LeRobotDataset)"] = converted

    demos_cfg = DatasetConfig(repo_id="local/roboscape_demos", root=str(demos))
    start = _stage(f"3/{stages} train the image tokenizer (tiny preset)")
    tokenizer_dir = out / "tokenizer"
    train_tokenizer(TrainTokenizerConfig(
        dataset=demos_cfg, tokenizer=TinyTokenizerConfig(image_size=cfg.image_size),
        train=TokenizerTrainingConfig(steps=cfg.tokenizer_steps, save_freq=cfg.tokenizer_steps),
        output_dir=tokenizer_dir, num_workers=cfg.workers, allow_random_lpips=True,
    ))  # fmt: skip
    print(f"done in {time.time() - start:.0f}s")
    artifacts["tokenizer"] = tokenizer_dir / FINAL

    for number, control, steps in ((4, "action", cfg.wm_steps), (5, "text", cfg.text_wm_steps)):
        start = _stage(f"{number}/{stages} train the {control} world model (tiny preset)")
        wm_dir = out / f"world_model_{control}"
        train_world_model(TrainWorldModelConfig(
            dataset=demos_cfg, tokenizer=str(tokenizer_dir / FINAL), wm=TinyWorldModelConfig(control=control),
            train=WorldModelTrainingConfig(steps=steps, batch_size=4, save_freq=steps),
            output_dir=wm_dir, cache_dir=out / "token_cache",
        ))  # fmt: skip
        print(f"done in {time.time() - start:.0f}s")
        artifacts[f"{control} world model"] = wm_dir / FINAL

    start = _stage(f"6/{stages} fidelity report of the action world model on the held-out episode")
    report = evaluate_fidelity(FidelityConfig(
        dataset=DatasetConfig(repo_id="local/maniskill_converted", root=str(converted)),
        tokenizer=str(tokenizer_dir / FINAL), world_model=str(out / "world_model_action" / FINAL),
        output_dir=out / "fidelity", allow_random_lpips=True,
    ))  # fmt: skip
    mean = report["mean"]
    print(f"PSNR {mean['prediction_psnr']:.1f} dB (tokenizer alone {mean['reconstruction_psnr']:.1f}), "
          f"SSIM {mean['prediction_ssim']:.2f}, done accuracy {report['done_teacher_forced']['accuracy']:.2f}, "
          f"in {time.time() - start:.0f}s")
    artifacts["fidelity report"] = out / "fidelity" / "fidelity.md"
    artifacts["predicted vs real video"] = out / "fidelity" / "side_by_side.mp4"

    start = _stage(f"7/{stages} random actions in the roboscape_wm environment (world-model reward)")
    rollout = random_rollout(out, demos, cfg.image_size)
    print(f"{rollout['steps']} steps of {rollout['episodes']} episodes, return {rollout['returns']}, "
          f"in {time.time() - start:.0f}s")
    artifacts["roboscape_wm rollout video (frame | goal)"] = rollout["video"]
    artifacts["roboscape_wm reward curve"] = rollout["plot"]

    wm_env_args = ["--env.dataset_repo_id=local/roboscape_demos", f"--env.dataset_root={demos}",
                   f"--env.tokenizer={tokenizer_dir / FINAL}",
                   f"--env.action_world_model={out / 'world_model_action' / FINAL}",
                   f"--env.text_world_model={out / 'world_model_text' / FINAL}", "--env.allow_random_lpips=true",
                   "--env.max_goal_steps=40"]  # fmt: skip

    start = _stage(f"8/{stages} SFT of the MLP policy with lerobot-train")
    mlp = lerobot_sft(out / "sft_mlp", "local/roboscape_demos", str(demos), ["--policy.type=roboscape_mlp"],
                      cfg.mlp_steps, batch_size=16)
    print(f"done in {time.time() - start:.0f}s")
    artifacts["MLP policy after SFT"] = mlp

    start = _stage(f"9/{stages} lerobot-eval of the MLP policy in roboscape_maniskill and roboscape_wm")
    for env_type, env_args in (("roboscape_maniskill", []), ("roboscape_wm", wm_env_args)):
        artifacts[f"MLP evaluation in {env_type}"] = lerobot_eval(out / f"eval_mlp_{env_type}", mlp, env_type,
                                                                  cfg, env_args)
    print(f"done in {time.time() - start:.0f}s")

    start = _stage(f"10/{stages} PPO of the MLP policy in roboscape_maniskill and in roboscape_wm; the small Table 1")
    tables = TablesConfig(
        dataset_repo_id="local/roboscape_demos", dataset_root=str(demos), tokenizer=str(tokenizer_dir / FINAL),
        action_world_model=str(out / "world_model_action" / FINAL),
        text_world_model=str(out / "world_model_text" / FINAL), families=cfg.families, per_task=False,
        ppo_iterations=cfg.ppo_iterations, num_envs=cfg.ppo_envs, episode_length=cfg.ppo_episode_length,
        eval_episodes=cfg.table_episodes, eval_batch_size=len(cfg.families) * cfg.table_episodes,
        eval_episode_length=cfg.eval_episode_length, image_size=cfg.image_size, allow_random_lpips=True,
        output_dir=out / "tables", device="cpu",
    )  # fmt: skip
    shutil.rmtree(tables.output_dir, ignore_errors=True)
    run_tables(tables, sft_checkpoints={"roboscape_mlp": mlp})
    print((tables.output_dir / "tables.md").read_text())
    print(f"done in {time.time() - start:.0f}s")
    artifacts["MLP after PPO in ManiSkill"] = tables.output_dir / "roboscape_mlp" / "ppo_maniskill_" \
        f"{'-'.join(cfg.families)}" / "checkpoints" / "last"
    artifacts["MLP after PPO in the world model"] = tables.output_dir / "roboscape_mlp" / "ppo_world_model_" \
        f"{'-'.join(cfg.families)}" / "checkpoints" / "last"
    artifacts["small Table 1"] = tables.output_dir / "tables.md"
    artifacts["Table 1 bar chart"] = tables.output_dir / "tables.png"

    if cfg.openvla_steps:
        start = _stage(f"11/{stages} SFT of the tiny OpenVLA (LoRA) and lerobot-eval in roboscape_maniskill")
        openvla_args = ["--policy.type=openvla", "--policy.base_model=tiny", "--policy.gradient_checkpointing=false"]
        openvla = lerobot_sft(out / "sft_openvla", "local/roboscape_demos", str(demos), openvla_args,
                              cfg.openvla_steps, batch_size=8)
        artifacts["tiny OpenVLA adapter after SFT"] = openvla
        artifacts["tiny OpenVLA evaluation in roboscape_maniskill"] = lerobot_eval(
            out / "eval_openvla_roboscape_maniskill", openvla, "roboscape_maniskill", cfg, [])
        print(f"done in {time.time() - start:.0f}s")

    print("\n=== results ===")
    for name, path in artifacts.items():
        print(f"{name:40s} {path}")
    return artifacts


def lerobot_eval(output_dir: Path, checkpoint: Path, env_type: str, cfg: DemoConfig, env_args: list[str]) -> Path:
    """Evaluate `checkpoint` in `env_type` with lerobot-eval; prints the result, returns its eval_info.json."""
    shutil.rmtree(output_dir, ignore_errors=True)
    run_lerobot("lerobot_eval", [
        f"--policy.path={checkpoint}", f"--env.type={env_type}", f"--env.image_size={cfg.image_size}",
        f"--env.families=[{','.join(cfg.families)}]", f"--env.episode_length={cfg.eval_episode_length}",
        *env_args, f"--eval.n_episodes={cfg.eval_episodes}", f"--eval.batch_size={cfg.eval_episodes}",
        f"--output_dir={output_dir}",
    ])  # fmt: skip
    result = json.loads((output_dir / "eval_info.json").read_text())["overall"]
    print(f"{env_type}: success {result['pc_success']:.0f}% of {result['n_episodes']} episodes, "
          f"mean return {result['avg_sum_reward']:.2f}")
    return output_dir / "eval_info.json"


def random_rollout(out: Path, demos: Path, image_size: int, episodes: int = 2, steps: int = 40) -> dict:
    """Random actions in a roboscape_wm env of the demo's models: a video of frame beside goal and the reward."""
    env = RoboscapeWorldModelEnv(RoboscapeWorldModelEnvConfig(
        dataset_repo_id="local/roboscape_demos", dataset_root=str(demos), tokenizer=str(out / "tokenizer" / FINAL),
        action_world_model=str(out / "world_model_action" / FINAL),
        text_world_model=str(out / "world_model_text" / FINAL), image_size=image_size, episode_length=steps,
        max_goal_steps=40, allow_random_lpips=True,
    ), num_envs=episodes)  # fmt: skip
    env.reset(seed=0)
    frames, rewards = [np.concatenate(env.render(), axis=1)], []
    rng = np.random.default_rng(0)
    for _ in range(steps):
        _, reward, terminated, truncated, _ = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        frames.append(np.concatenate(env.render(), axis=1))
        rewards.append(reward)
        if (terminated | truncated).all():
            break
    rewards = np.stack(rewards)
    video, plot = out / "wm_rollout.mp4", out / "wm_rollout_reward.png"
    av.logging.set_level(av.logging.ERROR)
    iio.imwrite(video, np.stack(frames), plugin="pyav", codec="libx264", fps=env.metadata["render_fps"])
    fig, ax = plt.subplots(figsize=(6, 3))
    for i in range(episodes):
        ax.plot(rewards[:, i], label=env.tasks()[i])
    ax.set_xlabel("step")
    ax.set_ylabel("reward")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(plot, dpi=100)
    plt.close(fig)
    return {"video": video, "plot": plot, "steps": len(rewards), "episodes": episodes,
            "returns": [round(float(r), 2) for r in rewards.sum(0)]}


def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    run_demo(draccus.parse(DemoConfig, args=argv))


if __name__ == "__main__":
    main()
