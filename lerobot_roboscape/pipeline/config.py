"""What one run of the pipeline does, at each scale: the config of `roboscape-demo` and `roboscape-experiment`."""

from dataclasses import dataclass

import torch

from lerobot_roboscape.tasks import TASK_FAMILIES
from roboscape_core.errors import InvalidInputError

ALL = list(TASK_FAMILIES)

# What each scale sets; a flag given on the command line wins.
# - "smoke": every stage at its smallest (the end-to-end test).
# - "tiny": the embedded default (2 CPU cores, under 20 min): shows every stage working, judges none.
# - "bench": the paper's experiment at the largest size that fits 2 CPU cores in a few hours, sized from
#   measurements (docs/results/bench/report.md): push and pick&place, all 64 IND scenes, a 16x16 token grid. The
#   simulator makes about 47 env steps/s with two 64 px cameras on the 2 cores, the policy included
#   (docs/results/simulator/report.md), so Table 1 has 50 episodes per cell, as the paper's tables: a 95% interval
#   at most 27 points wide.
#   The tokenizer trains for 8000 steps (about 40 min) with the object's pixels weighted up, sized by its held-out
#   curves (docs/results/tokenizer/report.md).
# - "paper": the paper's setting (GPUs, days: 80 scenes, 128 px, paper presets, OpenVLA-7B with LoRA).
SCALES = {
    "smoke": dict(
        families=["push"],
        scenes=1,
        episodes_per_scene=1,
        explore_episodes_per_scene=1,
        exploration_share=0.5,
        heldout_scenes=0,
        report_episodes=4,
        image_size=64,
        workers=1,
        tokenizer_preset="tiny",
        wm_preset="tiny",
        tokenizer_steps=4,
        tokenizer_batch_size=8,
        wm_steps=4,
        text_wm_steps=4,
        wm_batch_size=4,
        reward_model_steps=0,
        mlp_steps=4,
        sft_batch_size=16,
        openvla_steps=0,
        openvla_base="tiny",
        eval_episodes=1,
        eval_episode_length=4,
        ppo_iterations=1,
        ppo_minutes=None,
        ppo_critic_warmup=1,
        ppo_envs=2,
        ppo_episode_length=4,
        ppo_one_scene=False,
        reward_ablation=False,
        wm_starts_per_scene=None,
        table_episodes=1,
        table_episode_length=4,
        max_goal_steps=4,
        loader_workers=0,
        device="cpu",
    ),
    "tiny": dict(
        families=["pick_place", "push"],
        scenes=2,
        episodes_per_scene=2,
        explore_episodes_per_scene=1,
        exploration_share=0.5,
        heldout_scenes=0,
        report_episodes=8,
        image_size=64,
        workers=2,
        tokenizer_preset="tiny",
        wm_preset="tiny",
        tokenizer_steps=200,
        tokenizer_batch_size=8,
        wm_steps=200,
        text_wm_steps=100,
        wm_batch_size=4,
        reward_model_steps=0,
        mlp_steps=400,
        sft_batch_size=16,
        openvla_steps=0,
        openvla_base="tiny",
        eval_episodes=2,
        eval_episode_length=60,
        ppo_iterations=2,
        ppo_minutes=None,
        ppo_critic_warmup=1,
        ppo_envs=6,
        ppo_episode_length=30,
        ppo_one_scene=False,
        reward_ablation=False,
        wm_starts_per_scene=None,
        table_episodes=1,
        table_episode_length=60,
        max_goal_steps=40,
        loader_workers=2,
        device="cpu",
    ),
    "bench": dict(
        families=["pick_place", "push"],
        scenes=None,
        # SFT success grew with the demonstrations per scene up to the 16 measured (docs/results/sft): 2048
        # planner episodes, about 50 min of collection on 2 cores.
        episodes_per_scene=16,
        # exploratory episodes (noisy, excursion, random) for the action world model: 512, about 13 min
        explore_episodes_per_scene=4,
        # shares 0, 0.25 and 0.5 were within noise of each other at 1,500 steps; 0.25 is the one run to 3,000
        # (docs/results/world_model/report.md)
        exploration_share=0.25,
        heldout_scenes=8,
        report_episodes=64,
        image_size=64,
        workers=2,
        tokenizer_preset="bench",
        wm_preset="bench",
        tokenizer_steps=8000,
        tokenizer_batch_size=8,
        # 31 min alone on 2 cores at batch 4; the action gain still rose at the end, retrieval did not
        # (docs/results/world_model/report.md)
        wm_steps=3000,
        text_wm_steps=500,
        wm_batch_size=4,
        reward_model_steps=600,
        mlp_steps=10_000,  # success stops rising here (docs/results/sft); about 14 min on 2 cores
        sft_batch_size=32,
        openvla_steps=0,
        openvla_base="tiny",
        eval_episodes=4,
        eval_episode_length=60,
        ppo_iterations=1000,
        ppo_minutes=8.0,  # each of the five runs: 40 min of PPO on 2 cores
        ppo_critic_warmup=1,
        ppo_envs=8,
        ppo_episode_length=100,
        ppo_one_scene=True,
        reward_ablation=True,
        # one start per (family, scene): 128 goals, 11 min of the text model on 2 cores, before PPO's clock
        wm_starts_per_scene=1,
        table_episodes=50,
        table_episode_length=100,
        max_goal_steps=200,  # beyond every family's horizon: a goal not found within it counts as missed
        loader_workers=2,
        device="auto",
    ),
    "paper": dict(
        families=ALL,
        scenes=None,
        episodes_per_scene=25,
        explore_episodes_per_scene=5,
        exploration_share=0.5,
        heldout_scenes=16,
        report_episodes=64,
        image_size=128,
        workers=16,
        tokenizer_preset="paper",
        wm_preset="paper",
        tokenizer_steps=100_000,
        tokenizer_batch_size=32,
        wm_steps=200_000,
        text_wm_steps=100_000,
        wm_batch_size=32,
        reward_model_steps=5000,
        mlp_steps=20_000,
        sft_batch_size=32,
        openvla_steps=20_000,
        openvla_base="openvla/openvla-7b",
        eval_episodes=50,
        eval_episode_length=160,
        ppo_iterations=200,
        ppo_minutes=None,
        ppo_critic_warmup=None,
        ppo_envs=64,
        ppo_episode_length=None,
        ppo_one_scene=True,
        reward_ablation=True,
        wm_starts_per_scene=None,
        table_episodes=50,
        table_episode_length=None,
        max_goal_steps=100,
        loader_workers=8,
        device="auto",
    ),
}

