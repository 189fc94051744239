"""The supervised training loop shared by the tokenizer and the world models, on Accelerate.

The same code runs on one CPU, one GPU, or under `accelerate launch` on several. Checkpoints hold the whole
Accelerate state (model, optimiser, scheduler, RNG) plus the step; `resume=True` continues from the last one with
the same step counter. Batches are a pure function of (step, process), so a resumed run sees the batches an
uninterrupted run would have seen.
"""

import contextlib
import json
import logging
import math
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from accelerate import Accelerator
from accelerate.utils import set_seed
from torch import nn
from tqdm import tqdm

from lerobot_roboscape.io.atomic import make_tmp_dir
from lerobot_roboscape.io.console import say_once
from lerobot_roboscape.training.checkpoints import (
    CHECKPOINTS,
    FINAL,
    LOGS,
    begin_checkpoint,
    last_checkpoint,
    publish_checkpoint,
)
from lerobot_roboscape.training.throughput import Throughput, peak_flops
from roboscape_core.errors import InvalidInputError, OutputExistsError

logger = logging.getLogger(__name__)
# Accelerate warns at every checkpoint of a model with tied weights (they reload tied): once is enough.
say_once("accelerate.utils.other", "Removed shared tensor")
# One {"step", "seconds" (of training, evaluations excluded), <measure>: value} line per held-out evaluation.
HELDOUT_CURVE = "heldout_curve.jsonl"
# One line per logging step: the losses, and the throughput since the previous one (samples/s, TFLOP/s, MFU).
TRAIN_LOG = "train_log.jsonl"
TRAIN_CONFIG = "train_config.json"  # the run's settings, beside its log


@dataclass
class TrainingConfig:
    """Args:
    steps: optimiser steps in total.
    batch_size: samples per step and process.
    lr: peak learning rate (AdamW), reached after warmup_steps and decayed by a cosine to lr / 10.
    weight_decay: AdamW weight decay of weight matrices and embeddings (biases and norms are not decayed).
    warmup_steps: linear warm-up steps.
    grad_clip: gradient-norm clipping.
    log_freq: steps between log lines (TensorBoard under output_dir/logs, and the progress bar).
    save_freq: steps between checkpoints.
    eval_freq: steps between held-out evaluations (when the stage has held-out data; 0: at the end only). They are
        logged and appended to output_dir/heldout_curve.jsonl: the curves that size a run.
    keep_checkpoints: checkpoints kept on disk (older ones are deleted).
    seed: seed of the initialisation and of the batch sampling.
    mixed_precision: "auto" (bf16 on a GPU that supports it, else full precision), "bf16", "fp16" or "no".
    compile: torch.compile the model's training step (static shapes); null: on a GPU only, where it pays (on the
        CPU its compilation outweighs a short run).
    tf32: on a GPU, TF32 tensor cores for the matmuls left in fp32.
    peak_tflops: the device's peak bf16 TFLOP/s that MFU is read against; null: looked up from the GPU's name
        (training/throughput.py), none on a CPU (then only TFLOP/s are reported).
    time_budget_s: end the run after about this many seconds (evaluations and resumes included) instead of after
        `steps` (then its upper bound): at every logging step the run's last step is set from the pace so far, and
        the cosine decays over the steps it will take; at the deadline (with several processes, at the first logging
        step past it) it ends, whatever the plan, as a run of that many steps does (final evaluation, checkpoint and
        model). For a lease of fixed length, whatever the device's speed. Null: `steps`.
    resume: continue from the last checkpoint in output_dir.
    """

    steps: int = 1000
    batch_size: int = 16
    lr: float = 3e-4
    weight_decay: float = 0.01
    warmup_steps: int = 50
    grad_clip: float = 1.0
    log_freq: int = 25
    save_freq: int = 250
    eval_freq: int = 0
    keep_checkpoints: int = 2
    seed: int = 0
    mixed_precision: str = "auto"
    compile: bool | None = None
    tf32: bool = True
    peak_tflops: float | None = None
    time_budget_s: float | None = None
    resume: bool = False

    def __post_init__(self):
        if str(self.mixed_precision).lower() in ("false", "none"):  # the CLI's YAML reads "no" as false
            self.mixed_precision = "no"
        if self.mixed_precision not in ("auto", "bf16", "fp16", "no"):
            raise InvalidInputError(f"mixed_precision must be auto, bf16, fp16 or no, got {self.mixed_precision!r}")
        if self.steps < 1 or self.batch_size < 1 or self.save_freq < 1:
            raise InvalidInputError(
                f"steps, batch_size and save_freq must be >= 1, got {self.steps}, {self.batch_size}, {self.save_freq}"
            )


