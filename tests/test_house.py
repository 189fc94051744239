"""The house's sizes (issue 102): a folder of the package is one stage a reader can hold (<= 3,000 lines, <= 20
files), a file one idea (<= 400 lines), a function one screen (<= 80 lines), in the package, its scripts and its
tests."""

import ast
from pathlib import Path

import lerobot_roboscape

ROOT = Path(lerobot_roboscape.__file__).parent
SCRIPTS = ROOT.parent / "scripts"
TESTS = ROOT.parent / "tests"
MAX_FOLDER_LINES, MAX_FOLDER_FILES, MAX_FILE_LINES, MAX_FUNCTION_LINES = 3000, 20, 400, 80


def python_files(*roots: Path) -> list[Path]:
    return sorted(p for root in roots for p in root.rglob("*.py") if "__pycache__" not in p.parts)


def lines(path: Path) -> int:
    return len(path.read_text().splitlines())


def test_no_package_folder_over_its_size():
    folders = {p.parent for p in python_files(ROOT)}
    too_big = []
    for folder in sorted(folders):
        files = sorted(folder.glob("*.py"))
        total = sum(lines(p) for p in files)
        if total > MAX_FOLDER_LINES or len(files) > MAX_FOLDER_FILES:
            too_big.append(f"{folder.relative_to(ROOT.parent)}: {len(files)} files, {total} lines")
    assert not too_big, "\n".join(too_big)


def test_no_file_over_its_size():
    too_long = [
        f"{p.relative_to(ROOT.parent)}: {lines(p)} lines"
        for p in python_files(ROOT, SCRIPTS, TESTS)
        if lines(p) > MAX_FILE_LINES
    ]
    assert not too_long, "\n".join(too_long)


def test_no_function_over_its_size():
    too_long = []
    for path in python_files(ROOT, SCRIPTS, TESTS):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    too_long.append(f"{path.relative_to(ROOT.parent)}:{node.lineno} {node.name}: {length} lines")
    assert not too_long, "\n".join(too_long)