# The scales sized to judge the bench experiment's targets; the others only show every stage working.
JUDGED_SCALES = ("bench", "paper")

# The bench scale on a machine with a GPU: the models train longer (the world model is the part a GPU speeds up);
# the simulator, on the CPU either way, still bounds PPO in ManiSkill and the evaluation.
BENCH_ON_GPU = dict(
    tokenizer_steps=6000,
    tokenizer_batch_size=32,
    wm_steps=6000,
    text_wm_steps=3000,
    wm_batch_size=16,
    reward_model_steps=1000,
    ppo_envs=16,
    ppo_minutes=15.0,
)


@dataclass
class PipelineConfig:
    """Args:
    scale: "tiny" (default), "smoke", "bench" or "paper": sets every field left unset below (bench grows on a GPU:
        BENCH_ON_GPU).
    output_dir: where every artifact goes. A rerun skips each stage whose outputs are complete and were made with
        the same settings (so a killed run resumes); --fresh=true starts over.
    fresh: retrain everything, ignoring what output_dir holds.
    stop_after: run the stages up to this one and stop (a stage's name, e.g. "tokenizer": the data and the tokenizer
        that scripts/experiments/device_world_models.sh packs for a GPU); null: every stage.
    report_dir: also write the experiment's report (report.md, results.json, figures) here.
    families: task families to collect and evaluate.
    scenes: IND scenes per family (null: all).
    episodes_per_scene: planner episodes per (family, IND scene), a quarter of them deliberately failed.
    explore_episodes_per_scene: exploratory episodes per (family, IND scene), noisy, excursion and random dealt
        evenly (demos/exploration.py): a dataset of their own that only the action world model trains on.
    exploration_share: share of the action world model's training clips drawn from the exploratory episodes.
    heldout_scenes: OOD scenes of the held-out collection (4 episodes per family and scene, half of them failed)
        that the fidelity, done and reward reports are measured on, and of the controllability set's starts; with
        them, a validation collection (one episode per IND scene, half failed) on which the done threshold is
        chosen. 0: one recorded and converted IND episode instead, and the done threshold chosen on the
        demonstrations.
    report_episodes: held-out episodes (spread over the held-out dataset) behind the fidelity and reward reports.
    image_size: camera resolution.
    workers: ManiSkill worker processes (collection, and evaluations run side by side).
    tokenizer_preset: "tiny", "bench" or "paper".
    wm_preset: "tiny", "bench" or "paper" (the world models').
    tokenizer_steps: training steps of the tokenizer.
    tokenizer_batch_size: frames per tokenizer training step.
    wm_steps: training steps of the action world model.
    text_wm_steps: training steps of the text world model.
    wm_batch_size: clips per world-model training step.
    reward_model_steps: training steps of each baseline reward model (embedding, proxy); 0 skips them.
    mlp_steps: lerobot-train steps of the MLP policy.
    sft_batch_size: lerobot-train batch size of the MLP policy.
    openvla_steps: lerobot-train steps of OpenVLA (LoRA); 0 skips it. With OpenVLA, the table has its rows too.
    openvla_base: OpenVLA base model: "tiny" (random, CPU) or a checkpoint such as openvla/openvla-7b.
    eval_episodes: episodes of the lerobot-eval run in roboscape_wm.
    eval_episode_length: steps per lerobot-eval episode.
    ppo_iterations: PPO iterations in each env (one episode per parallel env each), at most.
    ppo_minutes: wall-clock budget of each PPO run (null: none), so that RL in the world model and in the
        simulator get the same time.
    ppo_critic_warmup: PPO's first iterations that train the critic only (null: the policy type's default); a
        run of a few iterations (CPU) keeps it at 1 so that the policy learns at all.
    ppo_envs: parallel episodes of PPO.
    ppo_episode_length: steps per PPO episode; null: per task family, its longest successful demonstration.
    ppo_one_scene: also run PPO in the simulator in one scene per family, as the paper's baseline did.
    reward_ablation: also run PPO in the world model on its sparse reward only and on its dense reward only (each
        evaluated out of domain).
    wm_starts_per_scene: demonstrations per (family, scene) whose first frames start PPO's world-model episodes
        (null: all); each start's goal is generated once, before PPO.
    table_episodes: simulator episodes per (split, family) behind each cell of Table 1.
    table_episode_length: steps of those episodes; null: as ppo_episode_length.
    max_goal_steps: control steps the text world model may generate while looking for a goal (a frame per frame_skip).
    loader_workers: data-loading processes of lerobot-train (0 saves their start-up on tiny runs).
    device: "cpu", "cuda" or "auto".
    push_to_hub: upload every artifact to the Hub (needs `hf auth login`); otherwise write the repos to
        output_dir/hub.
    hub_namespace: the Hub user or organisation of the repos.
    """

    scale: str = "tiny"
    output_dir: str = "outputs/demo"
    fresh: bool = False
    stop_after: str | None = None
    report_dir: str | None = None
    families: list[str] | None = None
    scenes: int | None = None
    episodes_per_scene: int | None = None
    explore_episodes_per_scene: int | None = None
    exploration_share: float | None = None
    heldout_scenes: int | None = None
    report_episodes: int | None = None
    image_size: int | None = None
    workers: int | None = None
    tokenizer_preset: str | None = None
    wm_preset: str | None = None
    tokenizer_steps: int | None = None
    tokenizer_batch_size: int | None = None
    wm_steps: int | None = None
    text_wm_steps: int | None = None
    wm_batch_size: int | None = None
    reward_model_steps: int | None = None
    mlp_steps: int | None = None
    sft_batch_size: int | None = None
    openvla_steps: int | None = None
    openvla_base: str | None = None
    eval_episodes: int | None = None
    eval_episode_length: int | None = None
    ppo_iterations: int | None = None
    ppo_minutes: float | None = None
    ppo_critic_warmup: int | None = None
    ppo_envs: int | None = None
    ppo_episode_length: int | None = None
    ppo_one_scene: bool | None = None
    reward_ablation: bool | None = None
    wm_starts_per_scene: int | None = None
    table_episodes: int | None = None
    table_episode_length: int | None = None
    max_goal_steps: int | None = None
    loader_workers: int | None = None
    device: str | None = None
    push_to_hub: bool = False
    hub_namespace: str = "local"

    def __post_init__(self):
        if self.scale not in SCALES:
            raise InvalidInputError(f"--scale must be one of {list(SCALES)}, got {self.scale!r}")
        preset = dict(SCALES[self.scale])
        if self.scale == "bench" and self.device != "cpu" and torch.cuda.is_available():
            preset |= BENCH_ON_GPU
        for name, value in preset.items():
            if getattr(self, name) is None:
                setattr(self, name, list(value) if isinstance(value, list) else value)
        unknown = [f for f in self.families if f not in TASK_FAMILIES]
        if unknown:
            raise InvalidInputError(f"unknown task families {unknown}; choose from {list(TASK_FAMILIES)}")
