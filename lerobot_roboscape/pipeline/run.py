"""The whole pipeline, stage after stage (the data and model stages in `stages.py`, the policy stages in
`policy_stages.py`), with a header and the time of each stage."""

import contextlib
import io
import time
from pathlib import Path

from lerobot_roboscape.envs import reward_report
from lerobot_roboscape.evaluation.tables import write_table
from lerobot_roboscape.hub.push import push_run
from lerobot_roboscape.pipeline import data_stages, layout, methods, policy_stages, stages
from lerobot_roboscape.pipeline.artifacts import ArtifactKind, Artifacts, load_artifact
from lerobot_roboscape.pipeline.clock import StageClock, StopAfter
from lerobot_roboscape.pipeline.config import PipelineConfig, preset
from lerobot_roboscape.pipeline.report.write import write_report
from lerobot_roboscape.tokenizer import report as tokenizer_report
from lerobot_roboscape.world_model.measures import fidelity as fidelity_report

# The demo's stages, in order; each header names one, with the details of this run.
STAGES = (
    "collect",
    "tokenizer",
    "tokenizer report",
    "world models",
    "fidelity report",
    "done and reward",
    "world-model rollout",
    "SFT",
    "lerobot-eval in the world model",
    "PPO",
    "Table 1",
    "push",
    "report",
)


def run_pipeline(cfg: PipelineConfig) -> Artifacts:
    """Run every stage (skipping those already complete in output_dir), or those up to cfg.stop_after; returns
    {artifact name: artifact} of the stages run."""
    artifacts = Artifacts()
    with contextlib.suppress(StopAfter):
        _run_stages(cfg, StageClock(STAGES, cfg.stop_after), artifacts)
    return artifacts


def _run_stages(cfg: PipelineConfig, clock: StageClock, artifacts: Artifacts) -> None:
    out = Path(cfg.output_dir).resolve()
    data, tokenizer, models, wm_env = _data_and_world_models(cfg, out, clock, artifacts)
    checkpoints = _policies(cfg, out, clock, artifacts, data, wm_env)
    _push_and_report(cfg, out, clock, artifacts, data, tokenizer, models, checkpoints)


def _data_and_world_models(cfg: PipelineConfig, out: Path, clock: StageClock, artifacts: Artifacts):
    """The stages up to the world-model env: the data, the tokenizer, the world models, their reports, the done
    signal, the rewards and a rollout in the env. Returns (data, tokenizer, world models, the env's config)."""

    clock("collect", "collect demonstrations and held-out episodes (ManiSkill); record and convert a trajectory file")
    data = data_stages.demonstrations(cfg.data, out, cfg.fresh)
    artifacts.add("demonstrations (LeRobotDataset)", ArtifactKind.DATASET, Path(data.train.root))
    artifacts.add("held-out episodes (LeRobotDataset)", ArtifactKind.DATASET, Path(data.heldout.root))
    artifacts.add("ManiSkill trajectory file", ArtifactKind.TRAJECTORY_FILE, data.trajectory_file)

    clock("tokenizer", f"train the image tokenizer ({preset(cfg.tokenizer)} preset)")
    tokenizer = stages.tokenizer(cfg, out, data)
    artifacts.add("tokenizer", ArtifactKind.TOKENIZER, tokenizer)

    clock("tokenizer report", "tokenizer report on the held-out frames (whole frame, object, codebook; each view)")
    print(tokenizer_report.headline(stages.tokenizer_report(cfg, out, data, tokenizer)))
    artifacts.add("tokenizer report", ArtifactKind.MARKDOWN, out / layout.TOKENIZER_REPORT_DIR / "tokenizer_report.md")

    clock("world models", f"train the action and the text world models ({preset(cfg.wm)} preset)")
    models = stages.world_models(cfg, out, data, tokenizer)
    for control, path in models.items():
        artifacts.add(f"{control} world model", ArtifactKind.WORLD_MODEL, path)

    clock("fidelity report", "fidelity of the action world model: new starts of its training scenes, then OOD")
    for domain in ("ind", "ood"):
        fidelity = stages.fidelity(cfg, out, data, tokenizer, models, domain)
        if fidelity is None:
            continue
        print(f"{domain.upper()}: {fidelity_report.headline(fidelity)}")
        name = "fidelity report" + (" IND" if domain == "ind" else "")
        artifacts.add(name, ArtifactKind.MARKDOWN, out / layout.fidelity_dir(domain) / "fidelity.md")
    artifacts.add("predicted vs real video", ArtifactKind.VIDEO, out / layout.FIDELITY_DIR / "side_by_side.mp4")

    clock("done and reward", "reward models, the done signal and the reward report (held-out episodes)")
    trained = stages.reward_models(cfg, out, data, tokenizer, models)
    done = stages.done_report(cfg, out, data, tokenizer, models, trained)
    print(f"done: {done.source} at threshold {done.theta:.3f}")
    for name, folder in (("done report", layout.DONE_REPORT_DIR), ("done report IND", layout.DONE_REPORT_IND_DIR)):
        if (out / folder).is_dir():
            artifacts.add(name, ArtifactKind.MARKDOWN, out / folder / "done_report.md")
    wm_env = stages.world_model_env(cfg, data.train, tokenizer, models, done, trained)
    rewards = stages.reward_report(cfg, out, data, wm_env, trained)
    print(reward_report.headline(rewards))
    artifacts.add("reward report", ArtifactKind.MARKDOWN, out / layout.REWARD_REPORT_DIR / "reward_report.md")

    clock("world-model rollout", "random actions in the roboscape_wm environment (world-model reward)")
    rollout = stages.world_model_rollout(out, wm_env)
    print(f"{rollout.steps} steps of {rollout.episodes} episodes, return {rollout.returns}")
    artifacts.add("roboscape_wm rollout video (frame | goal)", ArtifactKind.VIDEO, rollout.video)
    artifacts.add("roboscape_wm reward curve", ArtifactKind.IMAGE, rollout.plot)
    return data, tokenizer, models, wm_env


