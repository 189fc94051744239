"""The experiments on a pipeline run's trained stages, behind `roboscape-experiment` and
`roboscape-run-world-model-pack`: the paper's claim measured (`experiment.py`; what it reads, `trained.py`; its
levers, `levers.py` with the done's refresh in `done_refresh.py`; the replay in the simulator, `replay.py`; the
checkpoint curves, `curves.py`), its targets (`claim_targets.py`), its records (`claim_summary.py`), its report
(`experiment_report.py` with its words in `claim_markdown.py`), and the world models trained elsewhere and packed
for a run (`world_model_runs.py`, `pack_format.py`)."""
