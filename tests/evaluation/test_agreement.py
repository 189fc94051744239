import dataclasses
import json

import numpy as np
import pytest

from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.evaluation import agreement
from lerobot_roboscape.evaluation.agreement import AgreementConfig, evaluate_agreement
from lerobot_roboscape.evaluation.ladder import agreement_summary, balanced_accuracy, ladder_summary
from roboscape_core.errors import InvalidInputError


def test_balanced_accuracy_is_the_mean_of_both_recalls():
    sim = [True, True, True, True, False, False]
    wm = [True, True, True, False, False, True]  # 3/4 successes and 1/2 failures recalled
    assert balanced_accuracy(sim, wm) == pytest.approx(0.5 * (3 / 4 + 1 / 2))
    assert balanced_accuracy(sim, [True] * 6) == pytest.approx(0.5)  # calling everything a success: chance
    assert balanced_accuracy([False] * 3, [False] * 3) is None  # no success to recall


def episode(sim, wm, sim_return=0.0, wm_return=0.0):
    return {
        "sim_success": sim,
        "wm_success": wm,
        "sim_return": sim_return,
        "wm_return": wm_return,
        "goal_reached": True,
    }


def test_agreement_summary_counts_the_confusion_table():
    s = agreement_summary([episode(True, True), episode(True, False), episode(False, False), episode(False, False)])
    assert s["confusion"] == {
        "sim_success_wm_success": 1,
        "sim_success_wm_failure": 1,
        "sim_failure_wm_success": 0,
        "sim_failure_wm_failure": 2,
    }
    assert s["agreement"] == 0.75 and s["balanced_accuracy"] == 0.75
    assert s["simulator"]["successes"] == 2 and s["world_model"]["successes"] == 1


def test_ladder_ranks_by_the_world_models_mean_return():
    def rung(name, sim_rate, wm_return):
        eps = [episode(i < 10 * sim_rate, False, wm_return=wm_return) for i in range(10)]
        return {"policy": name, "episodes": eps, "summary": agreement_summary(eps)}

    agreeing = ladder_summary([rung("a", 0.0, 1.0), rung("b", 0.3, 2.0), rung("c", 0.6, 5.0)])
    assert agreeing["spearman_return_vs_success"] == pytest.approx(1.0)
    reversed_ = ladder_summary([rung("a", 0.0, 5.0), rung("b", 0.3, 2.0), rung("c", 0.6, 1.0)])
    assert reversed_["spearman_return_vs_success"] == pytest.approx(-1.0)
    assert ladder_summary([rung("a", 0.0, 1.0), rung("b", 0.3, 2.0)])["spearman_return_vs_success"] is None


def test_config_refuses_goals_the_simulator_cannot_give():
    with pytest.raises(InvalidInputError, match="policy_paths"):
        AgreementConfig()
    with pytest.raises(InvalidInputError, match="goal_source"):
        AgreementConfig(policy_paths=["x"], env=RoboscapeWorldModelEnvConfig(goal_source="dataset_last_frame"))