def resolve_device(value: str) -> str:
    """ "auto" -> "cuda" when a GPU is present, else "cpu"; anything else as given."""
    return ("cuda" if torch.cuda.is_available() else "cpu") if value == "auto" else value


def resolve_mixed_precision(value: str | bool) -> str:
    if str(value).lower() == "false":  # the command line's YAML reads `--mixed_precision=no` as false
        return "no"
    if value != "auto":
        return value
    return "bf16" if torch.cuda.is_available() and torch.cuda.is_bf16_supported() else "no"


def native_bf16(device: str) -> bool:
    """Whether `device` computes bf16 natively: a CUDA GPU that supports it, or a CPU with AVX512-BF16 or AMX
    (Linux's CPU flags; elsewhere, no)."""
    if device.startswith("cuda"):
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return "avx512_bf16" in flags or "amx_bf16" in flags


def make_accelerator(config: TrainingConfig, output_dir: Path) -> Accelerator:
    accelerator = Accelerator(
        mixed_precision=resolve_mixed_precision(config.mixed_precision), log_with="tensorboard", project_dir=output_dir
    )
    if accelerator.device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = config.tf32
    set_seed(config.seed)
    return accelerator


def _save_checkpoint(
    accelerator: Accelerator, model: nn.Module, step: int, output_dir: Path, keep: int, seconds: float
) -> None:
    tmp = begin_checkpoint(output_dir, step) if accelerator.is_main_process else None
    tmp = Path(from_main_process(accelerator, tmp))
    accelerator.save_state(tmp)  # every process writes its part
    if accelerator.is_main_process:
        accelerator.unwrap_model(model).save_pretrained(tmp / FINAL)
        (tmp / "training_step.json").write_text(json.dumps({"step": step, "seconds": seconds}))
        publish_checkpoint(output_dir, step, tmp, keep)
    accelerator.wait_for_everyone()


def from_main_process(accelerator: Accelerator, value):
    """The main process's `value` (a path to write to, a planned step), on every process."""
    from accelerate.utils import broadcast_object_list

    holder = [value]
    if accelerator.num_processes > 1:
        broadcast_object_list(holder)
    return holder[0]


class CosineWithWarmup:
    """The learning rate's factor at a step: linear warm-up, then a cosine to 1/10 at the run's last step, `steps`,
    which a time budget moves. An object, not a function: LambdaLR saves its attributes with the scheduler's state,
    so a resumed run keeps the last step it planned."""

    def __init__(self, warmup_steps: int, steps: int):
        self.warmup_steps, self.steps = warmup_steps, steps

    def __call__(self, step: int) -> float:
        if step < self.warmup_steps:
            return (step + 1) / self.warmup_steps
        progress = (step - self.warmup_steps) / max(1, self.steps - self.warmup_steps)
        return 0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0)))


def planned_last_step(config: TrainingConfig, step: int, seconds: float, paced: tuple[int, float]) -> int:
    """The run's last step under its time budget: `step` steps done after `seconds`, at the pace since `paced`
    (a step and the seconds then, after the first step's compilation and warm-up)."""
    since_step, since_seconds = paced
    per_step = (seconds - since_seconds) / max(step - since_step, 1)
    left = int((config.time_budget_s - seconds) / max(per_step, 1e-9))
    return max(min(config.steps, step + left), step)


