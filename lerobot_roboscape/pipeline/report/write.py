"""The experiment's report: every target of the bench experiment with its measured value, the Table 1 of the run,
the time of each stage and the figures a user judges the stages by (report.md, results.json and small PNGs)."""

import json
import os
import platform
import shutil
from datetime import date
from pathlib import Path
from typing import NamedTuple

import matplotlib
import torch

from lerobot_roboscape.envs import reward_report
from lerobot_roboscape.evaluation.results import Results
from lerobot_roboscape.evaluation.tables import format_table, read_table
from lerobot_roboscape.io.templates import number, render_report
from lerobot_roboscape.pipeline.config import JUDGED_SCALES, PipelineConfig
from lerobot_roboscape.pipeline.layout import (
    CONTROL_DIR,
    CONVERTED_DIR,
    DEMOS_DIR,
    DONE_REPORT_DIR,
    DONE_REPORT_IND_DIR,
    EVAL_DIR,
    FIDELITY_DIR,
    FIDELITY_IND_DIR,
    HELDOUT_DIR,
    REWARD_REPORT_DIR,
    TABLES_DIR,
    TOKENIZER_DIR,
    TOKENIZER_REPORT_DIR,
    VALIDATION_DIR,
    reward_model_dir,
    rl_dir,
    sft_dir,
    world_model_dir,
)
from lerobot_roboscape.pipeline.methods import (
    POLICIES,
    REWARD_ABLATION,
    REWARD_BASELINES,
    RL_MANISKILL,
    RL_MANISKILL_ONE_SCENE,
    RL_WORLD_MODEL,
    SUCCESS_CLASSIFIER,
)
from lerobot_roboscape.pipeline.report.figures import WM_FIGURE_FRAMES, ppo_curves, world_model_figure
from lerobot_roboscape.pipeline.report.targets import measure_targets, tokenizer_targets
from lerobot_roboscape.pipeline.report.world_model_targets import world_model_targets
from lerobot_roboscape.pipeline.resume import stage_seconds
from lerobot_roboscape.reward import done_report
from lerobot_roboscape.tokenizer import report as tokenizer_report
from lerobot_roboscape.training.loop import TrainingTime
from lerobot_roboscape.world_model.measures import fidelity as fidelity_report
from lerobot_roboscape.world_model.measures.fidelity_readings import FidelityReadings

matplotlib.use("Agg")


# The folders under output_dir (as stages.py names them), by the stage that makes them (for the time table).
STAGE_FOLDERS = {
    "collect (demonstrations, held-out, validation, controllability set, trajectory file)": [
        DEMOS_DIR,
        HELDOUT_DIR,
        VALIDATION_DIR,
        CONTROL_DIR,
        CONVERTED_DIR,
    ],
    "tokenizer": [TOKENIZER_DIR],
    "tokenizer report": [TOKENIZER_REPORT_DIR],
    "action world model (with the token cache)": [world_model_dir("action")],
    "text world model": [world_model_dir("text")],
    "fidelity report": [FIDELITY_IND_DIR, FIDELITY_DIR],
    "reward models, success classifier, done and reward reports": [
        *map(reward_model_dir, (*REWARD_BASELINES, SUCCESS_CLASSIFIER)),
        DONE_REPORT_DIR,
        DONE_REPORT_IND_DIR,
        REWARD_REPORT_DIR,
    ],
    "SFT (lerobot-train)": [*map(sft_dir, POLICIES)],
}


