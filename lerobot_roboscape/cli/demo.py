"""`roboscape-demo`: the whole RoboScape-R pipeline on an embedded default, in minutes on CPU.

Stages: collect planner demonstrations in the task suite -> record a ManiSkill trajectory file and convert it
(a held-out episode: another seed) -> train the image tokenizer -> train the action and the text world models ->
the world model's fidelity report on the held-out episode -> random actions in the `roboscape_wm` environment
built from those models -> SFT of the MLP policy with `lerobot-train` (and of OpenVLA with `--openvla_steps`) ->
`lerobot-eval` in `roboscape_wm` -> PPO in `roboscape_maniskill` and in `roboscape_wm` and the small Table 1
(success in the simulator, IND/OOD) -> a push of every artifact, with its card, to a local folder shaped like the
Hub repos (or to the Hub with `--push_to_hub=true`). The summary names every artifact and checks that it loads.

    roboscape-demo                      # tiny presets, CPU, under 20 minutes on 2 cores
    roboscape-demo --scale=smoke        # the smallest run of every stage (the end-to-end test)
    roboscape-demo --scale=paper --push_to_hub=true --hub_namespace=me   # paper presets, GPUs
"""

import contextlib
import io
import json
import logging
import shutil
import time
from dataclasses import dataclass, replace
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
from lerobot_roboscape.evaluation.tables import TablesConfig, lerobot_sft, run_lerobot, run_tables, sft_episodes
from lerobot_roboscape.hub.push import push_dataset, push_policy, push_world_models
from lerobot_roboscape.tasks import TASK_FAMILIES, select_scenes
from lerobot_roboscape.tokenizer.configuration_tokenizer import TokenizerConfig
from lerobot_roboscape.tokenizer.train import TokenizerTrainingConfig, TrainTokenizerConfig, train_tokenizer
from lerobot_roboscape.training import FINAL, last_checkpoint
from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig
from lerobot_roboscape.world_model.fidelity import FidelityConfig, evaluate_fidelity
from lerobot_roboscape.world_model.train import (
    TrainWorldModelConfig,
    WorldModelTrainingConfig,
    train_world_model,
)

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HELDOUT_SEED = 1000  # the recorded episode gets an initial state that the collected episodes do not have
ALL = list(TASK_FAMILIES)

# What each scale sets; a flag given on the command line wins. "tiny" is the embedded default (2 CPU cores, under
# 20 min: two task families, so that the simulator evaluations behind the table fit); "smoke" runs every stage
# at its smallest; "paper" is the paper's setting (GPUs, days: 80 scenes, 128 px, the paper presets of the
# tokenizer and world models, OpenVLA-7B with LoRA).
SCALES = {
    "smoke": dict(
        families=["push"], scenes=1, episodes_per_scene=1, image_size=64, workers=1, preset="tiny",
        tokenizer_steps=4, tokenizer_batch_size=8, wm_steps=4, text_wm_steps=4, wm_batch_size=4, mlp_steps=4,
        openvla_steps=0, openvla_base="tiny", eval_episodes=1, eval_episode_length=4, ppo_iterations=1,
        ppo_envs=2, ppo_episode_length=4, table_episodes=1, max_goal_steps=4, loader_workers=0, device="cpu",
    ),
    "tiny": dict(
        families=["pick_place", "push"], scenes=2, episodes_per_scene=2, image_size=64, workers=2, preset="tiny",
        tokenizer_steps=200, tokenizer_batch_size=8, wm_steps=200, text_wm_steps=100, wm_batch_size=4,
        mlp_steps=400, openvla_steps=0, openvla_base="tiny", eval_episodes=2, eval_episode_length=60,
        ppo_iterations=2, ppo_envs=6, ppo_episode_length=30, table_episodes=1, max_goal_steps=40,
        loader_workers=2, device="cpu",
    ),
    "paper": dict(
        families=ALL, scenes=None, episodes_per_scene=25, image_size=128, workers=16, preset="paper",
        tokenizer_steps=100_000, tokenizer_batch_size=32, wm_steps=200_000, text_wm_steps=100_000,
        wm_batch_size=32, mlp_steps=20_000, openvla_steps=20_000, openvla_base="openvla/openvla-7b",
        eval_episodes=50, eval_episode_length=160, ppo_iterations=200, ppo_envs=64, ppo_episode_length=80,
        table_episodes=50, max_goal_steps=100, loader_workers=8, device="auto",
    ),
}


