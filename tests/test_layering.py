"""Data moves forward through the stages: no module of the library imports from a later stage."""

import ast
import subprocess
import sys
from pathlib import Path

import lerobot_roboscape

# The library's folders and top-level modules, upstream first.
STAGES = [
    "io",
    "training",  # shared foundations
    "robot",  # the robot's interface: cameras, state, actions, rate
    "tasks",
    "dataset",
    "demos",
    "metrics",  # measures on the datasets' frames and masks, for the models' reports
    "tokenizer",
    "world_model",
    "reward",
    "hub",
    "envs",
    "rl",
    "evaluation",
    "pipeline",
    "cli",
]


def test_no_module_imports_from_a_later_stage():
    root = Path(lerobot_roboscape.__file__).parent
    rank = {stage: i for i, stage in enumerate(STAGES)}
    backwards, unknown = [], set()
    for path in root.rglob("*.py"):
        stage = path.relative_to(root).parts[0].removesuffix(".py")
        if stage == "__init__":
            continue
        if stage not in rank:
            unknown.add(stage)
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("lerobot_roboscape."):
                target = node.module.split(".")[1]
                if rank.get(target, len(STAGES)) > rank[stage]:
                    backwards.append(f"{path.relative_to(root)} imports {node.module}")
    assert not unknown, f"place these in STAGES: {sorted(unknown)}"
    assert not backwards, "\n".join(sorted(backwards))


def test_the_world_model_env_imports_without_the_simulator():
    """A GPU machine without ManiSkill (scripts/experiments/device_world_models.sh) runs roboscape_wm."""
    code = (
        "import sys, lerobot_roboscape.envs.world_model_env; print(sorted({'mani_skill', 'sapien'} & set(sys.modules)))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