def test_paired_episodes_share_starts_and_horizons_and_resume(env_config, mlp_checkpoint, tmp_path, monkeypatch):
    """The policy runs from the simulator's starts in both envs; each record holds both outcomes; the summary is
    those records'; videos are written; a rerun reads the finished policy instead of running it again."""
    seen = []
    paired_batch = agreement.paired_batch

    def spy(sim, wm, policy, io, seed, record=False, goals=None):
        result = paired_batch(sim, wm, policy, io, seed, record, goals)
        first = sim.reset(seed=seed)[0]["pixels"]  # the same seed gives the same starts
        seen.append((first, [s.horizon for s in wm._starts], sim.horizons.tolist(), wm.tokenizer, wm._starts))
        return result

    monkeypatch.setattr(agreement, "paired_batch", spy)
    cfg = AgreementConfig(
        policy_paths=[str(mlp_checkpoint)],
        env=env_config(episode_length=None),
        families=["push"],
        split="ood",
        episodes=3,
        batch_size=2,
        episode_length=8,
        videos=1,
        workers=1,
        output_dir=tmp_path / "agreement",
        device="cpu",
    )
    ladder = evaluate_agreement(cfg)
    assert len(seen) == 2  # 3 episodes at 2 per batch
    first, wm_horizons, sim_horizons, tokenizer, starts = seen[0]
    assert wm_horizons == sim_horizons == [8, 8]
    import torch

    tokens = tokenizer.encode_views([torch.from_numpy(first[c]).permute(0, 3, 1, 2) for c in ("third_view", "wrist")])
    assert torch.equal(torch.stack([s.first_tokens for s in starts]), tokens)  # the world model starts there
    out = tmp_path / "agreement" / "policy_0"
    records = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert len(records) == 3 and {r["family"] for r in records} == {"push"}
    summary = json.loads((out / "agreement.json").read_text())["summary"]
    assert summary["simulator"]["successes"] == sum(r["sim_success"] for r in records)
    assert summary["mean_return"]["world_model"] == pytest.approx(np.mean([r["wm_return"] for r in records]))
    assert ladder["policies"] == [str(mlp_checkpoint)]
    assert len(list((out / "videos").glob("00_push_sim_*_wm_*.mp4"))) == 1 and (out / "paired.png").is_file()
    assert (tmp_path / "agreement" / "ladder.md").is_file() and (tmp_path / "agreement" / "ladder.png").is_file()

    def must_not_run(*args, **kwargs):
        raise AssertionError("the finished policy ran again")

    monkeypatch.setattr(agreement, "paired_batch", must_not_run)
    assert evaluate_agreement(cfg)["pooled"] == ladder["pooled"]

    # Grown to 5 episodes, the run keeps its whole batch 0, runs again batch 1 (cut short at 3 episodes) and
    # runs batch 2; its records are those of a fresh run of 5.
    seeds = []

    def counting(sim, wm, policy, io, seed, record=False, goals=None):
        seeds.append(seed)
        return paired_batch(sim, wm, policy, io, seed, record, goals)

    monkeypatch.setattr(agreement, "paired_batch", counting)
    cfg.episodes = 5
    evaluate_agreement(cfg)
    assert seeds == [cfg.seed + 7919, cfg.seed + 2 * 7919]
    fresh = dataclasses.replace(cfg, output_dir=tmp_path / "fresh")
    evaluate_agreement(fresh)
    grown_records, fresh_records = (
        [json.loads(line) for line in (d / "policy_0" / "episodes.jsonl").read_text().splitlines()]
        for d in (tmp_path / "agreement", tmp_path / "fresh")
    )
    assert len(grown_records) == 5 and grown_records == fresh_records


def test_success_goals_are_the_last_frames_of_each_scenes_first_success(demo_dataset):
    from lerobot.configs.default import DatasetConfig

    from lerobot_roboscape.dataset.reader import episode_facts, open_dataset, read_episode

    _, root = demo_dataset
    goals = agreement.success_goals(DatasetConfig(repo_id="test/demos", root=str(root)))
    dataset = open_dataset("test/demos", root)
    scene = episode_facts(dataset, 0)["scene"]
    assert set(goals) == {("pick_place", scene), ("push", scene)}
    first_push_success = 4  # episodes 3-5 are push, 3 failed
    last = read_episode(dataset, first_push_success).images
    for cam, image in goals[("push", scene)].items():
        assert np.array_equal(image, last[cam][-1])


def test_agreement_targets_are_met_or_missed_by_the_measured_values():
    from lerobot_roboscape.pipeline.report.world_model_targets import agreement_targets

    def rung(name, successes, wm_return, n=100, wm=None):
        sim = [i < successes for i in range(n)]
        eps = [episode(s, s if wm is None else wm, wm_return=wm_return) for s in sim]
        return {"policy": name, "episodes": eps, "summary": agreement_summary(eps)}

    # five rungs 25 points apart at 100 episodes each: the simulator's 95% intervals are disjoint
    good = ladder_summary([rung(str(k), 25 * k, float(k)) for k in range(5)])
    assert good["told_apart"]
    bad = ladder_summary([rung(str(k), 25 * k, float(4 - k), wm=True) for k in range(5)])
    rewards = {
        "summary": {
            "world_model": {"roc_auc_of_return": 0.95},
            "world_model_dense": {"roc_auc_of_return": 0.6},
            "embedding": {"roc_auc_of_return": 0.97},
        },
        "similarity": "tokenizer",
        "done_source": "world_model",
        "theta": 0.9,
    }
    met = {name: t["met"] for name, t in agreement_targets(good, rewards).items()}
    assert [met[n] for n in met if n.startswith(("agreement", "ladder"))] == [True, True]
    assert not any(met[n] for n in met if n.startswith("reward"))  # below the embedding baseline; dense 0.6 < 0.75
    missed = agreement_targets(bad)
    assert len(missed) == 2 and not any(t["met"] for t in missed.values())
    assert missed[next(n for n in missed if n.startswith("agreement"))]["value"] == 0.5  # all called success


