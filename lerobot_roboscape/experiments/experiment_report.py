"""The claim experiment's report (`roboscape-experiment`): the targets with the 95% intervals of the differences,
Table 1 with the paper's numbers beside, PPO's curves, the simulator success of PPO's checkpoints along its run,
world-model rollouts replayed in the simulator, the reward ablation and the time of each step (report.md,
results.json, figures, videos), and the README's results block."""

import json
import shutil
from datetime import date
from pathlib import Path

import matplotlib
import numpy as np

from lerobot_roboscape.envs.goal_bank import goal_generation_seconds
from lerobot_roboscape.evaluation.results import ALL, Difference, Results
from lerobot_roboscape.evaluation.tables import (
    TABLES_JSON,
    write_table,
)
from lerobot_roboscape.experiments.claim_markdown import markdown, readme_block, update_readme
from lerobot_roboscape.experiments.claim_summary import ClaimSummary, OtherProtocol, PpoRun, WorldModelRunsRecord
from lerobot_roboscape.experiments.claim_targets import claim_targets, signal_targets
from lerobot_roboscape.experiments.curves import Curves
from lerobot_roboscape.experiments.done_refresh import refresh_rounds
from lerobot_roboscape.experiments.levers import lever_descriptions
from lerobot_roboscape.experiments.pack_format import PackResults
from lerobot_roboscape.experiments.replay import REPLAY_PNG, Replay
from lerobot_roboscape.experiments.world_model_runs import GOALS, RUNS_DIR
from lerobot_roboscape.io.records import from_record
from lerobot_roboscape.pipeline.layout import (
    CURVE_DIR,
    EVAL_DIR,
    GOAL_FILE,
    REPLAY_DIR,
    protocol_dir,
    replay_dir,
    rl_dir,
)
from lerobot_roboscape.pipeline.methods import (
    PROTOCOLS,
    REWARD_ABLATION,
    RL_MANISKILL,
    RL_MANISKILL_ONE_SCENE,
    RL_WORLD_MODEL,
    SFT,
    Method,
)
from lerobot_roboscape.pipeline.report.figures import curve_figure, gaming_figure, ppo_curves
from lerobot_roboscape.pipeline.report.write import machine
from lerobot_roboscape.pipeline.resume import stage_seconds
from lerobot_roboscape.rl.history import read_ppo_history

matplotlib.use("Agg")


def differences(table: Results | dict, families: list[str]) -> list[Difference]:
    """PPO in the world model minus every other method, per policy, split and family, with 95% intervals."""
    rows, table = [], Results.of(table)
    for policy in table.policies:
        for other in (SFT, RL_MANISKILL_ONE_SCENE, RL_MANISKILL):
            if not table.has(policy, other):
                continue
            for split in table.splits():
                for family in [*families, ALL]:
                    ours, theirs = (table.cell(policy, m, split, family) for m in (RL_WORLD_MODEL, other))
                    rows.append(Difference.between(ours, theirs, policy, other, split, family))
    return rows


def ppo_runs(out: Path, policies: list[str], methods: list[str]) -> list[PpoRun]:
    """What each PPO run did in its budget: iterations, PPO's clock, env steps, the last iterations' training
    success and return in its own env, and the run's wall-clock with its setup (env, goals)."""
    mean = lambda values, digits: round(float(np.mean(values)), digits)  # noqa: E731
    rows = []
    for policy in policies:
        for method in methods:
            folder = out / rl_dir(policy, method)
            history = read_ppo_history(folder)
            if not history:
                continue
            first, last = history[0], history[-3:]
            ensemble = first.disagreement is not None  # an ensemble guarded the run: how far from the data it went
            halts = ensemble or any(row.halted for row in history)  # a guard halted its episodes
            rows.append(
                PpoRun(
                    policy,
                    method,
                    iterations=history[-1].iteration,
                    ppo_seconds=round(history[-1].seconds, 1),
                    decisions=sum(row.samples for row in history),
                    first_return=round(first.episode_return, 3),
                    last_return=mean([row.episode_return for row in last], 3),
                    first_success=round(first.success, 3),
                    last_success=mean([row.success for row in last], 3),
                    wall_seconds=stage_seconds(folder),
                    simulator_steps_beside_ppo=sum(r.simulator_steps for r in refresh_rounds(folder)),
                    first_disagreement=round(first.disagreement, 4) if ensemble else None,
                    last_disagreement=mean([row.disagreement for row in last], 4) if ensemble else None,
                    last_halted=mean([row.halted for row in last], 3) if halts else None,
                )
            )
    return rows


