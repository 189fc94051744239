"""The README against the code: its commands, console scripts, flags, paths and figures that the code fixes.

Runs the cheap commands only: the syntax of the set-up script, `--help` of every console script (in this process,
as the console scripts call the same `main`, and once through `.venv/bin`), and the scene listing.
"""

import ast
import contextlib
import dataclasses
import importlib
import io
import json
import re
import subprocess
import sys
import tomllib
from functools import cache
from pathlib import Path

import pytest

from lerobot_roboscape.experiments.claim_markdown import README_BEGIN, README_END
from lerobot_roboscape.pipeline.run import STAGES

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MAX_LINES = 260
QUICK_START_LINES = 40
# Top-level folders of the repository whose paths the README may name (outputs/ is made by the commands).
TRACKED_ROOTS = ("docs", "scripts", "lerobot_roboscape", "policies", "plugins", "hub_cards", "tests", ".ci")


def console_scripts() -> dict[str, str]:
    """{name: "module:function"} from pyproject.toml's [project.scripts]."""
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]


def shell_blocks(text: str) -> list[str]:
    """The contents of the fenced ```bash blocks."""
    return re.findall(r"^```(?:bash|sh|shell)\n(.*?)^```", text, re.S | re.M)


def shell_commands(text: str) -> list[str]:
    """Each command of the shell blocks: continuation lines joined, comments dropped, split at && ; and |."""
    commands = []
    for block in shell_blocks(text):
        for line in block.replace("\\\n", " ").splitlines():
            line = " ".join(re.sub(r"(^|\s)#.*$", "", line).split())
            commands += [part.strip() for part in re.split(r"&&|;|\|(?![^\[]*\])", line) if part.strip()]
    return commands


def inline_commands(text: str) -> list[str]:
    """Inline code spans that start with a console script (`roboscape-collect --kinds=...`)."""
    return [span for span in re.findall(r"`([^`\n]+)`", text) if re.match(r"(\.venv/bin/)?roboscape-\w", span)]


def script_of(command: str, names) -> tuple[str, str] | None:
    """(console script, the rest of the command) when the command runs one of `names`."""
    for i, word in enumerate(command.split()):
        name = word.removeprefix(".venv/bin/")
        if name in names:
            return name, " ".join(command.split()[i + 1 :])
    return None


def mentioned_scripts(text: str) -> set[str]:
    return set(re.findall(r"(?<![\w-])(roboscape-[a-z]+(?:-[a-z]+)*)", text))


@cache
def help_text(name: str) -> str:
    """What `name --help` prints, from its entry point in this process; its exit status must be 0."""
    module, function = console_scripts()[name].split(":")
    main = getattr(importlib.import_module(module), function)
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code in (0, None), f"{name} --help exited with {exit_info.value.code}"
    return out.getvalue()


@pytest.fixture(scope="module")
def readme() -> str:
    return README.read_text()


def test_shell_commands_are_parsed():
    text = "```bash\nbash a.sh && .venv/bin/roboscape-x --a=1 \\\n    --b.c=[1,2] # note\n```\n"
    assert shell_commands(text) == ["bash a.sh", ".venv/bin/roboscape-x --a=1 --b.c=[1,2]"]


def test_length_and_quick_start_first(readme):
    lines = readme.splitlines()
    assert len(lines) <= MAX_LINES, f"README.md has {len(lines)} lines, at most {MAX_LINES}"
    first = shell_commands("\n".join(lines[:QUICK_START_LINES]))
    assert "bash scripts/setup.sh" in first and ".venv/bin/roboscape-demo" in first, first
    assert any(c.startswith(".venv/bin/python -m pytest") for c in first), "the test command is not in the first lines"


def test_test_command_is_ci_command(readme):
    """The README's test command is the one `.ci/run` runs."""
    readme_tests = [c for c in shell_commands(readme) if " -m pytest" in c]
    ci = [line.strip() for line in (ROOT / ".ci/run").read_text().splitlines() if " -m pytest" in line]
    assert readme_tests and ci and readme_tests[0] == ci[0], (readme_tests, ci)


def test_setup_commands_exist_and_parse(readme):
    setups = [c.split()[1] for c in shell_commands(readme) if c.startswith("bash ")]
    assert "scripts/setup.sh" in setups
    for script in setups:
        assert (ROOT / script).is_file(), script
        result = subprocess.run(["bash", "-n", str(ROOT / script)], capture_output=True, text=True)
        assert result.returncode == 0, f"bash -n {script}: {result.stderr}"


