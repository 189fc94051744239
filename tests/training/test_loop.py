"""The training loop every model shares (`training/loop.fit`): a loss gone non-finite, and a time budget."""

import dataclasses
import json
import time
from pathlib import Path

import pytest
import torch

from lerobot_roboscape.training.checkpoints import FINAL, last_checkpoint
from lerobot_roboscape.training.loop import TRAIN_LOG, TrainingConfig, fit


class Tiny(torch.nn.Linear):
    """The smallest model `fit` saves."""

    def save_pretrained(self, path):
        Path(path).mkdir(parents=True, exist_ok=True)
        torch.save(self.state_dict(), Path(path) / "weights.pt")


def test_a_loss_gone_non_finite_stops_training_at_the_next_logging_step(tmp_path):
    """The loss is read on logging steps only (no wait on the device in between): a NaN from step 3 stops the run
    at step 4, the next logging step, with a message naming it."""

    def loss_fn(model, batch):
        loss = model(batch["x"]).pow(2).mean() * (torch.nan if batch["step"] >= 2 else 1.0)
        return loss, {"loss": loss.detach()}

    batches = lambda step, process: {"x": torch.ones(2, 3), "step": step}  # noqa: E731
    config = TrainingConfig(steps=8, batch_size=2, log_freq=4, warmup_steps=1, mixed_precision="no")
    with pytest.raises(FloatingPointError, match="loss is nan at step 4; lower --train.lr"):
        fit(torch.nn.Linear(3, 1), loss_fn, batches, config, tmp_path, {})


def test_a_time_budget_ends_the_run_on_time_with_its_cosine_decayed(tmp_path):
    """With --train.time_budget_s the run plans its last step from its pace and ends there as a run of that many
    steps does: its learning rate decayed to the floor, its checkpoint and model saved, its seconds recorded."""

    def loss_fn(model, batch):
        time.sleep(0.02)  # a step's pace
        loss = model(batch["x"]).pow(2).mean()
        return loss, {"loss": loss.detach()}

    batches = lambda step, process: {"x": torch.ones(2, 3)}  # noqa: E731
    config = TrainingConfig(
        steps=100_000, batch_size=2, lr=1e-2, log_freq=2, warmup_steps=2, save_freq=100_000, time_budget_s=2.0
    )
    began = time.time()
    fit(Tiny(3, 1), loss_fn, batches, dataclasses.replace(config, mixed_precision="no"), tmp_path, {})
    seconds = time.time() - began
    log = [json.loads(line) for line in (tmp_path / TRAIN_LOG).read_text().splitlines()]
    record = json.loads((last_checkpoint(tmp_path) / "training_step.json").read_text())
    assert 20 < record["step"] < 1000 and record["step"] >= log[-1]["step"]
    assert 1.5 < record["seconds"] < seconds + 0.5 and seconds < 6.0
    assert log[-1]["lr"] < 0.2 * config.lr  # the cosine spanned the steps the run took
    assert (tmp_path / FINAL / "weights.pt").is_file()


def test_a_time_budget_ends_the_run_at_its_deadline_even_between_logging_steps(tmp_path):
    """Steps slower than the budget's first plan: the run still ends at its deadline, with its model saved."""

    def loss_fn(model, batch):
        time.sleep(0.1)
        loss = model(batch["x"]).pow(2).mean()
        return loss, {"loss": loss.detach()}

    config = TrainingConfig(
        steps=1000, batch_size=2, log_freq=500, save_freq=1000, time_budget_s=1.0, mixed_precision="no"
    )
    began = time.time()
    fit(Tiny(3, 1), loss_fn, lambda step, process: {"x": torch.ones(2, 3)}, config, tmp_path, {})
    assert time.time() - began < 4.0 and (tmp_path / FINAL / "weights.pt").is_file()
    assert 5 <= json.loads((last_checkpoint(tmp_path) / "training_step.json").read_text())["step"] <= 20
