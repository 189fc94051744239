"""RoboScape-R's pipeline as code, the stages `roboscape-demo` runs: the scales that size it (`config.py`, `scales/`),
one function per stage (`stages.py` for the data and models, with `data_stages.py`, `given.py` and
`carried_stages.py`; `policy_stages.py` for SFT, PPO and the simulator's evaluation) and the run from first stage
to last (`run.py`). Beside them, one idea per file: the folders under output_dir (`layout.py`), skipping and
resuming stages (`resume.py`), the stage headers (`clock.py`), the methods (`methods.py`), the LeRobot command lines
(`lerobot_cli.py`), a PPO run's record (`ppo_run.py`), what goes to the Hub (`artifacts.py`), and the run's report
(`report/`). The experiments on a run's stages (the paper's claim, its levers, replays) are
`lerobot_roboscape/experiments/`, which imports from here and never the other way."""
