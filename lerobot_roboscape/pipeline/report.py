"""The experiment's report: every target of the bench experiment with its measured value, the Table 1 of the run,
the time of each stage and the figures a user judges the stages by (report.md, results.json and small PNGs)."""

import json
import os
import platform
import shutil
from datetime import date
from pathlib import Path

import matplotlib
import torch

from lerobot_roboscape.evaluation.tables import format_table
from lerobot_roboscape.pipeline.config import JUDGED_SCALES, PipelineConfig
from lerobot_roboscape.pipeline.figures import WM_FIGURE_FRAMES, ppo_curves, world_model_figure
from lerobot_roboscape.pipeline.layout import (
    CONTROL_DIR,
    CONVERTED_DIR,
    DEMOS_DIR,
    DONE_REPORT_DIR,
    EVAL_DIR,
    FIDELITY_DIR,
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
from lerobot_roboscape.pipeline.resume import stage_seconds
from lerobot_roboscape.pipeline.targets import format_value, measure_targets, tokenizer_targets
from lerobot_roboscape.training import read_curve

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
    "fidelity report": [FIDELITY_DIR],
    "reward models, success classifier, done and reward reports": [
        *map(reward_model_dir, (*REWARD_BASELINES, SUCCESS_CLASSIFIER)),
        DONE_REPORT_DIR,
        REWARD_REPORT_DIR,
    ],
    "SFT (lerobot-train)": [*map(sft_dir, POLICIES)],
}


def write_report(cfg: PipelineConfig, out: Path, report_dir: str | None = None) -> Path:
    """Write report.md, results.json and the figures into out/report (and report_dir); returns report.md."""
    folder = out / "report"
    folder.mkdir(parents=True, exist_ok=True)
    tokenizer = json.loads((out / TOKENIZER_REPORT_DIR / "tokenizer_report.json").read_text())
    fidelity = json.loads((out / FIDELITY_DIR / "fidelity.json").read_text())
    done = json.loads((out / DONE_REPORT_DIR / "done_report.json").read_text())
    rewards = json.loads((out / REWARD_REPORT_DIR / "reward_report.json").read_text())
    table = json.loads((out / TABLES_DIR / "tables.json").read_text())
    curve = read_curve(out / world_model_dir("action"))
    targets = tokenizer_targets(tokenizer) | measure_targets(fidelity, done, rewards, table, cfg.families, curve)
    times = stage_times(cfg, out)
    results = {
        "scale": cfg.scale,
        "families": cfg.families,
        "date": date.today().isoformat(),
        "machine": machine(),
        "targets": targets,
        "table": table,
        "stage_seconds": times,
        "tokenizer": tokenizer["views"],
        **world_model_results(fidelity, done, rewards),
    }
    (folder / "results.json").write_text(json.dumps(results, indent=2))

    shutil.copy2(out / TOKENIZER_REPORT_DIR / "reconstruction.png", folder / "tokenizer_reconstruction.png")
    if (out / TOKENIZER_REPORT_DIR / "heldout_curve.png").exists():
        shutil.copy2(out / TOKENIZER_REPORT_DIR / "heldout_curve.png", folder / "tokenizer_curve.png")
    world_model_figure(
        out / FIDELITY_DIR / "side_by_side.mp4", fidelity["prompt_frames"], folder / "world_model_open_loop.png"
    )
    ppo_curves(out, table, folder / "ppo_curves.png")
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


def world_model_results(fidelity: dict, done: dict, rewards: dict) -> dict:
    """What results.json keeps of the fidelity, done and reward reports."""
    return {
        "fidelity": {
            k: fidelity[k] for k in ("mean", "per_step", "controllability", "controllability_long") if k in fidelity
        },
        "done": {k: done[k] for k in ("chosen", "sources")},
        "reward": rewards["summary"],
        "goals": rewards["goals"],
        "similarity": rewards["similarity"],
    }


def protocol(cfg: PipelineConfig) -> str:
    """The experiment's protocol, as the paper's section 8.1, in the words of this run's settings."""
    heldout = (
        f"held-out episodes in {cfg.heldout_scenes} OOD scenes, half of them failed attempts"
        if cfg.heldout_scenes
        else "one recorded and converted IND episode (this scale collects no held-out OOD episodes)"
    )
    budget = (
        f"the same wall-clock budget ({cfg.ppo_minutes:g} min) on the same machine"
        if cfg.ppo_minutes
        else f"the same number of iterations ({cfg.ppo_iterations})"
    )
    length = cfg.table_episode_length or cfg.ppo_episode_length
    ending = f"{length} steps" if length else "the family's horizon (its longest successful demonstration)"
    return (
        f"As the paper's section 8.1: task families {', '.join(cfg.families)}; IND evaluates the training scenes with "
        "new initial states, OOD the held-out scenes (unseen objects and unseen object-container combinations). The "
        "world models and the MLP policy train on the demonstrations of the IND scenes "
        f"({cfg.episodes_per_scene} per family and scene, a quarter of them deliberately failed; SFT imitates the "
        f"successful ones). The fidelity and reward reports use {heldout}. RL: PPO from the SFT checkpoint, one "
        f"multi-task run per env over the families; each run gets {budget}."
        + (
            " RL in ManiSkill runs twice: in one scene (the paper's baseline: the simulator \"only initializes a "
            'single type of environment", section 3.2) and in every training scene.'
            if cfg.ppo_one_scene
            else " RL in ManiSkill runs in every training scene."
        )
        + f" Success: {_episodes(cfg.table_episodes)} in the simulator per (split, family); episodes end at success "
        f"or after {ending}."
    )


