"""The claim experiment's report in words (report.md) and the README's results block, rendered from the summary
that results.json holds: the answer first, the protocol, Table 1 with the paper's rows, the differences, the reward
ablation, the levers' rows and the command that regenerates it."""

import re
from pathlib import Path

from lerobot_roboscape.evaluation.results import ALL, Cell, Difference, Results
from lerobot_roboscape.evaluation.tables import (
    SHORT,
    SPLIT_NAMES,
    format_table,
)
from lerobot_roboscape.experiments.claim_summary import ClaimSummary, WorldModelRunsRecord
from lerobot_roboscape.experiments.replay import agreed
from lerobot_roboscape.pipeline.config import changed_flags, settings_flags
from lerobot_roboscape.pipeline.methods import (
    PAPER_PROTOCOL,
    RL_MANISKILL,
    RL_MANISKILL_ONE_SCENE,
    RL_WORLD_MODEL,
    SFT,
    Method,
    initial_scene,
)
from lerobot_roboscape.pipeline.report.write import render_pipeline_report

README_BEGIN, README_END = "<!-- bench-results:begin -->", "<!-- bench-results:end -->"
UPSTREAM_REPORTS = {
    "tokenizer": "docs/results/tokenizer/report.md",
    "world models, done and reward": "docs/results/world_model/report.md",
    "SFT": "docs/results/sft/report.md",
    "simulator speed": "docs/results/simulator/report.md",
}


def paper_methods(table: Results | dict) -> dict:
    """{our method: the paper's row beside it}: the paper's RL w. ManiSkill "only initializes a single type of
    environment", so it sits beside our run in one scene when there is one; our run over every training scene is
    the baseline the paper lacks."""
    table = Results.of(table)
    if any(table.has(policy, RL_MANISKILL_ONE_SCENE) for policy in table.policies):
        return {RL_MANISKILL_ONE_SCENE: RL_MANISKILL, RL_MANISKILL: None}
    return {}


def cell(cell: Cell | dict) -> str:
    """A cell (or a checkpoint curve's point, which holds one) as the report's tables show it."""
    c = Cell.from_json(cell)
    low, high = (100 * v for v in c.ci95)
    return f"{c.successes}/{c.episodes} ({100 * c.success_rate:.0f}% [{low:.0f}, {high:.0f}])"


def difference(d: Difference) -> str:
    low, high = d.ci95
    text = f"{100 * d.difference:+.0f} [{100 * low:+.0f}, {100 * high:+.0f}]"
    if d.paired_ci95:
        low, high = d.paired_ci95
        text += f" paired [{100 * low:+.0f}, {100 * high:+.0f}]"
    return text


FILTERS = {"cell": cell, "difference": difference}  # beside the run report's


def protocol(cfg, elsewhere: WorldModelRunsRecord | None = None) -> str:
    """The protocol's paragraph; `elsewhere`: where the runs in the world model ran (world_model_runs_record)."""
    p = cfg.pipeline
    if cfg.sft_checkpoint:
        sft = f"the SFT checkpoint `{cfg.sft_checkpoint}`"
    elif cfg.protocol == PAPER_PROTOCOL:
        sft = f"SFT with lerobot-train on the demonstrations of the initial scene only (`{initial_scene()}`)"
        if cfg.sft_dataset_root:
            sft += f" in `{cfg.sft_dataset_root}`"
        elif p.data.initial_scene_episodes:
            sft += f": the successful ones of {p.data.initial_scene_episodes} planner attempts per family there"
    else:
        sft = "SFT with lerobot-train on the demonstrations of every training scene"
    name = (
        "The paper's protocol (`--protocol=paper`): the policy learned one scene; RL in the world model meets "
        "every training scene. "
        if cfg.protocol == PAPER_PROTOCOL
        else "The all-scene protocol (`--protocol=all_scenes`): the policy learned every training scene. "
    )
    budget = (
        f"{'' if elsewhere else 'the same '}{p.ppo.time_budget_s / 60:g} min of PPO's clock (rollouts and updates)"
        if p.ppo.time_budget_s
        else f"the same number of iterations ({p.ppo.iterations})"
    )
    steps = f"{p.env.episode_length} steps" if p.env.episode_length else "the family's horizon"
    length = p.eval.episode_length or p.env.episode_length
    envs = "`roboscape_wm` starting from the first frame of a demonstration in every training scene (" + (
        f"{p.env.starts_per_scene} per family and scene)" if p.env.starts_per_scene else "every demonstration)"
    )
    if p.ppo_one_scene:
        envs += (
            f", `roboscape_maniskill` in the initial scene `{initial_scene()}` (the paper's baseline, which "
            '"only initializes a single type of environment")'
        )
    envs += " and `roboscape_maniskill` in every training scene"
    return name + (
        f"Task families {', '.join(p.data.families)}. PPO starts from {sft}, one multi-task run per env, "
        f"{p.ppo.num_envs} parallel episodes of {steps} per iteration, for {budget}"
        + (
            f" on the same machine, one run at a time: {envs}."
            if not elsewhere
            else f": {envs}. The runs in `roboscape_wm` ran where its models were trained "
            f"({elsewhere.gpu or 'no GPU'}, `--world_model_runs`), side by side, one process each, for "
            + (
                f"{elsewhere.time_budget_s / 60:.3g} min of PPO's clock"
                if elsewhere.time_budget_s
                else "the same iterations"
            )
            + "; those in the simulator here, one at a time; the table of PPO's runs gives each its env steps."
        )
        + " The world model's reward is the paper's: alpha x the sparse done reward + beta x the "
        "similarity to the goal frame the text model generated"
        + ("; the reward ablation pays one term only" if p.reward_ablation else "")
        + f". Success is measured in the simulator, {p.eval.episodes} episodes per (split, family) on the same "
        "initial states for every method; episodes end at success or after "
        + (f"{length} steps" if length else "the family's horizon")
        + ". "
        + (
            f"Scene: the initial scene `{initial_scene()}` with new initial states (the paper's IND, section 8.1: "
            '"train the policy in one environment and evaluate it in the same environment but with different initial '
            'states"); '
            if cfg.protocol == PAPER_PROTOCOL
            else ""
        )
        + "IND: the training scenes with new initial states; OOD: the held-out scenes (unseen objects and "
        "object-container pairs). Differences are our success minus theirs, with Newcombe's 95% interval for "
        "independent proportions and, since every method ran from the same initial states, his interval for "
        "paired proportions beside it (pairs of episodes from one initial state), which decides the targets."
    )


