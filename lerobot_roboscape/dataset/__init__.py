"""Episodes as the simulator gives them, and the LeRobot datasets written from them (writer.py). The package
imports nothing: a simulator worker reads `episode` and `segmentation` without loading LeRobot's dataset stack."""