def write_experiment_report(
    cfg,
    out: Path,
    results: Results,
    curves: Curves,
    replays: dict[str, list[Replay]],
    brought_back: PackResults | None = None,
) -> Path:
    """Write report.md, results.json, the figures and the replay videos into cfg.report_dir, and the README's
    results block; returns report.md. `replays`: each world-model run's, by method; `brought_back`: what the device
    reported of the runs in the world model, where they ran elsewhere."""
    p, folder = cfg.pipeline, Path(cfg.report_dir)
    folder.mkdir(parents=True, exist_ok=True)
    curve, lever_curves = curves.world_model, curves.levers
    table = results.where(lambda m: not Method.named(m).ood_only)
    ablation = results.where(lambda m: m in REWARD_ABLATION)
    levers = results.where(lambda m: m in lever_curves)
    policies = table.policies
    methods = [RL_WORLD_MODEL, RL_MANISKILL_ONE_SCENE, RL_MANISKILL, *REWARD_ABLATION, *lever_curves]
    runs = ppo_runs(out, policies, methods)
    targets = claim_targets(table, p.data.families, curve) | signal_targets(runs, replays)
    elsewhere = world_model_runs_record(cfg, brought_back)
    times = step_times(out, runs, Path(elsewhere.goals) if elsewhere else Path(p.output_dir).resolve() / GOAL_FILE)
    summary = ClaimSummary(
        protocol=cfg.protocol,
        scale=p.scale,
        families=p.data.families,
        date=date.today().isoformat(),
        machine=machine(),
        sft_checkpoint=cfg.sft_checkpoint,
        targets=targets,
        table=table,
        differences=differences(table, p.data.families),
        reward_ablation=ablation,
        levers=levers,
        ppo_runs=runs,
        curve=curve,
        lever_curves=lever_curves,
        lever_settings=lever_descriptions(lever_curves, cfg.lever),
        baseline_curves=curves.baselines,
        replays=replays[RL_WORLD_MODEL],
        lever_replays={m: rows for m, rows in replays.items() if m != RL_WORLD_MODEL},
        seconds=times,
        world_model_runs=elsewhere,
        other_protocol=other_protocol(cfg, out),
    )
    (folder / "results.json").write_text(json.dumps(summary.to_json(), indent=2))
    # Table 1 beside this protocol's runs, where the other protocol's report finds it.
    (out / PROTOCOL_TABLE).write_text(json.dumps({"protocol": cfg.protocol, "table": table.to_json()}, indent=2))
    write_table(table, p.data.families, folder, f"{p.scale} scale")
    (folder / TABLES_JSON).unlink()  # results.json holds it
    ppo_curves(out, policies, folder / "ppo_curves.png", methods)
    curve_figure(out, policies[0], curve, folder / "curve.png")
    gaming_figure(out, policies[0], {RL_WORLD_MODEL: curve} | lever_curves, folder / "gaming.png")
    copy_replays(out, replays, folder)
    text = markdown(cfg, summary)
    (folder / "report.md").write_text(text)
    if cfg.readme:
        update_readme(Path(cfg.readme), readme_block(cfg, summary))
    return folder / "report.md"


def world_model_runs_record(cfg, results: PackResults | None) -> WorldModelRunsRecord | None:
    """Where the runs in the world model ran, when they ran elsewhere (--world_model_runs) and came back with
    `results`: the folder they came back to, the GPU, the done threshold chosen there, the goals' file."""
    if results is None:
        return None
    folder = Path(cfg.world_model_runs).resolve() / RUNS_DIR
    return WorldModelRunsRecord(str(folder), results.gpu, results.done, results.time_budget_s, str(folder / GOALS))


PROTOCOL_TABLE = "table1.json"  # each protocol's Table 1, in its folder of the run (layout.protocol_dir)


def copy_replays(out: Path, replays: dict[str, list[Replay]], folder: Path) -> None:
    """Each run's replay videos into folder/videos (a lever's under its tag) and its picture beside the report (the
    plain run's as replay.png, a lever's as replay_<tag>.png)."""
    videos = folder / "videos"
    shutil.rmtree(videos, ignore_errors=True)
    for method, rows in replays.items():
        plain, tag = method == RL_WORLD_MODEL, Method.named(method).tag
        dest = videos if plain else videos / tag
        dest.mkdir(parents=True)
        for row in rows:
            shutil.copy2(out / replay_dir(method) / row.video, dest / row.video)
        shutil.copy2(out / replay_dir(method) / REPLAY_PNG, folder / (REPLAY_PNG if plain else f"replay_{tag}.png"))


def other_protocol(cfg, out: Path) -> OtherProtocol | None:
    """The other protocol's Table 1 on the same run (its world models, goals and data), when it ran: {protocol,
    table}."""
    run = Path(cfg.pipeline.output_dir).resolve()
    for name in PROTOCOLS:
        path = run / protocol_dir(name) / PROTOCOL_TABLE
        if name != cfg.protocol and path.is_file():
            return from_record(OtherProtocol, json.loads(path.read_text()))
    return None


def step_times(out: Path, runs: list[PpoRun], goal_file: Path) -> dict[str, float]:
    """Seconds of each step of the experiment, from the stage records in `out`. A PPO run's wall-clock holds its
    setup too: the first world-model run's holds the generation of every start's goal."""
    times = {}
    goals = goal_generation_seconds(goal_file)
    if goals is not None:
        times["goals of the world-model starts (the text model, once, before PPO's clock)"] = goals
    for run in runs:
        times[f"PPO {run.method}: PPO's clock (the budget)"] = run.ppo_seconds
        if run.wall_seconds:
            times[f"PPO {run.method}: wall-clock with its setup"] = run.wall_seconds
    evaluations = [stage_seconds(f.parent) or 0.0 for f in (out / EVAL_DIR).glob("*/*/*/stage.json")]
    times[f"simulator evaluation, Table 1 and the ablation ({len(evaluations)} jobs)"] = sum(evaluations)
    curves = (out / CURVE_DIR).glob("*/**/stage.json")  # a folder per policy (and per lever), then per checkpoint
    points = [stage_seconds(f.parent) or 0.0 for f in curves]
    times[f"simulator evaluation of PPO's checkpoints ({len(points)} points)"] = sum(points)
    replays = [stage_seconds(f.parent) or 0.0 for f in (out / REPLAY_DIR).glob("*/stage.json")]
    times[f"world-model rollouts replayed in the simulator ({len(replays)} runs)"] = sum(replays)
    return {k: round(v, 1) for k, v in times.items()}
