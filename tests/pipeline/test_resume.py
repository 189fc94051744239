"""The pipeline's stage bookkeeping: a completed stage is skipped only when its settings are unchanged, and an
interrupted training stage resumes only into a run of the same settings."""

import json
from dataclasses import dataclass, replace

import pytest

from lerobot_roboscape.pipeline import resume
from lerobot_roboscape.tasks import select_scenes


@dataclass
class Settings:
    steps: int
    lr: float = 1e-3


def test_a_stage_is_done_only_with_the_same_settings(tmp_path, monkeypatch):
    folder = tmp_path / "tokenizer"
    assert not resume.is_done(folder, Settings(10), fresh=False)
    clock = iter([1000.0, 1007.5, 1007.5])  # starts at 1,000 s; marked done at 1,007.5 s (read twice there)
    monkeypatch.setattr(resume.time, "time", lambda: next(clock))
    resume.start(folder).mkdir()
    (folder / "weights").write_text("w")
    resume.mark_done(folder, Settings(10))
    assert resume.is_done(folder, Settings(10), fresh=False)
    assert resume.stage_seconds(folder) == pytest.approx(7.5)
    assert not resume.is_done(folder, Settings(11), fresh=False)  # changed settings: the stage runs again
    assert not resume.is_done(folder, Settings(10), fresh=True)


def test_a_setting_added_since_a_stage_ran_leaves_it_done_while_empty(tmp_path):
    from lerobot_roboscape.evaluation.success_rate import EvalConfig

    folder, cfg = tmp_path / "eval", EvalConfig(policy_path="p", splits=["ind"], output_dir=tmp_path / "eval")
    before = {k: v for k, v in resume._jsonable(cfg).items() if k != "scenes"}
    resume.start(folder).mkdir()
    resume.mark_done(folder, before)  # recorded before EvalConfig had `scenes`
    assert resume.is_done(folder, cfg, fresh=False)
    assert not resume.is_done(folder, replace(cfg, scenes=[select_scenes("ind")[0].id]), fresh=False)
    assert not resume.is_done(folder, replace(cfg, episodes=21), fresh=False)


def test_an_interrupted_stage_resumes_only_into_the_same_settings(tmp_path):
    folder = tmp_path / "world_model"
    assert resume.prepare(folder, Settings(10), fresh=False) is False  # nothing to resume: a new run
    (folder / "checkpoints").mkdir()  # the run is killed after a checkpoint
    assert resume.prepare(folder, Settings(10), fresh=False) is True
    assert (folder / "checkpoints").is_dir()
    assert resume.prepare(folder, Settings(10, lr=3e-4), fresh=False) is False  # other settings: cleared
    assert not (folder / "checkpoints").exists()


def test_run_once_runs_a_stage_once_per_settings(tmp_path):
    folder, runs = tmp_path / "report", []

    def work():
        runs.append(1)
        folder.mkdir()
        (folder / "report.json").write_text("{}")

    assert resume.run_once(folder, Settings(1), False, work) is True
    assert resume.run_once(folder, Settings(1), False, work) is False and len(runs) == 1
    (folder / "stale").write_text("from the earlier run")
    assert resume.run_once(folder, Settings(2), False, work) is True  # other settings: cleared, run again
    assert not (folder / "stale").exists() and len(runs) == 2


def test_train_once_resumes_a_killed_run_and_skips_a_finished_one(tmp_path):
    folder, seen = tmp_path / "world_model", []

    def killed(resume_from_checkpoint):
        seen.append(resume_from_checkpoint)
        (folder / "checkpoints").mkdir()
        raise KeyboardInterrupt  # killed after its first checkpoint

    with pytest.raises(KeyboardInterrupt):
        resume.train_once(folder, Settings(10), False, killed)
    assert resume.train_once(folder, Settings(10), False, seen.append) is True  # resumed, then marked done
    assert seen == [False, True] and (folder / "checkpoints").is_dir()
    assert resume.train_once(folder, Settings(10), False, seen.append) is False and seen == [False, True]


def test_a_finished_run_given_a_larger_budget_goes_on_and_any_other_change_starts_again(tmp_path):
    folder, seen, budgets = tmp_path / "ppo", [], ("time_budget_s",)

    def train(resume_from_checkpoint):
        seen.append(resume_from_checkpoint)
        (folder / "checkpoints").mkdir(exist_ok=True)

    settings = lambda budget, lr=1e-3: {"time_budget_s": budget, "lr": lr}  # noqa: E731
    assert resume.train_once(folder, settings(60.0), False, train, budgets) and seen == [False]
    assert resume.train_once(folder, settings(120.0), False, train, budgets) and seen == [False, True]
    assert (folder / "checkpoints").is_dir()
    assert not resume.train_once(folder, settings(120.0), False, train, budgets)  # done at that budget
    assert resume.train_once(folder, settings(None), False, train, budgets) and seen[-1] is True  # no limit: longer
    assert resume.train_once(folder, settings(30.0), False, train, budgets) and seen[-1] is False  # shorter: anew
    assert resume.train_once(folder, settings(240.0, lr=3e-4), False, train, budgets) and seen[-1] is False
    assert resume.train_once(folder, settings(480.0, lr=3e-4), False, train) and seen[-1] is False  # no budgets named


