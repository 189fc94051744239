"""Reproduce the layout of the paper's Table 1 (policy x training method x IND/OOD x task family: SFT, RL in
ManiSkill, RL in the world model) or, with --per_task=false, Table 2 (one multi-task RL run), at the scale the
flags choose. Prints the table and writes tables.md, tables.json and the bar chart tables.png.

Tiny, on CPU, from a `roboscape-demo` run (minutes):

    python scripts/reproduce_tables.py --dataset_repo_id=local/roboscape_demos \
        --dataset_root=outputs/demo/datasets/roboscape_demos --tokenizer=outputs/demo/tokenizer/pretrained_model \
        --action_world_model=outputs/demo/world_model_action/pretrained_model \
        --text_world_model=outputs/demo/world_model_text/pretrained_model \
        --per_task=false --sft_steps=600 --ppo_iterations=3 --num_envs=8 --episode_length=40 \
        --eval_episodes=2 --eval_batch_size=8 --eval_episode_length=60 --output_dir=outputs/tables_tiny

Paper-like, on GPUs (paper presets of the world models, both policies, 50 evaluation episodes per cell):

    python scripts/reproduce_tables.py --dataset_repo_id=me/roboscape --tokenizer=me/roboscape-tokenizer \
        --action_world_model=me/roboscape-wm-action --text_world_model=me/roboscape-wm-text \
        --policies='[roboscape_mlp, openvla]' --image_size=128 --sft_steps=20000 --ppo_iterations=500 \
        --num_envs=64 --eval_episodes=50 --output_dir=outputs/tables

PPO runs each task family's fixed horizon (its longest successful demonstration) unless --episode_length is given;
the world-model env's dense reward uses LPIPS when its trunk weights are in the torch hub cache, else the
tokenizer-feature similarity (see the README).
"""

import logging

import draccus

from lerobot_roboscape.evaluation.tables import TablesConfig, run_tables


def main():
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    cfg = draccus.parse(TablesConfig)
    run_tables(cfg)
    print((cfg.output_dir / "tables.md").read_text())
    print(f"Bar chart: {(cfg.output_dir / 'tables.png').resolve()}")


if __name__ == "__main__":
    main()
