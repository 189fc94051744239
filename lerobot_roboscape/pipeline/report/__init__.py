"""The pipeline run's report: what it measured against what counts as success (`targets.py`, the world models' in
`world_model_targets.py`, a row's shape in `target_row.py`), its figures (`figures.py`), and the markdown written
from `lerobot_roboscape/templates/` (`write.py`)."""
