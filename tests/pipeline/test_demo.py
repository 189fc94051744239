"""`roboscape-demo` and `roboscape-experiment` at their smallest, end to end, as a user runs them: each SIGKILLed at
every stage boundary and run again ends with the outputs of an uninterrupted run; every artifact the demo names
exists and loads; and a rerun skips the completed stages."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from huggingface_hub import ModelCard
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.envs.world_model_env import RoboscapeWorldModelEnv
from lerobot_roboscape.experiments.claim_markdown import README_BEGIN, README_END
from lerobot_roboscape.experiments.experiment import STEPS, ExperimentConfig, run_experiment, run_or_pack
from lerobot_roboscape.pipeline.clock import header
from lerobot_roboscape.pipeline.config import PipelineConfig, parse_config
from lerobot_roboscape.pipeline.resume import STAGE_FILE
from lerobot_roboscape.pipeline.run import STAGES, run_pipeline
from lerobot_roboscape.rl.policy_loading import load_policy
from roboscape_core.errors import MissingInputError
from tests.harness import command, kill_at_line, output_differences, run

pytestmark = [pytest.mark.slow, pytest.mark.e2e]  # the simulator, or commands in subprocesses


def killed_at_every_boundary(name: str, args: list[str], stages: tuple[str, ...], out: Path) -> list[str]:
    """Run the command SIGKILLed as each stage after the first begins (the one before it just complete), each
    kill's rerun resuming the last, and then to its end. Returns the stage records that a later rerun wrote
    again: a stage that completed before a kill must be skipped after it, not run again."""
    completed: dict[Path, int] = {}
    for number in range(2, len(stages) + 1):
        kill_at_line(command(name, *args), header(number, len(stages)))
        completed |= {p: p.stat().st_mtime_ns for p in out.rglob(STAGE_FILE) if p not in completed}
    run(command(name, *args))
    return [str(p) for p, written in completed.items() if not p.is_file() or p.stat().st_mtime_ns != written]


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The smoke demo killed at every stage boundary, its folders then moved aside to killed/, and run again
    uninterrupted in the same folders. Returns (base folder, the uninterrupted run's output, the stages run again
    after a kill, what differs between the two runs' outputs)."""
    base = tmp_path_factory.mktemp("demo")
    args = ["--scale=smoke", f"--output_dir={base / 'demo'}", f"--report_dir={base / 'report'}"]
    run_again = killed_at_every_boundary("demo", args, STAGES, base / "demo")
    (base / "killed").mkdir()
    for folder in ("demo", "report"):
        (base / folder).rename(base / "killed" / folder)
    stdout = run(command("demo", *args)).stdout
    # Compared now, before the experiment writes into the demo's folders.
    differences = [*output_differences(base / "killed" / "demo", base / "demo")]
    differences += output_differences(base / "killed" / "report", base / "report")
    return base, stdout, run_again, differences


@pytest.fixture(scope="module")
def experiment(demo):
    """The smoke experiment on the demo's outputs, killed at every step boundary (its folders then moved aside to
    killed_experiment/), and run again uninterrupted on the same demo outputs. Returns (its arguments but the
    README's, the steps run again after a kill, what differs between the two runs' outputs)."""
    base = demo[0]
    args = [
        "--protocol=all_scenes",  # the pipeline's own SFT: the experiment reuses its PPO runs and evaluations
        "--pipeline.scale=smoke",
        f"--pipeline.output_dir={base / 'demo'}",
        "--curve_episodes=1",
        "--replay_rollouts=1",
        "--replay_episodes=1",
        f"--report_dir={base / 'claim'}",
    ]
    shutil.copytree(base / "demo", base / "before_experiment", symlinks=True)
    run_again = killed_at_every_boundary("experiment", [*args, "--readme=null"], STEPS, base / "demo")
    (base / "killed_experiment").mkdir()
    for folder in ("demo", "claim"):
        (base / folder).rename(base / "killed_experiment" / folder)
    (base / "before_experiment").rename(base / "demo")
    run(command("experiment", *args, "--readme=null"))
    differences = [*output_differences(base / "killed_experiment" / "demo", base / "demo")]
    differences += output_differences(base / "killed_experiment" / "claim", base / "claim")
    return args, run_again, differences


def test_demo_killed_at_every_stage_boundary_ends_as_an_uninterrupted_run(demo):
    _, _, run_again, differences = demo
    assert not run_again, f"completed stages ran again after a kill: {run_again}"
    assert not differences, f"differ beyond timing: {differences}"


def test_experiment_killed_at_every_step_boundary_ends_as_an_uninterrupted_run(experiment):
    _, run_again, differences = experiment
    assert not run_again, f"completed steps ran again after a kill: {run_again}"
    assert not differences, f"differ beyond timing: {differences}"


