"""The paper's tables: success rates of each policy after SFT, after PPO in ManiSkill and after PPO in the world
model, IND and OOD, per task family (Table 1), as markdown with 95% Wilson intervals and as a bar chart. The
pipeline (`roboscape-demo`, `scripts/reproduce_tables.py`) fills them."""

import json
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

SHORT = {"pick_place": "P.&P.", "push": "Push", "pull": "Pull", "move_to_aim": "M.A."}


def write_table(results: dict, families: list[str], output_dir: Path, title: str = "Table 1") -> None:
    """results: {policy: {method: {split: {family: cell}}}}, cells as `success_rate.summarise` makes them.
    Writes tables.md, tables.json and tables.png into output_dir."""
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    (output_dir / "tables.json").write_text(json.dumps(results, indent=2))
    (output_dir / "tables.md").write_text(format_table(results, families, title))
    bar_chart(results, families, output_dir / "tables.png", title)


def format_table(results: dict, families: list[str], title: str) -> str:
    """The paper's layout: rows policy x method, columns IND families then OOD families: success % [95% CI]."""
    names = [SHORT.get(f, f) for f in families]
    header = (
        "| Policy | Training method | "
        + " | ".join(f"IND {n}" for n in names)
        + " | "
        + " | ".join(f"OOD {n}" for n in names)
        + " |"
    )
    lines = [
        f"{title}: success rate (%) in the ManiSkill simulator [95% Wilson interval] (its width), episodes per cell: "
        f"{_episodes(results)}",
        "",
        header,
        "|---|---|" + "---:|" * (2 * len(families)),
    ]
    for policy, methods in results.items():
        for method, splits in methods.items():
            cells = [_cell(splits[split][f]) for split in ("ind", "ood") for f in families]
            lines.append(f"| {policy} | {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _cell(cell: dict) -> str:
    low, high = cell["ci95"]
    return f"{100 * cell['success_rate']:.0f} [{100 * low:.0f}, {100 * high:.0f}] ({100 * (high - low):.0f})"


def _episodes(results: dict) -> str:
    counts = {
        cell["episodes"]
        for methods in results.values()
        for splits in methods.values()
        for cells in splits.values()
        for family, cell in cells.items()
        if family != "all"
    }
    return ", ".join(map(str, sorted(counts)))


def bar_chart(results: dict, families: list[str], path: Path, title: str) -> None:
    """Success over all the families' episodes (each split's "all" cell), IND and OOD, one pair of bars per
    (policy, method), with the 95% Wilson intervals as error bars."""
    labels, bars = [], {"ind": [], "ood": []}
    for policy, methods in results.items():
        for method, splits in methods.items():
            labels.append(f"{policy}\n{method}")
            for split in bars:
                cell = splits[split]["all"]
                bars[split].append((100 * cell["success_rate"], 100 * np.array(cell["ci95"])))
    x = np.arange(len(labels))
    fig, ax = plt.subplots(figsize=(max(6, 1.6 * len(labels)), 3.5))
    for offset, split in ((-0.2, "ind"), (0.2, "ood")):
        rates = np.array([r for r, _ in bars[split]])
        spans = np.array([[r - ci[0], ci[1] - r] for r, ci in bars[split]]).T
        ax.bar(x + offset, rates, 0.4, yerr=spans, capsize=3, label=split.upper())
    ax.set_xticks(x, labels, fontsize=7)
    ax.set_ylabel("success rate (%)")
    ax.set_ylim(0, 100)
    ax.set_title(title, fontsize=9)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
