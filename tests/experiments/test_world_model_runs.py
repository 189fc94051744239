"""PPO in the world model run where the world models are: packed here without them, run there without the dataset,
and taken back as the experiment's own runs."""

import json
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from lerobot_roboscape.dataset.reader import open_dataset
from lerobot_roboscape.experiments import world_model_runs
from lerobot_roboscape.experiments.experiment import ExperimentConfig, take_world_model_runs
from lerobot_roboscape.experiments.pack_format import PLAN, RESULTS, ReplayPlan, read_plan, read_results, rollouts_file
from lerobot_roboscape.pipeline.layout import rl_dir
from lerobot_roboscape.pipeline.resume import STAGE_FILE
from lerobot_roboscape.reward.done_report import (
    DoneReportConfig,
    evaluate_done,
    load_token_episodes,
    save_token_episodes,
    token_episodes,
)
from lerobot_roboscape.rl.configuration_ppo import PPOConfig
from lerobot_roboscape.rl.policy_loading import load_policy
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.training.checkpoints import FINAL

FRAME_SKIP = 4  # the test world models'


@pytest.fixture
def done_sets(demo_dataset, trained_tokenizer):
    """The demo dataset (two failed episodes among six) as the done report's validation and held-out episodes."""
    _, root = demo_dataset
    tokenizer = VisualTokenizer.from_pretrained(trained_tokenizer).eval()
    episodes = token_episodes(open_dataset("test/demos", root), tokenizer, FRAME_SKIP, "cpu")
    return {"validation": episodes, "heldout": episodes}


def tiny_runs(env_config, mlp_checkpoint, iterations: int) -> tuple:
    """The world-model env of a few steps, a PPO run of `iterations` in it, and the env with the ensemble's lever."""
    env = env_config(episode_length=3, max_goal_steps=3, similarity="tokenizer", split="", device="cpu")
    ppo = PPOConfig(
        policy_path=str(mlp_checkpoint),
        env=env,
        num_envs=2,
        iterations=iterations,
        save_freq=1,
        critic_warmup_iterations=1,
        minibatch_size=4,
        device="cpu",
        mixed_precision="no",
    )
    return env, ppo, replace(env, ensemble=[world_model_runs.ON_DEVICE], disagreement_penalty=1.0)


def test_the_done_report_reads_token_episodes_as_it_reads_the_dataset(
    demo_dataset, trained_tokenizer, world_models, done_sets, tmp_path
):
    _, root = demo_dataset
    common = dict(tokenizer=str(trained_tokenizer), world_model=str(world_models["action"]), device="cpu")
    from_data = evaluate_done(
        DoneReportConfig(
            dataset=replace(DoneReportConfig().dataset, repo_id="test/demos", root=str(root)),
            validation=replace(DoneReportConfig().validation, repo_id="test/demos", root=str(root)),
            output_dir=tmp_path / "data",
            **common,
        )
    )
    files = {name: save_token_episodes(e, FRAME_SKIP, tmp_path / f"{name}.st", name) for name, e in done_sets.items()}
    from_tokens = evaluate_done(
        DoneReportConfig(
            dataset_tokens=str(files["heldout"]),
            validation_tokens=str(files["validation"]),
            output_dir=tmp_path / "tokens",
            **common,
        )
    )
    assert from_tokens["chosen"] == from_data["chosen"] and from_data["chosen"]["theta_from"] == "validation"
    assert from_tokens["sources"] == from_data["sources"] and from_tokens["episodes"] == from_data["episodes"]
    with pytest.raises(ValueError, match="frame skip is 2"):  # episodes for a model of another frame skip
        load_token_episodes(files["validation"], 2, "cpu")