def _policies(cfg: PipelineConfig, out: Path, clock: StageClock, artifacts: Artifacts, data, wm_env) -> dict:
    """SFT, LeRobot's evaluation in the world model, PPO in both envs and Table 1; returns {policy: {method:
    checkpoint}}."""
    clock("SFT", "SFT with lerobot-train: " + " and ".join(policy_stages.policy_specs(cfg)))
    sft = policy_stages.sft(cfg, out, data.train)
    for name, path in sft.items():
        artifacts.add(f"{name} after SFT", ArtifactKind.POLICY, path)

    clock("lerobot-eval in the world model", "lerobot-eval in roboscape_wm (LeRobot's evaluation in the world model)")
    for name, path in policy_stages.lerobot_eval_in_world_model(cfg, out, sft, wm_env).items():
        artifacts.add(f"{name} lerobot-eval in roboscape_wm", ArtifactKind.JSON, path)

    clock(
        "PPO",
        "PPO in roboscape_wm and in roboscape_maniskill"
        + (f" (each {cfg.ppo.time_budget_s / 60:g} min)" if cfg.ppo.time_budget_s else ""),
    )
    rl = policy_stages.rl(cfg, out, data.train, wm_env, sft)
    checkpoints = policy_stages.every_checkpoint(sft, rl)
    for name, runs in rl.items():
        for method, path in runs.items():
            artifacts.add(f"{name} after {method}", ArtifactKind.POLICY, path)

    clock("Table 1", "success in the simulator, IND and OOD (Table 1)")
    table = policy_stages.simulator_eval(cfg, out, data.train, checkpoints)
    # Table 1's methods; the reward ablation's OOD rows are roboscape-experiment's to report.
    table = table.where(lambda method: method not in methods.REWARD_ABLATION)
    tables = out / layout.TABLES_DIR
    write_table(table, cfg.data.families, tables)
    print((tables / "tables.md").read_text())
    artifacts.add("Table 1", ArtifactKind.MARKDOWN, tables / "tables.md")
    artifacts.add("Table 1 bar chart", ArtifactKind.IMAGE, tables / "tables.png")
    return checkpoints


def _push_and_report(
    cfg, out: Path, clock: StageClock, artifacts: Artifacts, data, tokenizer, models, checkpoints
) -> None:
    """Every artifact to the Hub (or a folder shaped like it), the run's report, and the table of what was made."""
    hub = out / "hub"
    clock("push", "push to the Hub" if cfg.push_to_hub else f"push to a local folder shaped like the Hub ({hub})")
    local_dir = None if cfg.push_to_hub else hub
    labels = {"dataset repo": ArtifactKind.DATASET, "world models repo": ArtifactKind.WORLD_MODELS_BUNDLE}
    policies = {}
    for name, runs in checkpoints.items():
        for method, checkpoint in runs.items():
            tag = methods.Method.named(method).tag
            policies[f"{name}_{tag}"] = (checkpoint, out / layout.eval_dir(name, method))
            labels[f"{name} {tag} repo"] = ArtifactKind.POLICY
    world_models = dict(
        tokenizer=tokenizer,
        action_world_model=models.action,
        text_world_model=models.text,
        fidelity_dir=out / layout.FIDELITY_DIR,
    )
    pushed = push_run(cfg.hub_namespace, local_dir, Path(data.train.root), world_models, policies)
    for (label, kind), where in zip(labels.items(), pushed.values(), strict=True):
        print(f"{label:36s} {where}")
        if local_dir is not None:
            artifacts.add(label, kind, Path(where))

    clock("report", "the experiment's report")
    report = write_report(cfg, out, cfg.report_dir)
    artifacts.add("experiment report", ArtifactKind.MARKDOWN, report)
    clock.done()

    print(f"\n=== results ({(time.time() - clock.began) / 60:.1f} min) ===")
    for name, artifact in artifacts.items():
        with contextlib.redirect_stdout(io.StringIO()):  # LeRobot's from_pretrained prints where it loads from
            loaded = load_artifact(artifact)
        print(f"{name:44s} {loaded:34s} {artifact.path}")