@dataclass
class DemoConfig:
    """Args:
    scale: "tiny" (default), "smoke" or "paper": sets every field left unset below.
    output_dir: where every artifact goes (replaced if it holds an earlier demo run).
    families: task families to collect and evaluate.
    scenes: IND scenes per family (null: all).
    episodes_per_scene: planner episodes per (family, scene).
    image_size: camera resolution.
    workers: ManiSkill worker processes.
    preset: "tiny" or "paper" presets of the tokenizer and world models.
    tokenizer_steps: training steps of the tokenizer.
    tokenizer_batch_size: frames per tokenizer training step.
    wm_steps: training steps of the action world model.
    text_wm_steps: training steps of the text world model.
    wm_batch_size: clips per world-model training step.
    mlp_steps: lerobot-train steps of the MLP policy.
    openvla_steps: lerobot-train steps of OpenVLA (LoRA); 0 skips it. With OpenVLA, the table has its rows too.
    openvla_base: OpenVLA base model: "tiny" (random, CPU) or a checkpoint such as openvla/openvla-7b.
    eval_episodes: episodes of the lerobot-eval run in roboscape_wm.
    eval_episode_length: steps per evaluation episode.
    ppo_iterations: PPO iterations in each env (one episode per parallel env each).
    ppo_envs: parallel episodes of PPO.
    ppo_episode_length: steps per PPO episode.
    table_episodes: simulator episodes per (split, family) behind each cell of the small Table 1.
    max_goal_steps: frames the text world model may generate while looking for a goal.
    loader_workers: data-loading processes of lerobot-train (0 saves their start-up on tiny runs).
    device: "cpu", "cuda" or "auto".
    push_to_hub: upload every artifact to the Hub (needs `hf auth login`); otherwise write the repos to
        output_dir/hub.
    hub_namespace: the Hub user or organisation of the repos.
    """

    scale: str = "tiny"
    output_dir: str = "outputs/demo"
    families: list[str] | None = None
    scenes: int | None = None
    episodes_per_scene: int | None = None
    image_size: int | None = None
    workers: int | None = None
    preset: str | None = None
    tokenizer_steps: int | None = None
    tokenizer_batch_size: int | None = None
    wm_steps: int | None = None
    text_wm_steps: int | None = None
    wm_batch_size: int | None = None
    mlp_steps: int | None = None
    openvla_steps: int | None = None
    openvla_base: str | None = None
    eval_episodes: int | None = None
    eval_episode_length: int | None = None
    ppo_iterations: int | None = None
    ppo_envs: int | None = None
    ppo_episode_length: int | None = None
    table_episodes: int | None = None
    max_goal_steps: int | None = None
    loader_workers: int | None = None
    device: str | None = None
    push_to_hub: bool = False
    hub_namespace: str = "local"

    def __post_init__(self):
        if self.scale not in SCALES:
            raise ValueError(f"--scale must be one of {list(SCALES)}, got {self.scale!r}")
        for name, value in SCALES[self.scale].items():
            if getattr(self, name) is None:
                setattr(self, name, list(value) if isinstance(value, list) else value)
        unknown = [f for f in self.families if f not in TASK_FAMILIES]
        if unknown:
            raise ValueError(f"unknown task families {unknown}; choose from {list(TASK_FAMILIES)}")


class Stages:
    """Numbered stage headers with the time each stage took."""

    def __init__(self, total: int):
        self.total, self.number, self.start, self.began = total, 0, None, time.time()

    def __call__(self, title: str):
        self.done()
        self.number += 1
        self.start = time.time()
        print(f"\n=== {self.number}/{self.total} {title} ===", flush=True)

    def done(self):
        if self.start is not None:
            print(f"--- stage {self.number} done in {time.time() - self.start:.0f}s "
                  f"({(time.time() - self.began) / 60:.1f} min so far)", flush=True)
            self.start = None