def test_demo_smoke_scale_end_to_end(demo, experiment, capsys):
    base, stdout, _, _ = demo
    out, tmp_path = base / "demo", base
    args = ["--scale=smoke", f"--output_dir={out}", f"--report_dir={base / 'report'}"]
    tokenizer_weights = (out / "tokenizer" / "pretrained_model" / "model.safetensors").stat().st_mtime_ns
    artifacts = run_pipeline(parse_config(PipelineConfig, args))
    # A rerun with the same settings skips every completed stage: nothing is trained again.
    assert (out / "tokenizer" / "pretrained_model" / "model.safetensors").stat().st_mtime_ns == tokenizer_weights
    assert "done in 0s" in capsys.readouterr().out
    summary = stdout.split("=== results")[1]  # the uninterrupted run's

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

    # The claim experiment on the same run (its steps complete, it writes the report and the README's block): its
    # PPO runs and Table 1 are the pipeline's.
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{README_BEGIN}\nold\n{README_END}\nrest\n")
    report = run_experiment(parse_config(ExperimentConfig, [*experiment[0], f"--readme={readme}"], "pipeline."))
    claim = json.loads((tmp_path / "claim" / "results.json").read_text())
    assert claim["table"]["roboscape_mlp"] == tables  # the pipeline's evaluations, not new ones
    assert [point["iteration"] for point in claim["curve"]] == [0, 1]  # SFT, then PPO's one checkpoint
    assert "roboscape_mlp, OOD Push: PPO in WM minus SFT" in claim["targets"]
    replay = claim["replays"][0]
    assert (tmp_path / "claim" / "videos" / replay["video"]).is_file() and replay["family"] == "push"
    assert "| Supervised finetune |" in report.read_text() and (tmp_path / "claim" / "curve.png").is_file()
    assert (tmp_path / "claim" / "gaming.png").is_file()
    assert any("checkpoint curve" in name for name in claim["targets"])
    assert report.read_text().splitlines()[2] == "**Does RL in the world model make the policy better out of domain?**"
    text = readme.read_text()
    assert "old" not in text and "PPO in WM minus SFT" in text and text.endswith(f"{README_END}\nrest\n")


def test_the_runs_in_the_world_model_go_where_its_models_are_and_come_back(demo, experiment, tmp_path):
    """--world_model_runs: the first run packs the runs in the world model and does the simulator's part; the runs,
    made elsewhere (here on the CPU, with the demo's models), are taken back by the same command, which goes on.
    SFT imitates demonstrations collected in the initial scene for it (--pipeline.data.initial_scene_episodes)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    from lerobot_roboscape.experiments.levers import LEVERS
    from lerobot_roboscape.experiments.world_model_runs import RunPackConfig, run_pack
    from lerobot_roboscape.pipeline.layout import INITIAL_SCENE_DIR, INITIAL_SCENE_REPO_ID, eval_dir, rl_dir, sft_dir
    from lerobot_roboscape.pipeline.methods import RL_MANISKILL, RL_WORLD_MODEL, SFT, Method, initial_scene

    run = demo[0] / "demo"
    args = [
        "--protocol=paper",
        "--pipeline.scale=smoke",
        f"--pipeline.output_dir={run}",
        "--pipeline.data.initial_scene_episodes=1",
        "--levers=[kl]",
        "--curve_episodes=1",
        "--replay_rollouts=1",
        "--replay_episodes=1",
        f"--world_model_runs={tmp_path}",
        f"--report_dir={tmp_path / 'claim'}",
        "--readme=null",
    ]
    cfg = parse_config(ExperimentConfig, args, "pipeline.")
    with pytest.raises(MissingInputError, match="the runs in the world model are not back in"):
        run_experiment(cfg)
    pack = run_or_pack(cfg).folder
    assert pack == tmp_path / "pack" and not (tmp_path / "claim").exists()
    protocol = run / "protocol_paper"
    assert (protocol / rl_dir("roboscape_mlp", RL_MANISKILL) / STAGE_FILE).is_file()  # done here meanwhile
    initial = LeRobotDatasetMetadata(INITIAL_SCENE_REPO_ID, root=run / INITIAL_SCENE_DIR)
    assert initial.total_episodes == 1  # the one push attempt there, a success
    sft_settings = json.loads((protocol / sft_dir("roboscape_mlp") / STAGE_FILE).read_text())["settings"]
    assert f"--dataset.root={run / INITIAL_SCENE_DIR}" in sft_settings and "--dataset.episodes=[0]" in sft_settings
    assert not (protocol / rl_dir("roboscape_mlp", RL_WORLD_MODEL)).exists()

    models = {c: str(run / f"world_model_{c}" / "pretrained_model") for c in ("action", "text")}
    run_pack(RunPackConfig(pack=str(pack), **models, output_dir=str(tmp_path / "runs"), device="cpu"))
    report = run_or_pack(cfg)
    claim = json.loads((tmp_path / "claim" / "results.json").read_text())
    assert claim["world_model_runs"]["folder"] == str(tmp_path / "runs") and "--world_model_runs" in report.read_text()
    kl = LEVERS["kl"].method
    assert {RL_WORLD_MODEL, kl, RL_MANISKILL} <= {r["method"] for r in claim["ppo_runs"]}
    assert claim["replays"] and claim["lever_curves"][kl] and claim["lever_replays"][kl]  # every run is replayed
    assert (tmp_path / "claim" / f"replay_{Method.named(kl).tag}.png").is_file()
    assert "The signal each run in the world model got" in report.read_text()
    # The paper's IND, the scene SFT learned with new initial states, is a column of its own for every method.
    assert all(list(splits) == ["scene", "ind", "ood"] for splits in claim["table"]["roboscape_mlp"].values())
    scene_eval = json.loads((protocol / eval_dir("roboscape_mlp", SFT) / "scene" / STAGE_FILE).read_text())
    assert scene_eval["settings"]["scenes"] == [initial_scene()] and scene_eval["settings"]["splits"] == ["ind"]
    assert "| Policy | Training method | Scene " in report.read_text()
