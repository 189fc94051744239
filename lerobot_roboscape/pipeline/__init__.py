"""RoboScape-R's pipeline as code: one function per stage (`stages.py`), the scales that size them (`config.py`),
the run from first stage to last (`run.py`) and the experiment's report (`report.py`). `roboscape-demo` and
`scripts/reproduce_tables.py` are thin command lines over it."""