def test_a_stage_that_fills_its_config_in_place_is_still_skipped_next_time(tmp_path):
    # The world-model trainer fills its config's action statistics: the record must hold what was asked for.
    folder, runs = tmp_path / "world_model", []

    def train(resume_from: bool, settings: Settings) -> None:
        runs.append(resume_from)
        settings.lr = 0.5

    for _ in range(2):
        asked = Settings(10)
        resume.train_once(folder, asked, False, lambda r, s=asked: train(r, s))
        resume.run_once(tmp_path / "report", Settings(3), False, lambda: Settings(3).__setattr__("lr", 0.5))
    assert runs == [False]


@dataclass
class ReportSettings:
    model: str
    episodes: int = 4


def test_a_stage_reruns_when_a_model_it_reads_was_made_again_with_other_settings(tmp_path):
    """The report names the model by path; the model's stage retrained with other settings keeps the path, so the
    report is stale: it runs again. Retrained with the same settings (a resumed run), it stays done."""
    from lerobot_roboscape.training.checkpoints import FINAL

    model, report, runs = tmp_path / "world_model", tmp_path / "report", []

    def train(steps):
        resume.train_once(model, Settings(steps), False, lambda _: (model / FINAL).mkdir(exist_ok=True))

    def read():
        return resume.run_once(report, ReportSettings(str(model / FINAL)), False, lambda: runs.append(1))

    train(10)
    assert read() is True and read() is False
    train(10)
    assert read() is False
    train(20)
    assert read() is True and runs == [1, 1]
    assert not resume.is_done(tmp_path / "other", ReportSettings(str(tmp_path / "elsewhere" / FINAL)), False)


def test_world_models_trained_elsewhere_are_taken_once_and_checked(world_models, trained_tokenizer, tmp_path):
    """--world_models: each model is copied with its logs into the folder the run's own would train in, once; new
    weights there are taken again and rerun what read the old ones; a model of the wrong control, or none, is
    refused by name."""
    import shutil

    from lerobot_roboscape.pipeline import stages
    from lerobot_roboscape.pipeline.config import scale_config
    from lerobot_roboscape.pipeline.layout import world_model_dir
    from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
    from lerobot_roboscape.tokenizer.token_cache import tokenizer_fingerprint
    from lerobot_roboscape.training.checkpoints import FINAL
    from lerobot_roboscape.training.loop import TRAIN_CONFIG
    from roboscape_core.errors import InvalidInputError, MissingInputError
    from tests.harness import assert_same_weights

    given, out = tmp_path / "from_gpu", tmp_path / "run"
    for control, model in world_models.items():
        shutil.copytree(model, given / control / FINAL)
        shutil.copy2(model.parent / TRAIN_CONFIG, given / control)  # names the tokenizer it learned from
        (given / control / "heldout_curve.jsonl").write_text('{"step": 1}\n')
    cfg = scale_config("smoke", (f"--world_models={given}",))
    models = stages.world_models(cfg, out, None, trained_tokenizer)  # no data: nothing is trained
    for control, path in models.items():
        assert path == out / world_model_dir(control) / FINAL
        assert_same_weights(world_models[control] / "model.safetensors", path / "model.safetensors")
        assert (path.parent / "heldout_curve.jsonl").is_file()
    reader = ReportSettings(str(models.action))
    resume.run_once(tmp_path / "fidelity", reader, False, lambda: None)
    copied = (models.action / "model.safetensors").stat().st_mtime_ns
    stages.world_models(cfg, out, None, trained_tokenizer)
    assert (models.action / "model.safetensors").stat().st_mtime_ns == copied  # taken once
    assert resume.is_done(tmp_path / "fidelity", reader, False)

    (given / "action" / FINAL / "model.safetensors").write_bytes(
        (world_models["action"] / "model.safetensors").read_bytes()
    )
    stages.world_models(cfg, out, None, trained_tokenizer)
    assert (models.action / "model.safetensors").stat().st_mtime_ns != copied  # new weights: taken again
    assert not resume.is_done(tmp_path / "fidelity", reader, False)  # and what read the old ones reruns

    record = json.loads((given / "action" / TRAIN_CONFIG).read_text())
    assert record["tokenizer_fingerprint"] == tokenizer_fingerprint(VisualTokenizer.from_pretrained(trained_tokenizer))
    (given / "action" / TRAIN_CONFIG).write_text(json.dumps(record | {"tokenizer_fingerprint": "0" * 64}))
    with pytest.raises(InvalidInputError, match="action model of this run's tokenizer.*'tokenizer': '0000"):
        stages.world_models(cfg, tmp_path / "another_run", None, trained_tokenizer)
    shutil.rmtree(given / "text")
    shutil.copytree(world_models["action"], given / "text" / FINAL)
    with pytest.raises(InvalidInputError, match="is not the text model of this run's tokenizer.*'control': 'action'"):
        stages.world_models(cfg, out, None, trained_tokenizer)
    with pytest.raises(MissingInputError, match="nowhere holds none of tokenizer/, action/ and text/"):
        stages.world_models(
            scale_config("smoke", (f"--world_models={tmp_path / 'nowhere'}",)), out, None, trained_tokenizer
        )
    (tmp_path / "empty" / "action").mkdir(parents=True)
    with pytest.raises(MissingInputError, match="empty/action/pretrained_model/model.safetensors"):
        stages.world_models(scale_config("smoke", (f"--world_models={tmp_path / 'empty'}",)), out, None, None)


