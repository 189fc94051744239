"""`roboscape-demo` at its smallest, end to end: every artifact it names exists and loads, and a rerun skips the
completed stages."""

import json

import draccus
import numpy as np
import pytest
from huggingface_hub import ModelCard
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.envs.world_model_env import RoboscapeWorldModelEnv
from lerobot_roboscape.pipeline.config import PipelineConfig
from lerobot_roboscape.pipeline.experiment import ExperimentConfig, run_experiment
from lerobot_roboscape.pipeline.experiment_report import README_BEGIN, README_END
from lerobot_roboscape.pipeline.run import run_pipeline
from lerobot_roboscape.rl.policy_loading import load_policy

pytestmark = pytest.mark.slow  # the simulator, or commands in subprocesses


def test_demo_smoke_scale_end_to_end(tmp_path, capsys):
    out = tmp_path / "demo"
    args = ["--scale=smoke", f"--output_dir={out}", f"--report_dir={tmp_path / 'report'}"]
    artifacts = run_pipeline(draccus.parse(PipelineConfig, args=args))
    summary = capsys.readouterr().out.split("=== results")[1]

    for name, artifact in artifacts.items():
        assert artifact.path.exists(), f"{name}: {artifact.path}"
        assert f"{name} " in summary and str(artifact.path) in summary  # named, with what it loaded as
    hub = out / "hub"
    assert {
        "dataset repo",
        "world models repo",
        "roboscape_mlp sft repo",
        "roboscape_mlp ppo_maniskill repo",
        "roboscape_mlp ppo_world_model repo",
        "Table 1",
        "fidelity report",
        "reward report",
        "experiment report",
        "roboscape_mlp lerobot-eval in roboscape_wm",
    } <= set(artifacts)

    # The pushed dataset and world models drive a roboscape_wm env on their own.
    dataset_repo = hub / "datasets" / "local" / "roboscape_demos"
    assert len(LeRobotDataset("local/roboscape_demos", root=dataset_repo)) > 0
    env = RoboscapeWorldModelEnv(
        RoboscapeWorldModelEnvConfig(
            world_models=str(hub / "local" / "roboscape_world_models"),
            dataset_root=str(dataset_repo),
            allow_random_lpips=True,
            episode_length=2,
            max_goal_steps=2,
        ),
        num_envs=1,
    )
    obs, _ = env.reset(seed=0)
    _, reward, *_ = env.step(np.zeros((1, 7), np.float32))
    assert np.isfinite(reward).all()

    wm_card = ModelCard.load(hub / "local" / "roboscape_world_models" / "README.md")
    assert "world-model" in wm_card.data.tags and "PSNR" in wm_card.text and "No fidelity report" not in wm_card.text
    for method in ("sft", "ppo_maniskill", "ppo_world_model"):
        repo = hub / "local" / f"roboscape_mlp_{method}"
        policy, _, _ = load_policy(repo, "cpu")
        assert policy.config.type == "roboscape_mlp"
        card = ModelCard.load(repo / "README.md")
        assert card.data.datasets == ["local/roboscape_demos"]
        assert ("reinforcement-learning" in card.data.tags) == (method != "sft")
        assert "| IND | push |" in card.text  # its success table

    tables = json.loads((out / "tables" / "tables.json").read_text())["roboscape_mlp"]
    assert len(tables) == 3 and all(set(cells) == {"ind", "ood"} for cells in tables.values())
    results = json.loads((tmp_path / "report" / "results.json").read_text())
    assert results["table"]["roboscape_mlp"] == tables and results["targets"]
    assert (tmp_path / "report" / "tokenizer_reconstruction.png").is_file()

    # A rerun with the same settings skips every completed stage: nothing is trained again.
    tokenizer_weights = (out / "tokenizer" / "pretrained_model" / "model.safetensors").stat().st_mtime_ns
    run_pipeline(draccus.parse(PipelineConfig, args=args))
    assert (out / "tokenizer" / "pretrained_model" / "model.safetensors").stat().st_mtime_ns == tokenizer_weights
    assert "done in 0s" in capsys.readouterr().out

    # The claim experiment on the same run: its PPO runs and Table 1 are the pipeline's (skipped), the rest new.
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{README_BEGIN}\nold\n{README_END}\nrest\n")
    experiment = draccus.parse(
        ExperimentConfig,
        args=[
            "--pipeline.scale=smoke",
            f"--pipeline.output_dir={out}",
            "--curve_episodes=1",
            "--replay_episodes=1",
            f"--report_dir={tmp_path / 'claim'}",
            f"--readme={readme}",
        ],
    )
    report = run_experiment(experiment)
    claim = json.loads((tmp_path / "claim" / "results.json").read_text())
    assert claim["table"]["roboscape_mlp"] == tables  # the pipeline's evaluations, not new ones
    assert [point["iteration"] for point in claim["curve"]] == [0, 1]  # SFT, then PPO's one checkpoint
    assert "roboscape_mlp, OOD Push: PPO in WM minus SFT" in claim["targets"]
    replay = claim["replays"][0]
    assert (tmp_path / "claim" / "videos" / replay["video"]).is_file() and replay["family"] == "push"
    assert "| Supervised finetune |" in report.read_text() and (tmp_path / "claim" / "curve.png").is_file()
    text = readme.read_text()
    assert "old" not in text and "PPO in WM minus SFT" in text and text.endswith(f"{README_END}\nrest\n")
