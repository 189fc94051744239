"""The agreement ladder's readings: per-episode agreement of the world model with the simulator (the confusion, the
balanced accuracy), and over several policies the ladder (the world model's ranking against the simulator's success
rates, over all rungs and over the most rungs the simulator tells apart, since a ranking among rungs it cannot tell
apart measures noise), written as ladder.json, ladder.md and ladder.png by `agreement.evaluate_agreement`."""

import math
from pathlib import Path

import matplotlib
import numpy as np
from scipy.stats import spearmanr

from lerobot_roboscape.evaluation.results import Cell
from lerobot_roboscape.io.templates import render_report

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def balanced_accuracy(truth: np.ndarray, said: np.ndarray) -> float | None:
    """The mean of the world model's recall of the simulator's successes and of its failures; None when the
    simulator saw only one of them (then only the other recall is defined)."""
    truth, said = np.asarray(truth, bool), np.asarray(said, bool)
    if truth.all() or not truth.any():
        return None
    return float(0.5 * ((said & truth).sum() / truth.sum() + (~said & ~truth).sum() / (~truth).sum()))


def agreement_summary(episodes: list[dict]) -> dict:
    """Success in each env, the confusion table (simulator rows, world model columns), the agreement and the
    balanced accuracy with the simulator as truth, and the mean returns."""
    sim = np.array([e["sim_success"] for e in episodes], bool)
    wm = np.array([e["wm_success"] for e in episodes], bool)
    return {
        "episodes": len(episodes),
        "simulator": Cell.of(sim.tolist()).to_json(),
        "world_model": Cell.of(wm.tolist()).to_json(),
        "confusion": {
            "sim_success_wm_success": int((sim & wm).sum()),
            "sim_success_wm_failure": int((sim & ~wm).sum()),
            "sim_failure_wm_success": int((~sim & wm).sum()),
            "sim_failure_wm_failure": int((~sim & ~wm).sum()),
        },
        "agreement": float((sim == wm).mean()) if len(sim) else None,
        "balanced_accuracy": balanced_accuracy(sim, wm),
        "mean_return": {
            "simulator": float(np.mean([e["sim_return"] for e in episodes])),
            "world_model": float(np.mean([e["wm_return"] for e in episodes])),
        },
        "goals_reached": float(np.mean([e["goal_reached"] for e in episodes])),
    }


def ladder_summary(rungs: list[dict]) -> dict:
    """Over the policies: how the world model ranks them against the simulator's success rates, and the
    per-episode agreement of all their episodes pooled."""
    sim_rate = [r["summary"]["simulator"]["success_rate"] for r in rungs]
    wm_return = [r["summary"]["mean_return"]["world_model"] for r in rungs]
    wm_rate = [r["summary"]["world_model"]["success_rate"] for r in rungs]
    pooled = [e for r in rungs for e in r["episodes"]]

    def rank(a, b):  # undefined with fewer than 3 rungs or a constant side
        return None if len(a) < 3 or len(set(a)) < 2 or len(set(b)) < 2 else float(spearmanr(a, b).statistic)

    intervals = [r["summary"]["simulator"]["ci95"] for r in rungs]
    apart = apart_rungs(sim_rate, intervals)
    return {
        "policies": [r["policy"] for r in rungs],
        "simulator_success_rate": sim_rate,
        "simulator_ci95": intervals,
        "told_apart": told_apart(sim_rate, intervals),
        "world_model_mean_return": wm_return,
        "world_model_success_rate": wm_rate,
        "spearman_return_vs_success": rank(wm_return, sim_rate),
        "spearman_wm_success_vs_success": rank(wm_rate, sim_rate),
        "pooled": agreement_summary(pooled),
        "apart": {
            "rungs": apart,
            "spearman_return_vs_success": rank([wm_return[k] for k in apart], [sim_rate[k] for k in apart]),
            "pooled": agreement_summary([e for k in apart for e in rungs[k]["episodes"]]),
        },
    }


def told_apart(rates: list[float], intervals: list[list[float]]) -> bool:
    """Whether the simulator tells every rung from the next: their 95% intervals, in order of success, disjoint
    (a ranking over rungs it cannot tell apart measures noise)."""
    return len(apart_rungs(rates, intervals)) == len(rates)


def apart_rungs(rates: list[float], intervals: list[list[float]]) -> list[int]:
    """The most rungs the simulator tells apart, in order of success: a largest set whose 95% intervals are pairwise
    disjoint (interval scheduling: greedy by upper bound). Chosen from the simulator's readings alone, so the world
    model's ranking over them is measured, not picked."""
    chain, top = [], -math.inf
    for k in sorted(range(len(rates)), key=lambda k: (intervals[k][1], intervals[k][0])):
        if intervals[k][0] > top:
            chain.append(k)
            top = intervals[k][1]
    return sorted(chain, key=lambda k: rates[k])


def ladder_markdown(ladder: dict) -> str:
    return render_report("agreement_ladder.md", ladder=ladder)


def ladder_figure(ladder: dict, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.scatter(ladder["simulator_success_rate"], ladder["world_model_mean_return"])
    for k, (x, y) in enumerate(zip(ladder["simulator_success_rate"], ladder["world_model_mean_return"], strict=True)):
        ax.annotate(str(k), (x, y), textcoords="offset points", xytext=(4, 4))
    ax.set_xlabel("simulator success rate")
    ax.set_ylabel("world-model mean return")
    ax.set_title("the ladder: world model against simulator")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    fig.savefig(tmp, dpi=120)
    plt.close(fig)
    tmp.replace(path)