def run_demo(cfg: DemoConfig) -> dict[str, Path]:
    out = Path(cfg.output_dir).resolve()
    for stale in ("tokenizer", "world_model_action", "world_model_text", "hub"):  # a new run trains from scratch
        shutil.rmtree(out / stale, ignore_errors=True)
    artifacts: dict[str, Path] = {}
    stage = Stages(11)
    families_flag = f"--env.families=[{','.join(cfg.families)}]"

    stage("collect planner demonstrations (ManiSkill, both cameras)")
    demos = out / "datasets" / "roboscape_demos"
    ds = collect(CollectConfig(repo_id="local/roboscape_demos", root=str(demos), families=cfg.families,
                               max_scenes=cfg.scenes, episodes_per_scene=cfg.episodes_per_scene,
                               image_size=cfg.image_size, workers=cfg.workers, overwrite=True, keep_failed=True))
    print(f"{ds.meta.total_episodes} episodes, {ds.meta.total_frames} frames")
    artifacts["demonstrations (LeRobotDataset)"] = demos

    stage("record a held-out ManiSkill trajectory file and convert it")
    scene = select_scenes("ind")[0]
    h5 = record_maniskill_trajectories(out / "maniskill_trajectories", cfg.families[0], scene.id, episodes=1,
                                       image_size=cfg.image_size, seed=HELDOUT_SEED)
    converted = out / "datasets" / "maniskill_converted"
    ds = convert(ConvertConfig(h5=str(h5), root=str(converted), repo_id="local/maniskill_converted",
                               overwrite=True))
    print(f"{ds.meta.total_episodes} episodes, {ds.meta.total_frames} frames")
    artifacts["ManiSkill trajectory file"] = h5
    artifacts["converted dataset (LeRobotDataset)"] = converted

    demos_cfg = DatasetConfig(repo_id="local/roboscape_demos", root=str(demos))
    stage(f"train the image tokenizer ({cfg.preset} preset)")
    tokenizer = out / "tokenizer" / FINAL
    train_tokenizer(TrainTokenizerConfig(
        dataset=demos_cfg, tokenizer=TokenizerConfig.get_choice_class(cfg.preset)(image_size=cfg.image_size),
        train=TokenizerTrainingConfig(steps=cfg.tokenizer_steps, batch_size=cfg.tokenizer_batch_size,
                                      save_freq=cfg.tokenizer_steps),
        output_dir=tokenizer.parent, num_workers=min(cfg.workers, 2), allow_random_lpips=True,
    ))  # fmt: skip
    artifacts["tokenizer"] = tokenizer

    models = {}
    for control, steps in (("action", cfg.wm_steps), ("text", cfg.text_wm_steps)):
        stage(f"train the {control} world model ({cfg.preset} preset)")
        models[control] = out / f"world_model_{control}" / FINAL
        train_world_model(TrainWorldModelConfig(
            dataset=demos_cfg, tokenizer=str(tokenizer),
            wm=WorldModelConfig.get_choice_class(cfg.preset)(control=control),
            train=WorldModelTrainingConfig(steps=steps, batch_size=cfg.wm_batch_size, save_freq=steps),
            output_dir=models[control].parent, cache_dir=out / "token_cache", device=cfg.device,
        ))  # fmt: skip
        artifacts[f"{control} world model"] = models[control]

    stage("fidelity report of the action world model on the held-out episode")
    report = evaluate_fidelity(FidelityConfig(
        dataset=DatasetConfig(repo_id="local/maniskill_converted", root=str(converted)),
        tokenizer=str(tokenizer), world_model=str(models["action"]), output_dir=out / "fidelity",
        allow_random_lpips=True, device=cfg.device,
    ))  # fmt: skip
    mean = report["mean"]
    print(f"PSNR {mean['prediction_psnr']:.1f} dB (tokenizer alone {mean['reconstruction_psnr']:.1f}), "
          f"SSIM {mean['prediction_ssim']:.2f}, done accuracy {report['done_teacher_forced']['accuracy']:.2f}")
    artifacts["fidelity report"] = out / "fidelity" / "fidelity.md"
    artifacts["predicted vs real video"] = out / "fidelity" / "side_by_side.mp4"

    stage("random actions in the roboscape_wm environment (world-model reward)")
    wm_env = dict(dataset_repo_id="local/roboscape_demos", dataset_root=str(demos), tokenizer=str(tokenizer),
                  action_world_model=str(models["action"]), text_world_model=str(models["text"]),
                  max_goal_steps=cfg.max_goal_steps, allow_random_lpips=True, device=cfg.device)
    rollout = random_rollout(out, RoboscapeWorldModelEnvConfig(image_size=cfg.image_size, **wm_env))
    print(f"{rollout['steps']} steps of {rollout['episodes']} episodes, return {rollout['returns']}")
    artifacts["roboscape_wm rollout video (frame | goal)"] = rollout["video"]
    artifacts["roboscape_wm reward curve"] = rollout["plot"]

    stage("SFT with lerobot-train: the MLP policy" + (" and OpenVLA (LoRA)" if cfg.openvla_steps else ""))
    device_flag = [f"--policy.device={cfg.device}"] if cfg.device != "auto" else []
    successes = sft_episodes("local/roboscape_demos", str(demos))
    sft = {"roboscape_mlp": lerobot_sft(out / "sft_mlp", "local/roboscape_demos", str(demos),
                                        ["--policy.type=roboscape_mlp", *device_flag], cfg.mlp_steps, batch_size=16,
                                        num_workers=cfg.loader_workers, episodes=successes)}
    openvla_spec = f"openvla --policy.base_model={cfg.openvla_base}"
    if cfg.openvla_steps:
        sft["openvla"] = lerobot_sft(out / "sft_openvla", "local/roboscape_demos", str(demos),
                                     [*("--policy.type=openvla", f"--policy.base_model={cfg.openvla_base}"),
                                      *device_flag], cfg.openvla_steps, batch_size=8,
                                     num_workers=cfg.loader_workers, episodes=successes)  # fmt: skip
    for name, path in sft.items():
        artifacts[f"{name} after SFT"] = path

    stage("lerobot-eval in roboscape_wm (LeRobot's evaluation in the world model)")
    wm_flags = [f"--env.{key}={value}" for key, value in wm_env.items() if key != "device"]
    for name, path in sft.items():
        artifacts[f"{name} lerobot-eval in roboscape_wm"] = lerobot_eval(
            out / f"eval_{name}_roboscape_wm", path, "roboscape_wm", cfg, [families_flag, *wm_flags])

    stage("PPO in roboscape_maniskill and in roboscape_wm; the small Table 1 (success in the simulator)")
    tables = TablesConfig(
        dataset_repo_id="local/roboscape_demos", dataset_root=str(demos), tokenizer=str(tokenizer),
        action_world_model=str(models["action"]), text_world_model=str(models["text"]),
        policies=["roboscape_mlp"] + ([openvla_spec] if cfg.openvla_steps else []), families=cfg.families,
        per_task=False, ppo_iterations=cfg.ppo_iterations, critic_warmup_iterations=1, num_envs=cfg.ppo_envs,
        episode_length=cfg.ppo_episode_length, max_goal_steps=cfg.max_goal_steps,
        eval_episodes=cfg.table_episodes,
        eval_batch_size=len(cfg.families) * cfg.table_episodes, eval_episode_length=cfg.eval_episode_length,
        image_size=cfg.image_size, allow_random_lpips=True, output_dir=out / "tables", device=cfg.device,
    )  # fmt: skip
    shutil.rmtree(tables.output_dir, ignore_errors=True)
    run_tables(tables, sft_checkpoints=sft)
    print((tables.output_dir / "tables.md").read_text())
    group = "-".join(cfg.families)
    runs = {}
    for name in sft:
        runs[name] = {"sft": (sft[name], tables.output_dir / name / "eval_sft")}
        for env_type in ("maniskill", "world_model"):
            checkpoint = last_checkpoint(tables.output_dir / name / f"ppo_{env_type}_{group}") / FINAL
            runs[name][f"ppo_{env_type}"] = (checkpoint, tables.output_dir / name / f"eval_{env_type}_{group}")
            artifacts[f"{name} after PPO in {env_type.replace('_', ' ')}"] = checkpoint
    artifacts["small Table 1"] = tables.output_dir / "tables.md"
    artifacts["Table 1 bar chart"] = tables.output_dir / "tables.png"

    stage("push to the Hub" if cfg.push_to_hub else f"push to a local folder shaped like the Hub ({out / 'hub'})")
    local_dir = None if cfg.push_to_hub else out / "hub"
    ns = cfg.hub_namespace
    dataset_repo = f"{ns}/roboscape_demos"
    pushed = {"dataset repo": push_dataset(demos, dataset_repo, local_dir),
              "world models repo": push_world_models(
                  f"{ns}/roboscape_world_models", local_dir, tokenizer=tokenizer, action_world_model=models["action"],
                  text_world_model=models["text"], dataset_repo_id=dataset_repo, fidelity_dir=out / "fidelity")}
    for name, methods in runs.items():
        for method, (checkpoint, eval_dir) in methods.items():
            pushed[f"{name} {method} repo"] = push_policy(f"{ns}/{name}_{method}", checkpoint, local_dir,
                                                          eval_dir=eval_dir, dataset_repo_id=dataset_repo)
    for name, where in pushed.items():
        print(f"{name:36s} {where}")
        if local_dir is not None:
            artifacts[name] = Path(where)
    stage.done()

    print(f"\n=== results ({(time.time() - stage.began) / 60:.1f} min) ===")
    for name, path in artifacts.items():
        with contextlib.redirect_stdout(io.StringIO()):  # LeRobot's from_pretrained prints where it loads from
            loaded = load_artifact(path)
        print(f"{name:44s} {loaded:34s} {path}")
    return artifacts


