"""A run's completed stages carried to another machine: what travels (stage folders, the goals and the trajectory
file; not checkpoints, token caches, object masks nor unfinished work), and that the run they are taken into skips
them, as the run they came from did; an SFT run travels with its model."""

import json
import shutil
from dataclasses import dataclass

import pytest

from lerobot_roboscape.dataset.segmentation import SEGMENTATION_DIR, SEGMENTATION_META, has_masks
from lerobot_roboscape.pipeline import layout, methods, resume
from lerobot_roboscape.pipeline.carried_stages import MANIFEST, carry_stages, completed_stages, take_stages
from lerobot_roboscape.training.checkpoints import CHECKPOINTS, FINAL, LAST, publish_final
from roboscape_core.errors import InvalidInputError, MissingInputError


@dataclass
class Stage:
    model: str
    steps: int = 10


def _write(path):
    path.parent.mkdir(parents=True)
    path.write_text("{}")


def _run(out):
    """A run of three stages (a model, a report reading it, a PPO run inside the protocol's folder), one stage left
    unfinished and the caches and checkpoints a run keeps beside them; returns the settings of the report."""
    model, report = out / layout.world_model_dir("action"), out / layout.DONE_REPORT_DIR
    resume.train_once(model, Stage("none"), False, lambda _: (model / FINAL).mkdir(parents=True))
    (model / FINAL / "model.safetensors").write_bytes(b"w" * 100)
    (model / CHECKPOINTS / "000100").mkdir(parents=True)
    (model / CHECKPOINTS / "000100" / "model.safetensors").write_bytes(b"c" * 1000)
    settings = Stage(str(model / FINAL))
    resume.run_once(report, settings, False, lambda: _write(report / "done_report.json"))
    ppo = out / "protocol_paper" / layout.rl_dir("roboscape_mlp", methods.RL_WORLD_MODEL)
    resume.run_once(ppo, Stage("sft"), False, lambda: (ppo / FINAL).mkdir(parents=True))
    (out / layout.TOKEN_CACHE_DIR / "action").mkdir(parents=True)
    resume.mark_done(out / layout.TOKEN_CACHE_DIR / "action", Stage("cache"))
    (out / "datasets" / ".roboscape_demos.episodes").mkdir(parents=True)
    resume.mark_done(out / "datasets" / ".roboscape_demos.episodes", Stage("half collected"))
    demos = out / layout.DEMOS_DIR
    resume.run_once(demos, Stage("collect"), False, lambda: _write(demos / SEGMENTATION_META))
    (demos / SEGMENTATION_DIR / "episode_000000.npz").parent.mkdir()
    (demos / SEGMENTATION_DIR / "episode_000000.npz").write_bytes(b"m" * 10_000)
    (out / layout.GOAL_FILE).parent.mkdir(parents=True, exist_ok=True)
    (out / layout.GOAL_FILE).write_bytes(b"g")
    (out / layout.TRAJECTORIES_DIR).mkdir()
    (out / layout.TRAJECTORIES_DIR / "trajectory.h5").write_bytes(b"h5")
    return settings


def test_a_runs_stages_carried_to_another_machine_are_skipped_there(tmp_path):
    out, carried = tmp_path / "outputs" / "bench", tmp_path / "carried" / "bench_run"
    settings = _run(out)
    ppo = "protocol_paper/rl/roboscape_mlp/ppo_world_model"
    assert completed_stages(out) == [layout.DEMOS_DIR, "done_report", ppo, "world_model_action"]
    assert has_masks(out / layout.DEMOS_DIR)
    sizes = carry_stages(out, carried)
    assert set(sizes) == {*completed_stages(out), layout.GOAL_FILE, layout.TRAJECTORIES_DIR}
    assert not list(carried.rglob(CHECKPOINTS)) and not (carried / layout.TOKEN_CACHE_DIR).exists()
    assert not (carried / "datasets" / ".roboscape_demos.episodes").exists()  # a collection under way stays
    assert not has_masks(carried / layout.DEMOS_DIR) and not (carried / layout.DEMOS_DIR / SEGMENTATION_DIR).exists()
    assert sizes["world_model_action"] < 1000  # the model, not the checkpoint a killed run resumes from

    shutil.rmtree(out)  # the next machine: the same checkout, an empty run
    assert sorted(take_stages(carried, out)) == sorted(sizes)
    assert resume.run_once(out / layout.DONE_REPORT_DIR, settings, False, pytest.fail) is False
    assert resume.is_done(out / layout.world_model_dir("action"), Stage("none"), False)
    assert (out / layout.GOAL_FILE).read_bytes() == b"g"
    assert (out / layout.TRAJECTORIES_DIR / "trajectory.h5").read_bytes() == b"h5"

    (out / layout.DONE_REPORT_DIR / "done_report.json").write_text('{"kept": true}')
    assert take_stages(carried, out) == []  # what the run completed since is kept
    assert json.loads((out / layout.DONE_REPORT_DIR / "done_report.json").read_text()) == {"kept": True}


def test_stages_are_taken_only_into_the_run_they_came_from(tmp_path):
    out, carried = tmp_path / "run", tmp_path / "carried"
    _run(out)
    carry_stages(out, carried)
    with pytest.raises(InvalidInputError, match=rf"carried/{MANIFEST}: its stages ran in {out}.*not into"):
        take_stages(carried, tmp_path / "elsewhere")
    with pytest.raises(MissingInputError, match=rf"nothing/{MANIFEST} does not exist"):
        take_stages(tmp_path / "nothing", out)
    with pytest.raises(MissingInputError, match="holds no completed stage"):
        carry_stages(tmp_path / "empty", tmp_path / "none")
    assert not (tmp_path / "none").exists()


def test_an_sft_run_travels_with_the_model_lerobot_train_kept_in_its_newest_checkpoint(tmp_path):
    out, carried = tmp_path / "run", tmp_path / "carried"
    sft = out / "protocol_paper" / layout.sft_dir("roboscape_mlp")

    def lerobot_train():  # its layout: checkpoints/<step>/pretrained_model, `last` a link to the newest
        (sft / CHECKPOINTS / "010000" / FINAL).mkdir(parents=True)
        (sft / CHECKPOINTS / "010000" / FINAL / "model.safetensors").write_bytes(b"w")
        (sft / CHECKPOINTS / LAST).symlink_to("010000")

    resume.run_once(sft, Stage("demos"), False, lerobot_train)
    assert publish_final(sft) == sft / FINAL
    carry_stages(out, carried)
    shutil.rmtree(out)
    take_stages(carried, out)
    assert not (sft / CHECKPOINTS).exists()
    assert publish_final(sft) == sft / FINAL and (sft / FINAL / "model.safetensors").read_bytes() == b"w"

    shutil.rmtree(sft / FINAL)  # a run carried before its model was published: said, not loaded as nothing
    with pytest.raises(MissingInputError, match=rf"{sft} holds neither {FINAL}/ nor {CHECKPOINTS}/{LAST}/{FINAL}/"):
        publish_final(sft)
