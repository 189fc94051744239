"""OpenVLA-7B as the LeRobot policy type `openvla`."""