def test_models_carried_out_of_a_run_are_taken_by_another_with_their_tokenizer(
    world_models, trained_tokenizer, tmp_path
):
    """carry() writes a run's tokenizer and world models as --world_models takes them, without checkpoints; a run
    given them trains no tokenizer (it has no data here) but copies that one, once, and checks the world models
    against it; a folder may bring part of them; a tokenizer made for other cameras is refused by name, and so is
    a run without its tokenizer."""
    import shutil

    from lerobot_roboscape.pipeline import stages
    from lerobot_roboscape.pipeline.config import scale_config
    from lerobot_roboscape.pipeline.given import brought, carry
    from lerobot_roboscape.pipeline.layout import TOKENIZER_DIR, world_model_dir
    from lerobot_roboscape.training.checkpoints import CHECKPOINTS, FINAL
    from roboscape_core.errors import InvalidInputError, MissingInputError
    from tests.conftest import IMAGE_SIZE
    from tests.harness import assert_same_weights

    before, given, out = tmp_path / "before", tmp_path / "carried", tmp_path / "run"
    shutil.copytree(trained_tokenizer.parent, before / TOKENIZER_DIR)
    for control, model in world_models.items():
        shutil.copytree(model.parent, before / world_model_dir(control))
    sizes = carry(before, given)
    assert set(sizes) == {"tokenizer", "action", "text"} and not list(given.rglob(CHECKPOINTS))
    assert (before / TOKENIZER_DIR / CHECKPOINTS).is_dir()  # what the run resumes from stays with it

    cameras = f"--data.image_size={IMAGE_SIZE}", f"--tokenizer.image_size={IMAGE_SIZE}"
    cfg = scale_config("smoke", (f"--world_models={given}", *cameras))
    taken = stages.tokenizer(cfg, out, None)  # no data: nothing is trained
    assert taken == out / TOKENIZER_DIR / FINAL
    assert_same_weights(trained_tokenizer / "model.safetensors", taken / "model.safetensors")
    copied = (taken / "model.safetensors").stat().st_mtime_ns
    assert stages.tokenizer(cfg, out, None) == taken
    assert (taken / "model.safetensors").stat().st_mtime_ns == copied  # taken once
    models = stages.world_models(cfg, out, None, taken)  # their tokenizer fingerprint is the taken one's
    assert_same_weights(world_models["text"] / "model.safetensors", models.text / "model.safetensors")

    other = scale_config("smoke", (f"--world_models={given}", "--data.image_size=64", "--tokenizer.image_size=64"))
    with pytest.raises(InvalidInputError, match=rf"carried/tokenizer/pretrained_model reads {IMAGE_SIZE} px.*=64"):
        stages.tokenizer(other, tmp_path / "another_run", None)
    assert brought(cfg) == {"tokenizer", "action", "text"} and brought(scale_config("smoke", ())) == set()
    shutil.rmtree(given / "action")
    shutil.rmtree(given / "text")  # the tokenizer alone: the run trains its world models on it
    assert brought(cfg) == {"tokenizer"}
    shutil.rmtree(before / world_model_dir("text"))  # a run stopped after its action model carries what it has
    assert set(carry(before, tmp_path / "part")) == {"tokenizer", "action"}
    shutil.rmtree(before / TOKENIZER_DIR)
    with pytest.raises(MissingInputError, match="tokenizer/pretrained_model/model.safetensors does not exist"):
        carry(before, tmp_path / "again")
    assert (given / "tokenizer").is_dir()  # the folder carried before is left whole
