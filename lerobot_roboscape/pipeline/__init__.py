"""RoboScape-R's pipeline as code: one function per stage (`stages.py`), the scales that size them (`config.py`),
the run from first stage to last (`run.py`) and its report (`report.py`), and the paper's claim measured on a run's
trained stages (`experiment.py`, its report in `experiment_report.py`). `roboscape-demo` and
`roboscape-experiment` are thin command lines over it."""