def test_the_ladders_ranking_counts_only_over_rungs_the_simulator_tells_apart():
    """A perfect ranking is not met over rungs whose simulator intervals overlap, nor over fewer than five."""
    from lerobot_roboscape.pipeline.report.world_model_targets import agreement_targets

    def rung(successes, n):
        eps = [episode(i < successes, i < successes, wm_return=float(successes)) for i in range(n)]
        return {"policy": str(successes), "episodes": eps, "summary": agreement_summary(eps)}

    def spearman_met(ladder):
        return next(t["met"] for name, t in agreement_targets(ladder).items() if name.startswith("ladder"))

    close = ladder_summary([rung(k, 10) for k in range(5)])  # 0-4 of 10: intervals overlap
    assert close["spearman_return_vs_success"] == pytest.approx(1.0) and not close["told_apart"]
    assert not spearman_met(close)
    few = ladder_summary([rung(25 * k, 100) for k in range(4)])
    assert few["told_apart"] and not spearman_met(few)
    assert spearman_met(ladder_summary([rung(25 * k, 100) for k in range(5)]))


def test_the_ladder_is_judged_over_its_most_rungs_the_simulator_tells_apart():
    """Rungs between others (their intervals overlapping both) are left out of the ranking, whatever the world model
    says of them; the rest count, and the per-episode agreement is over their episodes."""
    from lerobot_roboscape.pipeline.report.world_model_targets import agreement_targets

    def rung(successes, wm_return, n=100):
        eps = [episode(i < successes, i < successes, wm_return=wm_return) for i in range(n)]
        return {"policy": str(successes), "episodes": eps, "summary": agreement_summary(eps)}

    # 0, 25, 50, 75, 100 of 100 ranked right; 30 and 55, each overlapping its neighbours, ranked backwards
    ladder = ladder_summary(
        [rung(50, 3.0), rung(30, 9.0), rung(0, 1.0), rung(100, 5.0), rung(25, 2.0), rung(75, 4.0), rung(55, 0.0)]
    )
    assert not ladder["told_apart"] and ladder["spearman_return_vs_success"] < 0.9
    assert ladder["apart"]["rungs"] == [2, 4, 0, 5, 3]
    assert ladder["apart"]["spearman_return_vs_success"] == pytest.approx(1.0)
    assert ladder["apart"]["pooled"]["episodes"] == 500
    target = next(t for name, t in agreement_targets(ladder).items() if name.startswith("ladder"))
    assert target["met"] and target["value"] == pytest.approx(1.0)
    assert "5 of 7 policies told apart" in target["detail"]


def test_episode_clip_pairs_each_episodes_own_renders():
    """Batches of 3 episodes: simulator renders 2 px wide each, world-model renders 4 px wide, the world model's run
    one frame longer. Episode 1's clip holds its own columns of each, the simulator's last frame held."""
    sim = [np.stack([np.full((2, 2, 3), 10 * t + e) for e in range(3)], 1).reshape(2, 6, 3) for t in range(2)]
    wm = [np.stack([np.full((2, 4, 3), 100 + 10 * t + e) for e in range(3)], 1).reshape(2, 12, 3) for t in range(3)]
    clip = agreement.episode_clip(sim, wm, 1, 3)
    assert len(clip) == 3 and clip[0].shape == (2, 6, 3)
    assert [int(f[0, 0, 0]) for f in clip] == [1, 11, 11]  # the simulator's episode 1, its last frame held
    assert [int(f[0, -1, 0]) for f in clip] == [101, 111, 121]  # the world model's episode 1
