"""RoboScape-R's pipeline as code: the scales that size it (`config.py`), one function per stage (`stages.py` for
the data and models, `policy_stages.py` for SFT, PPO and the simulator's evaluation), the run from first stage to
last (`run.py`) and the paper's claim measured on a run's trained stages (`experiment.py`: what it reads,
`trained.py`; its levers, `levers.py`; its replay, `replay.py`). Beside them, one idea per file: the folders under
output_dir (`layout.py`), skipping and resuming stages (`resume.py`), the stage headers (`clock.py`), the methods
(`methods.py`), the LeRobot command lines (`lerobot_cli.py`), what counts as success (`targets.py`, the world
models' in `world_model_targets.py`, a row's shape in `target_row.py`), the figures (`figures.py`), and the two
reports (`report.py`, `experiment_report.py` with its words in `claim_markdown.py`) rendered from
`lerobot_roboscape/templates/`. `roboscape-demo` and `roboscape-experiment` are thin command lines over it."""