def evaluation_summary(cfg: PipelineConfig, table: dict, seconds: dict) -> str:
    """Episodes per cell, each cell's 95% interval width, and the evaluation's time."""
    widths = [
        100 * (cell["ci95"][1] - cell["ci95"][0])
        for methods in table.values()
        for splits in methods.values()
        for cells in splits.values()
        for family, cell in cells.items()
        if family != "all"
    ]
    minutes = sum(v for k, v in seconds.items() if k.startswith("simulator evaluation")) / 60
    return (
        f"Each cell rests on {_episodes(cfg.table_episodes)}; its 95% interval is {min(widths):.0f} to "
        f"{max(widths):.0f} points wide (in parentheses after each interval). The evaluation took "
        f"{minutes:.1f} min ({len(widths)} cells, {cfg.workers} simulator processes)."
    )


def _episodes(n: int) -> str:
    return f"{n} episode" if n == 1 else f"{n} episodes"


def targets_table(targets: dict) -> list[str]:
    """Markdown rows of {target: row}: what was measured, the goal, whether it is met."""
    rows = [
        f"| {name} | {_measured(t)} | {t['goal']} | {'yes' if t['met'] else '**no**'} |" for name, t in targets.items()
    ]
    return ["| target | measured | goal | met |", "|---|---:|---|:---:|", *rows]


def _measured(target: dict) -> str:
    return format_value(target["value"]) + (f" ({target['detail']})" if "detail" in target else "")


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
    return f"simulator evaluation ({jobs} jobs one after another, on {cfg.workers} simulator processes)"


def machine() -> str:
    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else "no GPU"
    return f"{os.cpu_count()} CPU cores ({platform.processor() or platform.machine()}), {gpu}"


def markdown(cfg: PipelineConfig, results: dict, table: dict) -> str:
    targets, times = results["targets"], results["stage_seconds"]
    lines = [
        f"# RoboScape-R at the {cfg.scale} scale",
        "",
        f"{results['machine']}; {results['date']}; the time of each stage is at the end. "
        f"Regenerate with `roboscape-demo --scale={cfg.scale} --output_dir={cfg.output_dir} "
        f"--report_dir=docs/results/{cfg.scale}` (a rerun skips the stages already complete).",
        "",
        "## Protocol",
        "",
        protocol(cfg),
        "",
        "## Targets",
        "",
    ]
    if cfg.scale in JUDGED_SCALES:
        lines += targets_table(targets)
    else:
        lines += [
            f"The {cfg.scale} scale trains every model for minutes to show each stage working; it is too small to "
            f"judge the bench experiment's targets, so none is judged here (`--scale=bench` judges them). What "
            "this run measured:",
            "",
            "| target (bench scale) | measured | goal at the bench scale |",
            "|---|---:|---|",
        ]
        lines += [f"| {name} | {_measured(t)} | {t['goal']} |" for name, t in targets.items()]
    lines += [
        "",
        "## Table 1",
        "",
        format_table(table, cfg.families, f"{cfg.scale} scale"),
        "![Table 1](tables.png)",
        "",
        evaluation_summary(cfg, table, results["stage_seconds"]),
        "",
        "## Tokenizer",
        "",
        "Held-out OOD frames (top) and their reconstruction (bottom), each view, a column per episode at the frame "
        "that shows the object best; the held-out curves of its training:",
        "",
        "![tokenizer](tokenizer_reconstruction.png)",
        "",
        "![tokenizer curves](tokenizer_curve.png)",
        "",
        "## Action world model",
        "",
        f"Open loop from {WM_FIGURE_FRAMES} model frames of held-out recorded actions (each column: real | "
        "predicted, both views), and PSNR/SSIM per step against the tokenizer's own reconstruction:",
        "",
        "![open loop](world_model_open_loop.png)",
        "",
        "![fidelity](fidelity.png)",
        "",
        "## Done",
        "",
        f"Chosen on the validation episodes: {results['done']['chosen']['source']} at threshold "
        f"{results['done']['chosen']['theta']:.3f}. Along held-out episodes (solid: success, dashed: failure; the "
        "vertical lines mark the recorded success):",
        "",
        "![done curves](done_curves.png)",
        "",
        "## Reward",
        "",
        "Start, goal generated by the text model and real final frame of held-out successful episodes (the goal is "
        "nearer the real final frame than the start in "
        f"{format_value(results['goals']['nearer_final_than_start'])} of them):",
        "",
        "![goals](goal_grid.png)",
        "",
        f"Dense reward's similarity: {results['similarity']}. ROC-AUC of the episode return "
        "between successful and failed held-out episodes:",
        "",
        "| reward | ROC-AUC | mean return, success | mean return, failure |",
        "|---|---:|---:|---:|",
    ]
    for kind, s in results["reward"].items():
        lines.append(
            f"| {kind} | {format_value(s['roc_auc_of_return'])} | {format_value(s['mean_return_success'])} | "
            f"{format_value(s['mean_return_failure'])} |"
        )
    lines += [
        "",
        "Rewards along held-out successful episodes (each scaled to [0, 1], as the paper's Fig. 3):",
        "",
        "![reward curves](reward_curves.png)",
        "",
        "## PPO",
        "",
        "![PPO curves](ppo_curves.png)",
        "",
        "## Time per stage",
        "",
        "| stage | minutes |",
        "|---|---:|",
    ]
    lines += [f"| {stage} | {seconds / 60:.1f} |" for stage, seconds in times.items()]
    return "\n".join(lines) + "\n"