def answer(summary: ClaimSummary) -> list[str]:
    """The report's first lines: did PPO in the world model lift SFT out of domain (all families), by how much
    against SFT and each PPO in the simulator (paired intervals where kept), and how often the world model agreed
    with the simulator on that policy's replayed rollouts."""
    lines, by, table = [], summary.by_comparison(), summary.table
    for policy in table.policies:
        sft, wm = (table.cell(policy, m, "ood") for m in (SFT, RL_WORLD_MODEL))
        row = by[policy, SFT, "ood", ALL]
        low, high = row.interval
        verdict = "**Yes**" if low > 0 else "**No, it made it worse**" if high < 0 else "**Not shown**"
        lines.append(
            f"{verdict} ({policy}): PPO in the world model took the SFT policy from {sft.success_rate:.0%} to "
            f"{wm.success_rate:.0%} success out of domain ({wm.episodes} episodes, the same starts for each): "
            + _points(row)
        )
        for other in (RL_MANISKILL_ONE_SCENE, RL_MANISKILL):
            if (policy, other, "ood", ALL) in by:
                rate = table.cell(policy, other, "ood").success_rate
                lines.append(f"Against {other} ({rate:.0%} OOD): " + _points(by[policy, other, "ood", ALL]))
    replays = summary.replays
    lines.append(
        f"The world model agreed with the simulator on the outcome of {agreed(replays)} of {len(replays)} of this "
        f"policy's rollouts replayed there (successes: {sum(r.world_model_success for r in replays)} in the world "
        f"model, {sum(r.simulator_success for r in replays)} in the simulator)."
    )
    return lines


def _points(row: Difference) -> str:
    low, high = row.interval
    return f"{100 * row.difference:+.0f} points, {row.kind} 95% interval [{100 * low:+.0f}, {100 * high:+.0f}]."


def markdown(cfg, summary: "ClaimSummary | dict") -> str:
    summary = ClaimSummary.from_json(summary)
    p, table = cfg.pipeline, summary.table
    families = [*p.data.families, ALL]
    by = summary.by_comparison()
    difference_rows = [
        (other, SPLIT_NAMES[split], [by[policy, other, split, f] for f in families])
        for policy in table.policies
        for other in (SFT, RL_MANISKILL_ONE_SCENE, RL_MANISKILL)
        for split in table.splits()
        if (policy, other, split, ALL) in by
    ]
    ablation, ablation_rows = summary.reward_ablation, []
    for policy in ablation.policies:
        if methods := ablation.methods(policy):
            rows = {"both (alpha x sparse + beta x dense)": RL_WORLD_MODEL} | {
                Method.named(m).variant: m for m in methods
            }
            source = {RL_WORLD_MODEL: table} | dict.fromkeys(methods, ablation)
            ablation_rows += [
                (name, [source[m].cell(policy, m, "ood", f) for f in families]) for name, m in rows.items()
            ]
    return render_pipeline_report(
        "claim_report.md",
        FILTERS,
        p=p,
        summary=summary,
        targets=summary.targets,
        command=command(cfg),
        upstream={name: _relative(path, cfg.report_dir) for name, path in UPSTREAM_REPORTS.items()},
        protocol=protocol(cfg, summary.world_model_runs),
        answer=answer(summary),
        table=format_table(table, p.data.families, f"{p.scale} scale", True, paper_methods(table)),
        other=summary.other_protocol
        and (
            summary.other_protocol.protocol,
            format_table(summary.other_protocol.table, p.data.families, f"{p.scale} scale"),
        ),
        short=SHORT,
        difference_rows=difference_rows,
        ablation_rows=ablation_rows,
        lever_rows=lever_rows(summary, families),
        replays=summary.replays,
        agree=agreed(summary.replays),
        signal_rows=signal_rows(summary) if summary.lever_replays else [],
    )


