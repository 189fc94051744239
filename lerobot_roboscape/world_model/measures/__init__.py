"""How well a world model imitates the simulator, read from held-out episodes: the fidelity of its frames
(`fidelity.py`, the readings a report takes from it in `fidelity_readings.py`) and whether its frames follow the
actions (`controllability.py`, with the arm's own measures in `arm_measures.py` and `retrieval.py`)."""