def test_runs_packed_here_run_without_the_dataset_and_come_back_as_the_experiments_own(
    trained_tokenizer, world_models, mlp_checkpoint, env_config, done_sets, tmp_path
):
    env, ppo, ensemble = tiny_runs(env_config, mlp_checkpoint, iterations=3)
    jobs = {
        "plain": world_model_runs.Job("RL w. World Model", ppo),
        "kl": world_model_runs.Job("RL w. World Model, KL to SFT", replace(ppo, kl_coef=0.1)),
        "ensemble": world_model_runs.Job("RL w. World Model, ensemble disagreement", replace(ppo, env=ensemble), True),
        "branched": world_model_runs.Job(
            "RL w. World Model, branched short rollouts", replace(ppo, env=replace(env, branches_per_episode=2))
        ),
    }
    pack = world_model_runs.pack(
        tmp_path / "wm_runs" / "pack",
        jobs,
        mlp_checkpoint,
        trained_tokenizer,
        done_sets,
        FRAME_SKIP,
        replay={"episodes": 2},
        curve_checkpoints=2,
    )
    plan = read_plan(pack)
    assert sorted(p.name for p in pack.glob("starts_*")) == ["starts_0.safetensors", "starts_1.safetensors"]
    assert all("dataset_root" not in run.env and "tokenizer" not in run.env for run in plan.runs.values())
    assert plan.replay == ReplayPlan(2) and plan.runs["ensemble"].ensemble and plan.curve_checkpoints == 2

    out = tmp_path / "wm_runs" / "runs"
    results = world_model_runs.run_pack(
        world_model_runs.RunPackConfig(
            pack=str(pack),
            action=str(world_models["action"]),
            text=str(world_models["text"]),
            members=[str(world_models["action"])],
            output_dir=str(out),
            device="cpu",
        )
    )
    assert set(results.runs) == set(jobs) and (out / world_model_runs.GOALS).is_file()
    assert results.done == json.loads((out / "done_report" / "done_report.json").read_text())["chosen"]
    for tag, run in results.runs.items():
        kept = sorted(p.name for p in (out / "rl" / tag / "checkpoints").iterdir() if p.name.isdigit())
        assert kept == ["00000001", "00000003"], tag  # the curve's two: the first and the last
        weights = load_file(out / run.final / "model.safetensors")
        assert {v.dtype for v in weights.values() if v.is_floating_point()} == {torch.bfloat16}
        assert not list((out / "rl" / tag).rglob("optimizer_state.safetensors"))
    history = [json.loads(line) for line in (out / "rl" / "ensemble" / "history.jsonl").read_text().splitlines()]
    assert "charts/disagreement" in history[0]  # the members reached the ensemble's env
    assert results.replays == {tag: rollouts_file(tag) for tag in jobs}  # every run's policy, for its replay
    rollouts = world_model_runs.load_rollouts(out / rollouts_file("plain"))
    assert rollouts.frames.shape[:2] == (rollouts.actions.shape[0] + 1, 2) and len(rollouts.starts) == 2
    assert rollouts.cameras and all(start.task_family and start.scene for start in rollouts.starts)

    # Here: the experiment takes them as its own runs, once, and again when other results come back.
    protocol = tmp_path / "run" / "protocol_paper"
    cfg = ExperimentConfig(world_model_runs=str(tmp_path / "wm_runs"))
    taken = take_world_model_runs(cfg, protocol, out, "roboscape_mlp")
    final = taken.runs["RL w. World Model"]
    taken_run = protocol / rl_dir("roboscape_mlp", "RL w. World Model")
    assert final == taken_run / FINAL  # the run's published model, its last checkpoint's
    here = load_file(final / "model.safetensors")
    there = load_file(out / results.runs["plain"].final / "model.safetensors")
    assert all(here[k].dtype == torch.float32 and torch.equal(here[k], there[k].float()) for k in there)
    load_policy(final, "cpu")
    record = json.loads((taken_run / STAGE_FILE).read_text())
    assert record["seconds"] == pytest.approx(results.runs["plain"].seconds)
    written = (taken_run / STAGE_FILE).stat().st_mtime_ns
    take_world_model_runs(cfg, protocol, out, "roboscape_mlp")
    assert (taken_run / STAGE_FILE).stat().st_mtime_ns == written
    # A run that failed there is left out, the others taken; without the plain run's rollouts, nothing is.
    failed = {"method": "RL w. World Model, KL to SFT", "folder": "rl/kl", "error": "RuntimeError: out of memory"}
    written_results = results.to_json()
    (out / RESULTS).write_text(json.dumps(written_results | {"runs": written_results["runs"] | {"kl": failed}}))
    taken = take_world_model_runs(cfg, protocol, out, "roboscape_mlp")
    assert "RL w. World Model, KL to SFT" not in taken.runs and len(taken.runs) == 3
    assert (taken_run / STAGE_FILE).stat().st_mtime_ns != written  # other results: taken again
    (out / RESULTS).write_text(json.dumps({k: v for k, v in written_results.items() if k != "replays"}))
    with pytest.raises(FileNotFoundError, match="did not come back"):
        take_world_model_runs(cfg, protocol, out, "roboscape_mlp")


def test_a_pack_or_results_of_another_kind_are_refused_by_name(tmp_path):
    with pytest.raises(FileNotFoundError, match="plan.json is missing"):
        read_plan(tmp_path)
    (tmp_path / PLAN).write_text(json.dumps({"format": 99}))
    with pytest.raises(ValueError, match="format 99"):
        read_plan(tmp_path)
    with pytest.raises(FileNotFoundError, match="have not been brought back"):
        read_results(tmp_path, "RL w. World Model")
    with pytest.raises(ValueError, match="refresh"):
        ExperimentConfig(world_model_runs=str(tmp_path), levers=["refresh"])


def test_the_experiment_names_what_it_needs_without_world_models(tmp_path):
    from lerobot_roboscape.experiments.trained import trained_stages
    from lerobot_roboscape.pipeline.config import PipelineConfig

    with pytest.raises(FileNotFoundError, match="--stop_after=tokenizer"):
        trained_stages(PipelineConfig(output_dir=str(tmp_path)), Path(tmp_path), world_models=False)


def test_without_members_the_ensemble_run_fails_alone_and_the_others_run(
    trained_tokenizer, world_models, mlp_checkpoint, env_config, done_sets, tmp_path
):
    """A lease whose ensemble members did not save in their budget still brings back the other runs."""
    _, ppo, ensemble = tiny_runs(env_config, mlp_checkpoint, iterations=1)
    jobs = {
        "plain": world_model_runs.Job("RL w. World Model", ppo),
        "ensemble": world_model_runs.Job("RL w. World Model, ensemble disagreement", replace(ppo, env=ensemble), True),
    }
    pack = world_model_runs.pack(
        tmp_path / "pack", jobs, mlp_checkpoint, trained_tokenizer, done_sets, FRAME_SKIP, curve_checkpoints=1
    )
    out = tmp_path / "runs"
    results = world_model_runs.run_pack(
        world_model_runs.RunPackConfig(
            pack=str(pack), **{k: str(v) for k, v in world_models.items()}, output_dir=str(out), device="cpu"
        )
    )
    assert results.runs["ensemble"].error == "no ensemble member was given"
    assert not (out / "rl" / "ensemble").exists()
    assert results.runs["plain"].error is None and (out / results.runs["plain"].final).is_dir()
    assert json.loads((out / RESULTS).read_text()) == results.to_json()
