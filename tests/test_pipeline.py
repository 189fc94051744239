"""The pipeline's stage bookkeeping: a completed stage is skipped only when its settings are unchanged, an
interrupted training stage resumes only into a run of the same settings, and the report measures each target."""

from dataclasses import dataclass

from lerobot_roboscape.pipeline import stages
from lerobot_roboscape.pipeline.report import measure_targets


@dataclass
class Settings:
    steps: int
    lr: float = 1e-3


def test_a_stage_is_done_only_with_the_same_settings(tmp_path):
    folder = tmp_path / "tokenizer"
    assert not stages.is_done(folder, Settings(10), fresh=False)
    stages.start(folder).mkdir()
    (folder / "weights").write_text("w")
    stages.mark_done(folder, Settings(10))
    assert stages.is_done(folder, Settings(10), fresh=False)
    assert stages.stage_seconds(folder) >= 0
    assert not stages.is_done(folder, Settings(11), fresh=False)  # changed settings: the stage runs again
    assert not stages.is_done(folder, Settings(10), fresh=True)


def test_an_interrupted_stage_resumes_only_into_the_same_settings(tmp_path):
    folder = tmp_path / "world_model"
    assert stages.prepare(folder, Settings(10), fresh=False) is False  # nothing to resume: a new run
    (folder / "checkpoints").mkdir()  # the run is killed after a checkpoint
    assert stages.prepare(folder, Settings(10), fresh=False) is True
    assert (folder / "checkpoints").is_dir()
    assert stages.prepare(folder, Settings(10, lr=3e-4), fresh=False) is False  # other settings: cleared
    assert not (folder / "checkpoints").exists()


def cell(rate: float, n: int = 10) -> dict:
    from lerobot_roboscape.evaluation.success_rate import summarise

    return summarise([True] * round(rate * n) + [False] * (n - round(rate * n)))


def test_targets_compare_the_measured_values_with_the_goals():
    fidelity = {
        "mean": {"reconstruction_psnr": 27.0},
        "per_step": {"prediction_psnr": [25.0] * 8 + [10.0] * 8, "reconstruction_psnr": [27.0] * 16},
        "done_whole_episode_open_loop": {"roc_auc": 0.85},
    }
    rewards = {
        "summary": {
            "world_model": {"roc_auc_of_return": 0.9},
            "embedding": {"roc_auc_of_return": 0.95},
            "proxy": {"roc_auc_of_return": 0.5},
        }
    }
    split = lambda rate: {"push": cell(rate), "all": cell(rate)}  # noqa: E731
    table = {
        "roboscape_mlp": {
            stages.SFT: {"ind": split(0.4), "ood": split(0.2)},
            stages.RL_WORLD_MODEL: {"ind": split(0.5), "ood": split(0.2)},
            stages.RL_MANISKILL: {"ind": split(0.3), "ood": split(0.1)},
        }
    }
    met = {name: t["met"] for name, t in measure_targets(fidelity, rewards, table, ["push"]).items()}
    assert met["tokenizer held-out reconstruction PSNR (dB)"]
    assert met["action WM open-loop PSNR, first 8 steps (dB; tokenizer 27.00)"]  # 25 is within 3 dB of 27
    assert not met["done ROC-AUC, held-out episodes generated open loop"]
    assert not met["world-model reward: ROC-AUC of the return, held-out OOD episodes"]  # the embedding beats it
    assert met["roboscape_mlp SFT IND success, push"]
    assert met["roboscape_mlp PPO in WM vs Supervised finetune, IND (all families)"]
    assert not met["roboscape_mlp PPO in WM vs Supervised finetune, OOD (all families)"]  # equal is not higher
    assert met["roboscape_mlp PPO in WM vs RL w. ManiSkill, OOD (all families)"]