def load_artifact(path: Path) -> str:
    """Load an artifact of the demo by what it is; returns what was loaded (raises if it does not load)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    from lerobot_roboscape.hub.pull import WORLD_MODELS_MANIFEST, pull_world_models
    from lerobot_roboscape.rl.policy_loading import load_policy
    from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
    from lerobot_roboscape.world_model.modeling_world_model import STWorldModel

    path = Path(path)
    if path.suffix == ".mp4":
        with av.open(str(path)) as container:
            return f"video, {sum(1 for _ in container.decode(video=0))} frames"
    if path.suffix == ".png":
        return f"image {'x'.join(map(str, iio.imread(path).shape[:2]))}"
    if path.suffix == ".json":
        return f"JSON, {len(json.loads(path.read_text()))} keys"
    if path.suffix == ".md":
        return f"markdown, {len(path.read_text().splitlines())} lines"
    if path.suffix == ".h5":
        import h5py

        with h5py.File(path) as f:
            return f"trajectory file, {len(f.keys())} episodes"
    if (path / "meta" / "info.json").is_file():
        meta = LeRobotDatasetMetadata(json.loads((path / "meta" / "info.json").read_text()).get("repo_id", "local/x"),
                                      root=path)
        return f"dataset, {meta.total_episodes} episodes"
    if (path / WORLD_MODELS_MANIFEST).is_file():
        bundle = pull_world_models(str(path))
        for model in (bundle.action_world_model, bundle.text_world_model):
            STWorldModel.from_pretrained(str(model))
        VisualTokenizer.from_pretrained(str(bundle.tokenizer))
        return "tokenizer + 2 world models"
    config = json.loads((path / "config.json").read_text())
    if "type" in config:  # a LeRobot policy
        policy, _, _ = load_policy(path, "cpu")
        return f"{config['type']} policy"
    if "control" in config:
        return f"{STWorldModel.from_pretrained(str(path)).config.control} world model"
    VisualTokenizer.from_pretrained(str(path))
    return "tokenizer"


def lerobot_eval(output_dir: Path, checkpoint: Path, env_type: str, cfg: DemoConfig, env_args: list[str]) -> Path:
    """Evaluate `checkpoint` in `env_type` with lerobot-eval; prints the result, returns its eval_info.json."""
    shutil.rmtree(output_dir, ignore_errors=True)
    run_lerobot("lerobot_eval", [
        f"--policy.path={checkpoint}", f"--env.type={env_type}", f"--env.image_size={cfg.image_size}",
        f"--env.episode_length={cfg.eval_episode_length}",
        *env_args, f"--eval.n_episodes={cfg.eval_episodes}", f"--eval.batch_size={cfg.eval_episodes}",
        f"--output_dir={output_dir}",
    ])  # fmt: skip
    result = json.loads((output_dir / "eval_info.json").read_text())["overall"]
    print(f"{env_type}: success {result['pc_success']:.0f}% of {result['n_episodes']} episodes, "
          f"mean return {result['avg_sum_reward']:.2f}")
    return output_dir / "eval_info.json"


def random_rollout(out: Path, config: RoboscapeWorldModelEnvConfig, episodes: int = 2, steps: int = 40) -> dict:
    """Random actions in a roboscape_wm env of the demo's models: a video of frame beside goal and the reward."""
    env = RoboscapeWorldModelEnv(replace(config, episode_length=steps), num_envs=episodes)
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