def fit(
    model: nn.Module,
    loss_fn: Callable[[nn.Module, dict], tuple[torch.Tensor, dict]],
    batches: Callable[[int, int], dict],
    config: TrainingConfig,
    output_dir: str | Path,
    run_config: dict,
    desc: str = "training",
    evaluate: Callable[[nn.Module], dict[str, float]] | None = None,
    flops_per_sample: float | None = None,
) -> nn.Module:
    """Train `model` for config.steps steps on `batches(step, process_index)`; returns the unwrapped model, also
    saved to output_dir/pretrained_model. `evaluate(model)` runs every config.eval_freq steps and at the end (main
    process, eval mode, no gradients). `loss_fn`'s logs may be tensors: read (a wait for the device) on logging
    steps only, so the host queues steps ahead. `flops_per_sample` adds TFLOP/s and MFU to the logs."""
    output_dir = Path(output_dir)
    resume_from = _checkpoint_to_resume(output_dir, config)
    accelerator = make_accelerator(config, output_dir)
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = adamw(params, config, accelerator.device)
    schedule = CosineWithWarmup(config.warmup_steps, config.steps)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, schedule)
    model, optimizer, scheduler = accelerator.prepare(model, optimizer, scheduler)
    if config.compile if config.compile is not None else accelerator.device.type == "cuda":
        accelerator.unwrap_model(model).compile()  # in place: the state dict's keys stay as they are
    accelerator.init_trackers(LOGS, config={k: str(v) for k, v in run_config.items()})
    start, before = _resume(accelerator, resume_from, output_dir, run_config)
    clock = _Clock(before)
    samples = config.batch_size * accelerator.num_processes
    peak = peak_flops(accelerator.device, config.peak_tflops)
    throughput = Throughput(samples, flops_per_sample, peak, accelerator.device)
    model.train()
    rank = accelerator.process_index
    progress = tqdm(
        range(start, config.steps),
        desc=desc,
        initial=start,
        total=config.steps,
        disable=not accelerator.is_main_process,
        dynamic_ncols=True,
    )
    for step in progress:
        batch = {k: v.to(accelerator.device) if torch.is_tensor(v) else v for k, v in batches(step, rank).items()}
        with accelerator.autocast():
            loss, logs = loss_fn(model, batch)
        accelerator.backward(loss)
        logs["grad_norm"] = accelerator.clip_grad_norm_(params, config.grad_clip)
        optimizer.step()
        scheduler.step()
        optimizer.zero_grad(set_to_none=True)
        logging = (step + 1) % config.log_freq == 0 or step == start
        if logging:
            logs = _read_logs(logs, loss, step)
            if step == start:
                throughput.mark(step + 1)  # the first step (compilation, warm-up) is not throughput
                clock.paced = (step + 1, clock.elapsed())
            else:
                logs |= throughput.read(step + 1)
            if config.time_budget_s is not None and step > start:
                planned = planned_last_step(config, step + 1, clock.elapsed(), clock.paced)
                schedule.steps = progress.total = from_main_process(accelerator, planned)
            logs["lr"] = scheduler.get_last_lr()[0]
            accelerator.log(logs, step=step + 1)
            _log_line(output_dir, accelerator, step + 1, logs)
            progress.set_postfix({k: f"{v:.3g}" for k, v in logs.items() if k in PROGRESS_KEYS})
        if step + 1 < schedule.steps and _past_deadline(config, accelerator, clock, logging):
            schedule.steps = progress.total = step + 1
        last = step + 1 == schedule.steps
        if evaluate is not None and accelerator.is_main_process and (last or _every(step, config.eval_freq)):
            with clock.evaluation() as seconds:
                _evaluate(accelerator.unwrap_model(model), evaluate, accelerator, step + 1, output_dir, seconds)
        if (step + 1) % config.save_freq == 0 or last:
            _save_checkpoint(accelerator, model, step + 1, output_dir, config.keep_checkpoints, clock.elapsed())
        if last:
            break
    accelerator.end_training()
    unwrapped = accelerator.unwrap_model(model)
    if accelerator.is_main_process:
        save_atomically(unwrapped, output_dir / FINAL)
    return unwrapped


def _checkpoint_to_resume(output_dir: Path, config: TrainingConfig) -> Path | None:
    """The checkpoint a resumed run continues from (None: a new run, in a folder without checkpoints)."""
    if not config.resume and (output_dir / CHECKPOINTS).exists():
        raise OutputExistsError(
            f"{output_dir} already holds checkpoints; pass --resume=true to continue that run "
            "or choose a new --output_dir"
        )
    output_dir.mkdir(parents=True, exist_ok=True)
    return last_checkpoint(output_dir) if config.resume else None


def adamw(params: list[nn.Parameter], config: TrainingConfig, device: torch.device) -> torch.optim.Optimizer:
    """AdamW as nanoGPT's configure_optimizers makes it: weight matrices and embeddings decay; biases and norms'
    gains (1-D) do not; fused (one kernel for every parameter's update) on CUDA."""
    groups = [
        {"params": [p for p in params if p.dim() >= 2], "weight_decay": config.weight_decay},
        {"params": [p for p in params if p.dim() < 2], "weight_decay": 0.0},
    ]
    return torch.optim.AdamW(groups, lr=config.lr, betas=(0.9, 0.95), fused=device.type == "cuda")