def test_console_scripts_named_both_ways(readme):
    declared = set(console_scripts())
    in_code = {
        name for command in shell_commands(readme) + inline_commands(readme) for name in mentioned_scripts(command)
    }
    assert in_code - declared == set(), "the README runs console scripts that pyproject.toml does not declare"
    assert declared - mentioned_scripts(readme) == set(), "console scripts the README does not mention"


@pytest.mark.parametrize("name", sorted(console_scripts()))
def test_help_of_every_console_script(name):
    assert help_text(name).startswith("usage:"), help_text(name)[:200]


@pytest.mark.slow
def test_console_script_runs_from_the_environment():
    """One console script through its installed wrapper, as the README runs them."""
    executable = Path(sys.executable).parent / "roboscape-demo"
    assert executable.is_file(), f"{executable} is missing: run bash scripts/setup.sh"
    result = subprocess.run([str(executable), "--help"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and "--scale" in result.stdout, result.stderr[-2000:]


def test_readme_flags_exist(readme):
    """Every --flag the README gives a console script is in that script's --help."""
    unknown = []
    for command in shell_commands(readme) + inline_commands(readme):
        found = script_of(command, console_scripts())
        if found is None:
            continue
        name, rest = found
        for flag in re.findall(r"(?<![\w-])(--[A-Za-z_][\w.]*)", rest):
            if not re.search(re.escape(flag) + r"(?![\w.])", help_text(name)):
                unknown.append(f"{name} {flag}")
    assert unknown == []


def test_paths_exist(readme):
    """Every repository path the README names, in links or in text, exists."""
    links = [t for t in re.findall(r"\]\(([^)\s]+)\)", readme) if not re.match(r"[a-z]+://|#", t)]
    roots = "|".join(re.escape(r) for r in TRACKED_ROOTS)
    named = re.findall(rf"(?<![\w/.-])((?:{roots})/[\w./*-]*[\w*/])", readme)
    missing = [p for p in {*links, *named} if not (list(ROOT.glob(p)) if "*" in p else (ROOT / p).exists())]
    assert named and missing == []


def test_stage_count_is_the_pipeline_s(readme):
    """The README counts the demo's stages as the pipeline does."""
    stated = re.findall(r"(\d+) numbered stages", readme)
    assert stated and set(stated) == {str(len(STAGES))}, (stated, STAGES)


def test_results_block_for_the_experiment(readme):
    """`roboscape-experiment` rewrites the README's results block: its markers are there, once each."""
    assert readme.count(README_BEGIN) == 1 and readme.count(README_END) == 1
    assert readme.index(README_BEGIN) < readme.index(README_END)


def test_scene_listing(readme):
    """`roboscape-collect --list_scenes=true`: as many scenes and held-out scenes as the README says."""
    assert "roboscape-collect --list_scenes=true" in readme
    scenes = re.search(r"in (\d+) scenes:\s.*?(\d+) scenes held out", readme, re.S)
    module, function = console_scripts()["roboscape-collect"].split(":")
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        getattr(importlib.import_module(module), function)(["--list_scenes=true"])
    splits = [line.split()[-1] for line in out.getvalue().splitlines()]
    assert scenes and (len(splits), splits.count("ood")) == (int(scenes[1]), int(scenes[2]))


@pytest.mark.parametrize("folder", ["scripts", "scripts/benchmarks", "scripts/experiments"])
def test_scripts_readmes(folder):
    """Each scripts folder's README describes every script beside it, and its links resolve."""
    text = (ROOT / folder / "README.md").read_text()
    scripts = sorted(p.name for p in (ROOT / folder).glob("*.py")) + sorted(
        p.name for p in (ROOT / folder).glob("*.sh")
    )
    assert [name for name in scripts if f"`{name}`" not in text and name != "setup.sh"] == []
    links = [t for t in re.findall(r"\]\(([^)\s]+)\)", text) if not re.match(r"[a-z]+://|#", t)]
    assert links and [t for t in links if not (ROOT / folder / t).exists()] == []


def test_python_blocks(readme):
    """The README's Python compiles, its imports resolve, and the classes it calls take the keywords it gives."""
    blocks = re.findall(r"^```python\n(.*?)^```", readme, re.S | re.M)
    assert blocks
    for block in blocks:
        tree = ast.parse(block)
        names = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                module = importlib.import_module(node.module)
                names |= {alias.asname or alias.name: getattr(module, alias.name) for alias in node.names}
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in names:
                fields = {f.name for f in dataclasses.fields(names[node.func.id])}
                assert {k.arg for k in node.keywords} - fields == set(), node.func.id


def _measured(path: str, *keys: str):
    value = json.loads((ROOT / "docs" / "results" / path).read_text())
    for key in keys:
        value = value[key]
    return value


def _pct(value: float) -> str:
    return f"{100 * value:.0f}%"


def quoted_figures() -> list[str]:
    """Each sentence of the README's Results that quotes a figure, with the figure read from the committed results
    file that measured it."""
    sft = lambda split, family: _pct(  # noqa: E731  (the bench table's SFT row, below the results)
        _measured("bench/results.json", "table", "roboscape_mlp", "Supervised finetune", split, family, "success_rate")
    )
    tokenizer = lambda name, view: _measured("tokenizer/results.json", "targets", name.format(view), "value")  # noqa: E731
    done = _measured("world_model/results.json", "done", "sources", "world_model", "teacher_forced")
    control = _measured("world_model/results.json", "fidelity", "controllability")
    rebuilt = lambda *keys: _measured("world_model/bench70/rebuilt/results.json", *keys)  # noqa: E731
    psnr = "tokenizer reconstruction PSNR, whole frame, {} (dB)"
    survival = "tokenizer object survival, {} (share of held-out frames with the object >= 4 px)"
    return [
        f"The MLP succeeds in {sft('ind', 'push')} of push and {sft('ind', 'pick_place')} of pick&place episodes in "
        f"the training scenes (OOD: {sft('ood', 'push')} and {sft('ood', 'pick_place')};",
        f"({tokenizer(psnr, 'third_view'):.1f} / {tokenizer(psnr, 'wrist'):.1f} dB PSNR, third view / wrist,",
        f"the object survives in {_pct(tokenizer(survival, 'third_view'))} / {_pct(tokenizer(survival, 'wrist'))},",
        f"(ROC-AUC {done['frame_roc_auc']:.2f}), but calls {_pct(done['confusion']['failed_called_done_rate'])} of "
        "the failed episodes done",
        f"the TCP stays within {_pct(rebuilt('ind', 'tcp_error_share_of_moved'))} of the distance moved and the "
        f"rollouts find their own future among 4 action sequences in {_pct(rebuilt('ind', 'retrieval_whole_frame'))} "
        f"of IND starts (was {_pct(control['world_model']['whole_frame']['retrieval'])}; goal 90%); their done calls "
        f"{_pct(rebuilt('done_ind', 'open_loop', 'successes_called_done'))} of successes, "
        f"{_pct(rebuilt('done_ind', 'open_loop', 'failures_called_done'))} of failures.",
        ppo_in_the_simulator(),
        wm_in_the_scene(),
        *headline(),
    ]


CLAIM = "claim72_gpuwm/results.json"  # the paper protocol's latest run: PPO in the GPU-trained world models
CLAIM_2_CORES = "claim72_chain/table1/results.json"  # the same protocol in the world models the 2 cores trained
PAPER_METHODS = ("Supervised finetune", "RL w. World Model", "RL w. ManiSkill (one scene)", "RL w. ManiSkill")


def claim_figures(claim: str, split: str = "ood"):
    """A claim's success per method in `split` (pooled over families) and PPO in the world model's paired
    differences out of domain."""
    rate = lambda method: _pct(  # noqa: E731
        _measured(claim, "table", "roboscape_mlp", method, split, "all", "success_rate")
    )
    difference = lambda against: next(  # noqa: E731
        d for d in _measured(claim, "differences") if (d["against"], d["split"], d["family"]) == (against, "ood", "all")
    )
    return rate, difference


def interval(d: dict) -> str:
    return "[{:+d}, {:+d}]".format(*(round(100 * x) for x in d["paired_ci95"]))


def headline() -> list[str]:
    """The README's answer out of domain and its table: PPO in the world model against SFT and PPO in the simulator
    under the paper's protocol, in the GPU-trained world models (CLAIM) and in the 2-core ones (CLAIM_2_CORES)."""
    rate, difference = claim_figures(CLAIM)
    points = round(100 * difference("Supervised finetune")["difference"])
    points = f"{points:+d} point" + ("" if abs(points) == 1 else "s")
    episodes = _measured(CLAIM, "table", "roboscape_mlp", "RL w. World Model", "ood", "all")
    here, _ = claim_figures(CLAIM_2_CORES)
    sft, world_model, one_scene, _ = PAPER_METHODS
    return [
        f"PPO in the world model took the one-scene SFT policy from {rate(sft)} to {rate(world_model)} success "
        f"({points}, paired 95% interval {interval(difference(sft))}, "
        f"{episodes['episodes']} episodes each); PPO in the simulator in that scene reached {rate(one_scene)} "
        f"(world model minus simulator: paired {interval(difference(one_scene))}).",
        "| roboscape_mlp, GPU-trained world models | " + " | ".join(rate(m) for m in PAPER_METHODS) + " |",
        "| roboscape_mlp, 2-core world models | " + " | ".join(here(m) for m in PAPER_METHODS) + " |",
    ]


PPO_SIMULATOR = "ppo_sim/results.json"  # PPO in the simulator over every training scene, by lever and seed


def ppo_in_the_simulator() -> str:
    """The answer where the truth is known: PPO in ManiSkill from the all-scene SFT, GRPO at 400 and 1,200 episodes,
    GRPO wide at 512 and today's PPO, at two seeds, IND, each minus SFT on the same starts."""
    runs = _measured(PPO_SIMULATOR, "runs")
    cell = lambda run, seed: runs[f"{run}_seed{seed}"]["cell"]["all"]  # noqa: E731
    both = lambda run: "{} and {}".format(*(_pct(cell(run, seed)["success"]) for seed in (0, 1)))  # noqa: E731
    paired = lambda run: "{} and {}".format(  # noqa: E731
        *(interval({"paired_ci95": cell(run, seed)["paired_95"]}) for seed in (0, 1))
    )
    return (
        f"From the all-scene SFT policy ({_pct(_measured(PPO_SIMULATOR, 'sft_cell', 'all'))} IND here), PPO in "
        "ManiSkill over every training scene with GRPO (group-relative success, `--advantage=group`) reached "
        f"{both('grpo')} at two seeds after 400 episodes (paired {paired('grpo')}) and {both('grpo_long')} after "
        f"1,200 (paired {paired('grpo_long')}), with 4x the starts an iteration {both('grpo_wide')} after 512 (paired "
        f"{paired('grpo_wide')}); today's PPO {both('plain')}"
    )


PPO_WM_SCENE = "ppo_wm_scene/results.json"  # PPO in the world model in the paper protocol's initial scene


def wm_in_the_scene() -> str:
    """The answer in the world model where it has the most data: the initial scene, PPO in roboscape_wm (two seeds,
    with the KL to SFT, and with the done head refreshed) and in ManiSkill there, each minus SFT on the same starts."""
    sft = _measured(PPO_WM_SCENE, "sft_cell", "all")
    cell = lambda run: _measured(PPO_WM_SCENE, "runs", run, "cell", "all")  # noqa: E731
    theirs = _measured(PPO_WM_SCENE, "others", "cell_maniskill_one_scene", "all")
    paired = lambda c: interval({"paired_ci95": c["paired_95"]})  # noqa: E731
    both = lambda lever: "{} and {} (paired {} and {})".format(  # noqa: E731
        *(_pct(cell(f"{lever}_seed{s}")["success"]) for s in (0, 1)),
        *(paired(cell(f"{lever}_seed{s}")) for s in (0, 1)),
    )
    return (
        "In the world model, in the scene it knows best (the paper protocol's initial scene, the 2-core models), PPO "
        f"took the one-scene SFT policy from {_pct(sft)} to {both('std')} at two seeds, with the KL to SFT to "
        f"{both('std_kl')}, and with the done head also refitted on the policy's simulator rollouts to "
        f"{both('std_kl_refresh')}: in closed loop the 2-core world model loses the cube within 25 frames, so no done "
        f"head can judge there; PPO in ManiSkill there reached {_pct(theirs['success'])} "
        f"(paired {paired(theirs)})"
    )


def test_results_quote_the_committed_results_files(readme):
    """Every figure the README's Results give is the one in the results file that measured it."""
    text = " ".join(readme.split())
    missing = [sentence for sentence in quoted_figures() if " ".join(sentence.split()) not in text]
    assert missing == [], "the README quotes other figures than its results files hold:\n" + "\n".join(missing)