def lever_rows(summary: ClaimSummary, families: list[str]) -> list[tuple]:
    """Each lever's row: its method, its description, its OOD cells, its OOD difference from PPO in the world model
    without a lever (the same initial states: paired), its checkpoint curve and the simulator steps that ran beside
    its PPO (the done refresh's)."""
    beside = {(r.policy, r.method): r.simulator_steps_beside_ppo or 0 for r in summary.ppo_runs}
    levers, table = summary.levers, summary.table
    return [
        (
            method,
            summary.lever_settings.get(method, ""),
            [levers.cell(policy, method, "ood", f) for f in families],
            Difference.between(
                levers.cell(policy, method, "ood"),
                table.cell(policy, RL_WORLD_MODEL, "ood"),
                policy,
                RL_WORLD_MODEL,
                "ood",
                ALL,
            ),
            summary.lever_curves[method],
            beside.get((policy, method), 0),
        )
        for policy in levers.policies
        for method in levers.methods(policy)
    ]


def signal_rows(summary: ClaimSummary) -> list[tuple]:
    """Per run in the world model (the plain one, then each lever's): its method, the share of episodes its done
    fired in at its first and last iterations, and of its replayed rollouts: the world model's successes the
    simulator confirmed, those successes, the outcomes both worlds agreed on, the replays, and its picture."""
    runs = {r.method: r for r in summary.ppo_runs}
    replays = {RL_WORLD_MODEL: summary.replays} | summary.lever_replays
    rows = []
    for method, replayed in replays.items():
        run, called = runs.get(method), [r for r in replayed if r.world_model_success]
        picture = "replay.png" if method == RL_WORLD_MODEL else f"replay_{Method.named(method).tag}.png"
        fired = (run.first_success, run.last_success) if run else None
        confirmed = sum(r.simulator_success for r in called)
        rows.append((method, fired, confirmed, len(called), agreed(replayed), len(replayed), picture))
    return rows


def command(cfg) -> str:
    """The command that regenerates the report: the scale, and every setting that differs from its file."""
    p = cfg.pipeline
    parts = [f"roboscape-experiment --protocol={cfg.protocol} --pipeline.scale={p.scale}"]
    parts.append(f"--pipeline.output_dir={p.output_dir}")
    parts += [flag.replace("--", "--pipeline.", 1) for flag in settings_flags(p)]
    parts += changed_flags(cfg, type(cfg)(), ("pipeline", "protocol", "report_dir", "readme"))
    parts.append(f"--report_dir={cfg.report_dir}")
    if cfg.readme != "README.md":
        parts.append(f"--readme={cfg.readme or 'null'}")
    return " ".join(parts)


def _relative(path: str, report_dir: str) -> str:
    return str(Path("../" * len(Path(report_dir).parts)) / path)


def readme_block(cfg, summary: "ClaimSummary | dict") -> str:
    """The README's results: the claim's targets and Table 1, with the machine and the command."""
    p, summary = cfg.pipeline, ClaimSummary.from_json(summary)
    table = format_table(summary.table, p.data.families, f"{p.scale} scale", True, paper_methods(summary.table))
    text = render_pipeline_report(
        "readme_results.md", cfg=cfg, summary=summary, targets=summary.targets, command=command(cfg), table=table
    )
    return text.rstrip("\n") + "\n"  # one final newline, whatever the template's file ends with


def update_readme(readme: Path, block: str) -> None:
    """Replace what stands between the README's results markers with `block`."""
    text = readme.read_text()
    pattern = re.compile(re.escape(README_BEGIN) + ".*?" + re.escape(README_END), re.S)
    if not pattern.search(text):
        raise ValueError(f"{readme} has no {README_BEGIN} ... {README_END} block for the results")
    readme.write_text(pattern.sub(lambda _: f"{README_BEGIN}\n{block}\n{README_END}", text))