def write_report(cfg: PipelineConfig, out: Path, report_dir: str | None = None) -> Path:
    """Write report.md, results.json and the figures into out/report (and report_dir); returns report.md."""
    folder = out / "report"
    folder.mkdir(parents=True, exist_ok=True)
    tokenizer = tokenizer_report.read_tokenizer_report(out / TOKENIZER_REPORT_DIR)
    models = WorldModelReports.read(out)
    table = read_table(out / TABLES_DIR)
    targets = tokenizer_targets(tokenizer) | models.targets() | measure_targets(table, cfg.data.families)
    times = stage_times(cfg, out)
    results = {
        "scale": cfg.scale,
        "families": cfg.data.families,
        "date": date.today().isoformat(),
        "machine": machine(),
        "targets": targets,
        "table": table.to_json(),
        "stage_seconds": times,
        "tokenizer": tokenizer_report.results_entry(tokenizer),
        **models.results(),
    }
    (folder / "results.json").write_text(json.dumps(results, indent=2))

    shutil.copy2(out / TOKENIZER_REPORT_DIR / "reconstruction.png", folder / "tokenizer_reconstruction.png")
    if (out / TOKENIZER_REPORT_DIR / "heldout_curve.png").exists():
        shutil.copy2(out / TOKENIZER_REPORT_DIR / "heldout_curve.png", folder / "tokenizer_curve.png")
    world_model_figure(
        out / FIDELITY_DIR / "side_by_side.mp4",
        FidelityReadings.from_json(models.fidelity).prompt_frames,
        folder / "world_model_open_loop.png",
    )
    ppo_curves(out, table.policies, folder / "ppo_curves.png")
    for source, name in (
        (out / FIDELITY_DIR / "fidelity.png", "fidelity.png"),
        (out / REWARD_REPORT_DIR / "reward_curves.png", "reward_curves.png"),
        (out / REWARD_REPORT_DIR / "goal_grid.png", "goal_grid.png"),
        (out / DONE_REPORT_DIR / "done_curves.png", "done_curves.png"),
        (out / TABLES_DIR / "tables.png", "tables.png"),
    ):
        shutil.copy2(source, folder / name)
    (folder / "report.md").write_text(markdown(cfg, results, table))
    if report_dir:
        shutil.copytree(folder, report_dir, dirs_exist_ok=True)
    return folder / "report.md"


class WorldModelReports(NamedTuple):
    """The reports on a run's world models (None where the scale made none): fidelity OOD and IND, the done report
    on held-out OOD episodes and on the validation half that did not choose its threshold (IND), the reward report,
    and the action model's training time."""

    fidelity: dict
    fidelity_ind: dict | None
    done: dict
    done_ind: dict | None
    rewards: dict
    action_time: TrainingTime | None

    @classmethod
    def read(cls, out: Path) -> "WorldModelReports":
        return cls(
            fidelity_report.read_fidelity(out / FIDELITY_DIR),
            fidelity_report.read_fidelity(out / FIDELITY_IND_DIR),
            done_report.read_done_report(out / DONE_REPORT_DIR),
            done_report.read_done_report(out / DONE_REPORT_IND_DIR) if (out / DONE_REPORT_IND_DIR).is_dir() else None,
            reward_report.read_reward_report(out / REWARD_REPORT_DIR),
            TrainingTime.read(out / world_model_dir("action")),
        )

    def targets(self) -> dict:
        return world_model_targets(
            self.fidelity, self.done, self.rewards, self.action_time, self.fidelity_ind, self.done_ind
        )

    def results(self) -> dict:
        """What results.json keeps of them."""
        results = {"fidelity": fidelity_report.results_entry(self.fidelity)}
        results |= {"done": done_report.results_entry(self.done), **reward_report.results_entry(self.rewards)}
        if self.fidelity_ind is not None:
            results["fidelity_ind"] = fidelity_report.results_entry(self.fidelity_ind)
        if self.done_ind is not None:
            results["done_ind"] = done_report.results_entry(self.done_ind)
        return results


def protocol(cfg: PipelineConfig) -> str:
    """The experiment's protocol, as the paper's section 8.1, in the words of this run's settings."""
    heldout = (
        f"held-out episodes in {cfg.data.heldout_scenes} OOD scenes, half of them failed attempts"
        if cfg.data.heldout_scenes
        else "one recorded and converted IND episode (this scale collects no held-out OOD episodes)"
    )
    budget = (
        f"the same wall-clock budget ({cfg.ppo.time_budget_s / 60:g} min) on the same machine"
        if cfg.ppo.time_budget_s
        else f"the same number of iterations ({cfg.ppo.iterations})"
    )
    length = cfg.eval.episode_length or cfg.env.episode_length
    ending = f"{length} steps" if length else "the family's horizon (its longest successful demonstration)"
    return (
        f"As the paper's section 8.1: task families {', '.join(cfg.data.families)}; IND evaluates the training scenes "
        "with new initial states, OOD the held-out scenes (unseen objects and unseen object-container combinations). "
        "The world models and the MLP policy train on the demonstrations of the IND scenes "
        f"({cfg.data.episodes_per_scene} per family and scene, a quarter of them deliberately failed; SFT imitates the "
        f"successful ones). The fidelity and reward reports use {heldout}. RL: PPO from the SFT checkpoint, one "
        f"multi-task run per env over the families; each run gets {budget}."
        + (
            " RL in ManiSkill runs twice: in one scene (the paper's baseline: the simulator \"only initializes a "
            'single type of environment", section 3.2) and in every training scene.'
            if cfg.ppo_one_scene
            else " RL in ManiSkill runs in every training scene."
        )
        + f" Success: {_episodes(cfg.eval.episodes)} in the simulator per (split, family); episodes end at success "
        f"or after {ending}."
    )


