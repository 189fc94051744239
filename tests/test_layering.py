"""Data moves forward through the stages: no module of the library imports from a later stage."""

import ast
import json
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
    "pipeline",  # the stages roboscape-demo runs
    "experiments",  # the research harness on a run's stages: nothing in the product imports it
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


GPU_MACHINE_MODULES = (
    "lerobot_roboscape.envs.world_model_env",
    "lerobot_roboscape.experiments.world_model_runs",
    "lerobot_roboscape.cli.train_wm",
)


def test_what_the_gpu_machine_runs_imports_without_the_simulator():
    """A GPU machine without ManiSkill (scripts/experiments/device_world_models.sh) trains the world models and runs
    PPO in roboscape_wm. One fresh interpreter imports each module in turn (a start-up costs seconds), noting the
    simulator's modules loaded by then: the first module listed with any is the one that pulls it in."""
    code = (
        "import importlib, json, sys\n"
        "loaded = {}\n"
        "for module in sys.argv[1:]:\n"
        "    importlib.import_module(module)\n"
        "    loaded[module] = sorted({'mani_skill', 'sapien'} & set(sys.modules))\n"
        "print(json.dumps(loaded))"
    )
    run = subprocess.run([sys.executable, "-c", code, *GPU_MACHINE_MODULES], capture_output=True, text=True, check=True)
    assert json.loads(run.stdout) == {module: [] for module in GPU_MACHINE_MODULES}


def test_no_import_circle_between_modules():
    """No module reaches a module that reaches it back (within a stage too): each can be read on its own."""
    root = Path(lerobot_roboscape.__file__).parent
    graph = {}
    for path in root.rglob("*.py"):
        name = ".".join(("lerobot_roboscape", *path.relative_to(root).with_suffix("").parts)).removesuffix(".__init__")
        graph[name] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("lerobot_roboscape"):
                graph[name] |= {node.module, *(f"{node.module}.{alias.name}" for alias in node.names)}
    graph = {name: {d for d in deps if d in graph and d != name} for name, deps in graph.items()}
    circles = []
    for start in graph:  # a depth-first walk from each module; a circle returns to its start
        seen, todo = set(), [(start, (start,))]
        while todo:
            name, route = todo.pop()
            for dep in graph[name]:
                if dep == start:
                    circles.append(" -> ".join((*route, start)))
                elif dep not in seen:
                    seen.add(dep)
                    todo.append((dep, (*route, dep)))
    assert circles == []


def test_a_stage_s_results_file_is_named_and_read_only_where_it_is_written():
    """Each results file a stage writes (`*_JSON`) is spelled once, in the module that writes it and reads it back
    (`read_*`): no later stage reads another's JSON by its file name and keys."""
    files = [
        *Path(lerobot_roboscape.__file__).parent.rglob("*.py"),
        *(Path(__file__).parents[1] / "scripts").rglob("*.py"),
    ]
    homes = {}
    for path in files:
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.Assign) and any(getattr(t, "id", "").endswith("_JSON") for t in node.targets):
                homes[node.value.value] = path
    assert {"done_report.json", "fidelity.json", "eval.json", "tables.json", "clock.json"} <= set(homes)
    elsewhere = [
        f"{path} spells {name!r}"
        for path in files
        for name, home in homes.items()
        if path != home and f'"{name}"' in path.read_text()
    ]
    assert elsewhere == []


def test_reports_are_rendered_from_the_templates():
    """A report's markdown lives in one place, `lerobot_roboscape/templates/`: no module of the library builds a
    markdown table line by line."""
    package = Path(lerobot_roboscape.__file__).parent
    built = [str(path) for path in package.rglob("*.py") if '"|---' in path.read_text()]
    assert built == []
    assert {"tokenizer_report.md", "fidelity_report.md", "done_report.md", "reward_report.md"} <= {
        p.name for p in (package / "templates").glob("*.md")
    }
