"""The paper's tables: success rates of each policy after SFT, after PPO in ManiSkill and after PPO in the world
model, per split and task family (Table 1), as markdown with 95% Wilson intervals and as a bar chart. The
pipeline (`roboscape-demo`, `roboscape-experiment`) fills them."""

import json
from pathlib import Path

import matplotlib
import numpy as np

from lerobot_roboscape.evaluation.results import SCENE, Results
from lerobot_roboscape.io.templates import render_report

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

TABLES_JSON = "tables.json"
SPLIT_NAMES = {SCENE: "Scene", "ind": "IND", "ood": "OOD"}


def paper_split(split: str, splits: list[str]) -> str | None:
    """The paper's column a split of ours sits beside: its IND is the scene the policy learned (section 8.1), so
    beside our scene column when the table has one, else beside our IND."""
    if split == "ind" and SCENE in splits:
        return None
    return "ind" if split == SCENE else split


def read_table(folder: Path) -> Results:
    """The results `write_table` wrote into `folder`."""
    return Results.of(json.loads((Path(folder) / TABLES_JSON).read_text()))


SHORT = {"pick_place": "P.&P.", "push": "Push", "pull": "Pull", "move_to_aim": "M.A."}
# The paper's Table 1 (success %, ManiSkill): {policy: {method: {split: {family: rate}}}}.
PAPER_TABLE_1 = {
    "MLP": {
        "Supervised finetune": {
            "ind": {"pick_place": 12.0, "push": 84.5, "pull": 57.7, "move_to_aim": 35.8},
            "ood": {"pick_place": 3.5, "push": 13.3, "pull": 10.2, "move_to_aim": 10.6},
        },
        "RL w. ManiSkill": {
            "ind": {"pick_place": 85.0, "push": 98.5, "pull": 64.2, "move_to_aim": 87.6},
            "ood": {"pick_place": 32.1, "push": 15.6, "pull": 15.5, "move_to_aim": 42.9},
        },
        "RL w. World Model": {
            "ind": {"pick_place": 86.7, "push": 98.7, "pull": 65.2, "move_to_aim": 88.1},
            "ood": {"pick_place": 74.2, "push": 87.3, "pull": 51.3, "move_to_aim": 72.0},
        },
    },
    "OpenVLA": {
        "Supervised finetune": {
            "ind": {"pick_place": 22.5, "push": 94.4, "pull": 73.5, "move_to_aim": 67.5},
            "ood": {"pick_place": 47.5, "push": 84.0, "pull": 12.5, "move_to_aim": 24.5},
        },
        "RL w. ManiSkill": {
            "ind": {"pick_place": 92.5, "push": 97.7, "pull": 89.1, "move_to_aim": 92.5},
            "ood": {"pick_place": 54.5, "push": 93.0, "pull": 39.6, "move_to_aim": 41.5},
        },
        "RL w. World Model": {
            "ind": {"pick_place": 95.5, "push": 98.4, "pull": 91.4, "move_to_aim": 94.6},
            "ood": {"pick_place": 84.1, "push": 97.5, "pull": 85.8, "move_to_aim": 82.1},
        },
    },
}
PAPER_POLICY = {"roboscape_mlp": "MLP", "openvla": "OpenVLA"}


def write_table(results: Results | dict, families: list[str], output_dir: Path, title: str = "Table 1") -> None:
    """Writes tables.md, tables.json and tables.png of `results` into output_dir."""
    results, output_dir = Results.of(results), Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    (output_dir / TABLES_JSON).write_text(json.dumps(results.to_json(), indent=2))
    (output_dir / "tables.md").write_text(format_table(results, families, title))
    bar_chart(results, families, output_dir / "tables.png", title)


def format_table(
    results: Results | dict,
    families: list[str],
    title: str,
    with_paper: bool = False,
    paper_methods: dict | None = None,
) -> str:
    """The paper's layout: rows policy x method, columns each split's families (scene, IND, OOD, those evaluated):
    success % [95% CI]; `with_paper`: under each of our rows, the paper's number for the same policy kind and
    method (Table 1), "-" under a split the paper has none of. `paper_methods`: {our method: the paper's row
    beside it, or None for none}, where the two name them differently."""
    results = Results.of(results)
    splits = results.splits()
    return render_report(
        "table1.md",
        results=results.cells,
        families=families,
        names=[SHORT.get(f, f) for f in families],
        splits=splits,
        split_names=SPLIT_NAMES,
        paper_splits={split: paper_split(split, splits) for split in splits},
        title=title,
        episodes=", ".join(map(str, sorted({cell.episodes for cell in results.family_cells()}))),
        with_paper=with_paper,
        paper_table=PAPER_TABLE_1,
        paper_policy=PAPER_POLICY,
        paper_methods=paper_methods or {},
    )


def bar_chart(results: Results, families: list[str], path: Path, title: str) -> None:
    """Success over all the families' episodes (each split's "all" cell), one bar per split and (policy, method),
    with the 95% Wilson intervals as error bars."""
    splits = results.splits()
    labels, bars = [], {split: [] for split in splits}
    for policy in results.policies:
        for method in results.methods(policy):
            labels.append(f"{policy}\n{method}")
            for split in bars:
                cell = results.cell(policy, method, split)
                bars[split].append((100 * cell.success_rate, 100 * np.array(cell.ci95)))
    x = np.arange(len(labels))
    fig, ax = plt.subplots(figsize=(max(6, 1.6 * len(labels)), 3.5))
    width = 0.8 / len(splits)
    for k, split in enumerate(splits):
        rates = np.array([r for r, _ in bars[split]])
        spans = np.array([[r - ci[0], ci[1] - r] for r, ci in bars[split]]).T
        offset = (k - (len(splits) - 1) / 2) * width
        ax.bar(x + offset, rates, width, yerr=spans, capsize=3, label=SPLIT_NAMES[split])
    ax.set_xticks(x, labels, fontsize=7)
    ax.set_ylabel("success rate (%)")
    ax.set_ylim(0, 100)
    ax.set_title(title, fontsize=9)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