def evaluation_summary(cfg: PipelineConfig, table: Results | dict, seconds: dict) -> str:
    """Episodes per cell, each cell's 95% interval width, and the evaluation's time."""
    widths = [100 * (cell.ci95[1] - cell.ci95[0]) for cell in Results.of(table).family_cells()]
    minutes = sum(v for k, v in seconds.items() if k.startswith("simulator evaluation")) / 60
    return (
        f"Each cell rests on {_episodes(cfg.eval.episodes)}; its 95% interval is {min(widths):.0f} to "
        f"{max(widths):.0f} points wide (in parentheses after each interval). The evaluation took "
        f"{minutes:.1f} min ({len(widths)} cells, {cfg.data.workers} simulator processes)."
    )


def _episodes(n: int) -> str:
    return f"{n} episode" if n == 1 else f"{n} episodes"


def measured(target: dict) -> str:
    """A target's measured value as the reports write it, with its detail."""
    return number(target["value"]) + (f" ({target['detail']})" if "detail" in target else "")


def minutes(seconds: float) -> str:
    return f"{seconds / 60:.1f}"


# How the pipeline's reports write a target and a duration (`{{ target | measured }}`), beside the renderer's own.
FILTERS = {"measured": measured, "minutes": minutes}


def render_pipeline_report(template: str, filters: dict | None = None, **fields) -> str:
    return render_report(template, FILTERS | (filters or {}), **fields)


def stage_times(cfg: PipelineConfig, out: Path) -> dict[str, float]:
    """Seconds of each stage's last run, from the stage.json its folders hold."""
    times = {}
    for stage, folders in STAGE_FOLDERS.items():
        times[stage] = sum(stage_seconds(out / f) or 0.0 for f in folders)
    for policy in POLICIES:
        for method in (RL_WORLD_MODEL, RL_MANISKILL, RL_MANISKILL_ONE_SCENE, *REWARD_ABLATION):
            seconds = stage_seconds(out / rl_dir(policy, method))
            if seconds is not None:
                times[f"PPO {policy}: {method}"] = seconds
    times[evaluation_label(cfg, out)] = evaluation_seconds(out)
    return {k: round(v, 1) for k, v in times.items() if v}


def evaluation_seconds(out: Path) -> float:
    """Seconds of the simulator evaluations (their jobs run one after another)."""
    return sum(stage_seconds(p.parent) or 0.0 for p in (out / EVAL_DIR).glob("*/*/*/stage.json"))


def evaluation_label(cfg: PipelineConfig, out: Path) -> str:
    jobs = len(list((out / EVAL_DIR).glob("*/*/*/stage.json")))
    return f"simulator evaluation ({jobs} jobs one after another, on {cfg.data.workers} simulator processes)"


def machine() -> str:
    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else "no GPU"
    return f"{os.cpu_count()} CPU cores ({platform.processor() or platform.machine()}), {gpu}"


def markdown(cfg: PipelineConfig, results: dict, table: Results | dict) -> str:
    return render_pipeline_report(
        "run_report.md",
        cfg=cfg,
        results=results,
        targets=results["targets"],
        judged=cfg.scale in JUDGED_SCALES,
        protocol=protocol(cfg),
        table=format_table(table, cfg.data.families, f"{cfg.scale} scale"),
        evaluation=evaluation_summary(cfg, table, results["stage_seconds"]),
        wm_figure_frames=WM_FIGURE_FRAMES,
    )