def _resume(accelerator, resume_from: Path | None, output_dir: Path, run_config: dict) -> tuple[int, float]:
    """The step and the seconds a resumed run had (0, 0 for a new one), its state loaded; the run's config written
    and its curves cut back to that step."""
    start, before = 0, 0.0
    if resume_from is not None:
        accelerator.load_state(resume_from)
        record = json.loads((resume_from / "training_step.json").read_text())
        start, before = record["step"], record.get("seconds", 0.0)
        logger.info("resumed from %s at step %d", resume_from, start)
    if accelerator.is_main_process:
        (output_dir / TRAIN_CONFIG).write_text(json.dumps(run_config, indent=2, default=str))
        _truncate_curve(output_dir / HELDOUT_CURVE, start)
        _truncate_curve(output_dir / TRAIN_LOG, start)
    return start, before


class _Clock:
    """A run's clocks: its seconds over resumes (`elapsed`, what the time budget spends), this session's training
    seconds without its evaluations (the held-out curve's), and the pace since the first step (`paced`: the step and
    the seconds then, once read)."""

    def __init__(self, before: float):
        self.before, self.began, self.evaluating = before, time.time(), 0.0
        self.paced: tuple[int, float] | None = None

    def elapsed(self) -> float:
        return self.before + time.time() - self.began

    @contextlib.contextmanager
    def evaluation(self):
        """Time an evaluation apart; yields the training seconds before it."""
        tic = time.time()
        yield tic - self.began - self.evaluating
        self.evaluating += time.time() - tic


def _past_deadline(config: TrainingConfig, accelerator: Accelerator, clock: _Clock, logging: bool) -> bool:
    """Whether the time budget is spent: read between logging steps too on one process (the host's clock, no wait on
    the device); with several, at logging steps only, where they wait anyway (agreeing on it every step would cost a
    collective)."""
    if config.time_budget_s is None or not (accelerator.num_processes == 1 or logging):
        return False
    return from_main_process(accelerator, clock.elapsed() >= config.time_budget_s)


def _read_logs(logs: dict, loss: torch.Tensor, step: int) -> dict[str, float]:
    """The step's logs as numbers (a wait for the device); a loss that is not finite stops the run."""
    logs = {name: float(value) for name, value in logs.items()}
    if not math.isfinite(logs["loss"] if "loss" in logs else loss.item()):
        raise FloatingPointError(f"loss is {loss.item()} at step {step + 1}; lower --train.lr or check the data")
    return logs


PROGRESS_KEYS = ("loss", "token_acc", "l1", "samples_per_s", "mfu")


def _log_line(output_dir: Path, accelerator: Accelerator, step: int, logs: dict) -> None:
    if accelerator.is_main_process:
        with open(output_dir / TRAIN_LOG, "a") as f:
            f.write(json.dumps({"step": step, **{k: round(v, 6) for k, v in logs.items()}}) + "\n")


def _every(step: int, freq: int) -> bool:
    return freq > 0 and (step + 1) % freq == 0


def _evaluate(model: nn.Module, evaluate: Callable, accelerator: Accelerator, step: int, output_dir: Path, seconds):
    model.eval()
    with torch.no_grad():
        measures = evaluate(model)
    model.train()
    accelerator.log({f"heldout/{k}": v for k, v in measures.items() if v is not None}, step=step)
    with open(output_dir / HELDOUT_CURVE, "a") as f:
        f.write(json.dumps({"step": step, "seconds": round(seconds, 1), **measures}) + "\n")


def _truncate_curve(path: Path, step: int) -> None:
    """Drop the held-out points after `step`, which a resumed run measures again."""
    if path.exists():
        lines = [line for line in path.read_text().splitlines() if line and json.loads(line)["step"] <= step]
        path.write_text("".join(line + "\n" for line in lines))


def read_curve(output_dir: str | Path) -> list[dict]:
    path = Path(output_dir) / HELDOUT_CURVE
    return [json.loads(line) for line in path.read_text().splitlines() if line] if path.exists() else []


@dataclass(frozen=True)
class TrainingTime:
    """How far a run had trained at its last held-out reading: the step, and the seconds of training alone (the
    readings excluded)."""

    step: int
    seconds: float

    @classmethod
    def read(cls, output_dir: str | Path) -> "TrainingTime | None":
        """From the run's held-out curve; None when it has none."""
        curve = read_curve(output_dir)
        return cls(curve[-1]["step"], curve[-1]["seconds"]) if curve else None


def save_atomically(model, path: Path) -> None:
    """`model.save_pretrained(path)`, replacing `path` only once the new files are complete."""
    tmp = make_tmp_dir(path.parent, path.name)
    model.save_pretrained(tmp)
    shutil.rmtree(path, ignore_errors=True)
    os.replace(tmp, path)
