"""Reproduce the layout of the paper's Table 1 (policy x training method x IND/OOD x task family: SFT, RL in
ManiSkill in one scene and in every training scene, RL in the world model) from models you already have, with the
pipeline's stages (one multi-task RL run per env; `--families=[push]` for a per-family run). Prints the table and
writes tables.md, tables.json and the bar chart tables.png into --output_dir/tables.

From a `roboscape-demo` run (its dataset and models), tiny, on CPU:

    python scripts/reproduce_tables.py --dataset_root=outputs/demo/datasets/roboscape_demos \
        --models=outputs/demo --output_dir=outputs/tables_tiny --pipeline.scale=tiny --pipeline.mlp_steps=600

Paper-like, on GPUs: `--pipeline.scale=paper` and the paper's models (`--models` holds tokenizer/,
world_model_action/ and world_model_text/ as the pipeline writes them).
"""

import logging
from dataclasses import dataclass, field
from pathlib import Path

import draccus
from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.checkpoints import FINAL
from lerobot_roboscape.evaluation.tables import write_table
from lerobot_roboscape.pipeline import stages
from lerobot_roboscape.pipeline.config import PipelineConfig


@dataclass
class TablesConfig:
    """Args:
    dataset_repo_id: the demonstrations (SFT, and the world-model env's initial frames).
    dataset_root: their local root.
    models: a folder holding tokenizer/, world_model_action/ and world_model_text/ (as roboscape-demo writes).
    output_dir: where SFT, PPO, evaluations and the tables go.
    pipeline: sizes of the stages (--pipeline.scale, --pipeline.mlp_steps, --pipeline.ppo_minutes, ...).
    """

    dataset_repo_id: str = "local/roboscape_demos"
    dataset_root: str | None = None
    models: Path = Path("outputs/demo")
    output_dir: Path = Path("outputs/tables")
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)


def main():
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    cfg = draccus.parse(TablesConfig)
    p, out = cfg.pipeline, Path(cfg.output_dir).resolve()
    dataset = DatasetConfig(repo_id=cfg.dataset_repo_id, root=cfg.dataset_root)
    data = stages.Datasets(train=dataset, heldout=dataset, trajectory_file=Path())
    tokenizer = Path(cfg.models) / "tokenizer" / FINAL
    models = {c: Path(cfg.models) / f"world_model_{c}" / FINAL for c in ("action", "text")}
    sft = stages.sft(p, out, data)
    rl = stages.rl(p, out, data, stages.world_model_env(p, data, tokenizer, models), sft)
    table = stages.simulator_eval(p, out, data, {n: {stages.SFT: sft[n]} | runs for n, runs in rl.items()})
    write_table(table, p.families, out / "tables")
    print((out / "tables" / "tables.md").read_text())
    print(f"Bar chart: {out / 'tables' / 'tables.png'}")


if __name__ == "__main__":
    main()
