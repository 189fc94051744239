import json

import numpy as np
import pytest
import torch
from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.dataset.reader import episode_facts, open_dataset, read_episode
from lerobot_roboscape.dataset.segmentation import ROBOT
from lerobot_roboscape.demos.controllability import ControllabilityConfig, collect_controllability, offsets
from lerobot_roboscape.robot import TCP_POSITION
from lerobot_roboscape.tokenizer.configuration_tokenizer import TinyTokenizerConfig
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.world_model.measures.arm_measures import arm_measures, summarise_arm
from lerobot_roboscape.world_model.measures.controllability import (
    ControllabilityReportConfig,
    ControlStart,
    evaluate_controllability,
    likelihood_retrieval,
    read_control_set,
    retrieval_accuracy,
)
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from tests.conftest import IMAGE_SIZE

SEQUENCES, STEPS = 3, 5


@pytest.fixture(scope="module")
def control_set(tmp_path_factory):
    root = tmp_path_factory.mktemp("control") / "set"
    cfg = ControllabilityConfig(
        root=str(root),
        families=["push"],
        max_scenes=1,
        starts_per_scene=2,
        sequences=SEQUENCES,
        steps=STEPS,
        image_size=IMAGE_SIZE,
        workers=0,
    )
    return collect_controllability(cfg), root


def test_retrieval_counts_own_future_and_shares_ties():
    assert retrieval_accuracy(np.array([[3.0, 1.0], [0.0, 2.0]])) == 1.0
    assert retrieval_accuracy(np.array([[1.0, 3.0], [2.0, 0.0]])) == 0.0
    assert retrieval_accuracy(np.ones((4, 4))) == 0.25  # one rollout for every sequence: chance


def test_the_arms_measures_see_the_tcp_the_arm_and_the_motion():
    """K = 3 sequences whose TCPs move 10 cm apart: rollouts that predict their own TCP exactly are retrieved by state
    at 1 with no error; rollouts that keep the start's TCP have an error of the whole distance moved; a rollout equal
    to the real future moves as it does (ratio 1), a frozen one not at all (ratio 0)."""
    torch.manual_seed(0)
    tokenizer = VisualTokenizer(TinyTokenizerConfig(image_size=32)).eval()
    K, T, n, D = 3, 4, 2, 16
    states = torch.zeros(K, T, D)
    for j in range(K):  # sequence j's TCP moves along axis j, 2.5 cm a frame
        states[j, :, TCP_POSITION.start + j] = 0.025 * torch.arange(1, T + 1)
    real = (torch.rand(K, T, n, 3, 32, 32) * 255).to(torch.uint8)
    masks = torch.zeros(K, T, n, 32, 32, dtype=torch.uint8)
    masks[..., 8:20, 8:20] = ROBOT
    start = ControlStart(
        0, [0, 1, 2], "push", torch.zeros(1, 2 * 64), torch.zeros(K, T * 4, 7), real, masks, torch.zeros(1, D), states
    )
    exact = arm_measures(tokenizer, start, real.float() / 255, states, window=3)
    assert exact["retrieval_state"] == 1.0 and max(exact["tcp_error_m"]) == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(exact["tcp_moved_m"], 0.1, rtol=1e-5)
    assert exact["motion_ratio"] == pytest.approx(1.0) and exact["arm_psnr"] > 60  # the real future itself
    assert exact["arm_psnr_tokenizer"] < 40  # an untrained tokenizer does not reconstruct noise
    frozen = (real[:, :1].float() / 255).expand(-1, T, -1, -1, -1, -1)
    still = arm_measures(tokenizer, start, frozen, torch.zeros(K, T, D), window=3)
    assert still["motion_ratio"] == 0.0 and still["retrieval_state"] == pytest.approx(1 / K)  # tied: chance
    np.testing.assert_allclose(still["tcp_error_m"], 0.1, rtol=1e-5)
    summary = summarise_arm([exact, still])
    assert exact["scene_psnr_in_window"] > 60 and exact["scene_psnr_past_window"] > 60
    assert exact["arm_psnr_past_window"] > 60
    assert summary["tcp_error_cm"] == pytest.approx(5.0, abs=1e-3)  # median of three 0 cm and three 10 cm
    assert summary["retrieval_state"] == pytest.approx((1 + 1 / K) / 2)


def test_the_scene_is_read_in_and_past_the_window():
    """With a window of 3 frames, rollout frames 0-1 are generated seeing the start and frames 2-3 are not: a rollout
    that keeps the scene until the start leaves its window and loses it after reads high in and low past it; the arm's
    region alone past the window is read apart from the scene."""
    tokenizer = VisualTokenizer(TinyTokenizerConfig(image_size=32)).eval()
    K, T, n = 2, 4, 1
    real = torch.full((K, T, n, 3, 32, 32), 128, dtype=torch.uint8)
    masks = torch.zeros(K, T, n, 32, 32, dtype=torch.uint8)
    masks[..., :8, :8] = ROBOT
    start = ControlStart(0, [0, 1], "push", torch.zeros(1, 64), torch.zeros(K, T * 4, 7), real, masks, None, None)
    pred = real.float() / 255
    pred[:, 2:, ..., 16:, 16:] = 1.0  # the scene lost past the window, the arm's corner kept
    read = arm_measures(tokenizer, start, pred, None, window=3)
    assert read["scene_psnr_in_window"] == 100.0  # exact: the clamp of a zero error
    assert read["scene_psnr_past_window"] < 15 and read["arm_psnr_past_window"] == 100.0
    short = arm_measures(tokenizer, start, pred, None, window=5)  # the horizon ends before the start leaves
    assert "scene_psnr_past_window" not in short and "arm_psnr_past_window" not in short


def test_offsets_are_distinct_directions_of_the_given_length():
    out = offsets(seed=5, sequences=4, length=0.6)
    assert np.all(out[0] == 0)
    np.testing.assert_allclose(np.linalg.norm(out[1:], axis=1), 0.6, rtol=1e-5)
    cosines = out[1:] @ out[1:].T / 0.36
    assert (cosines[~np.eye(3, dtype=bool)] < 0.9).all()


def test_sequences_share_their_start_and_part_ways(control_set):
    dataset, _ = control_set
    episodes = [read_episode(dataset, i) for i in range(SEQUENCES)]
    facts = [episode_facts(dataset, i) for i in range(SEQUENCES)]
    assert [f["sequence"] for f in facts] == list(range(SEQUENCES)) and {f["start"] for f in facts} == {0}
    for e in episodes[1:]:
        # The same initial state (the first frame) under different actions: the frames part ways.
        np.testing.assert_array_equal(e.images["third_view"][0], episodes[0].images["third_view"][0])
        assert np.abs(e.images["third_view"][-1].astype(int) - episodes[0].images["third_view"][-1]).mean() > 0.5
        drift = e.action[:, :3] - episodes[0].action[:, :3]
        assert np.abs(drift).max() > 0.1


def test_controllability_report(control_set, trained_tokenizer, world_models, tmp_path):
    _, root = control_set
    cfg = ControllabilityReportConfig(
        dataset=DatasetConfig(repo_id="local/roboscape_controllability", root=str(root)),
        tokenizer=str(trained_tokenizer),
        world_model=str(world_models["action"]),
        output_dir=tmp_path,
        horizon=STEPS - 1,
    )
    report = evaluate_controllability(cfg)
    assert (tmp_path / "controllability.json").is_file() and (tmp_path / "controllability.png").is_file()
    assert len(report["starts"]) == 2
    for start in report["starts"]:
        for name in ("world_model", "ignoring_actions"):
            assert np.asarray(start[name]["whole_frame"]["psnr"]).shape == (SEQUENCES, SEQUENCES)
    assert np.isfinite(report["summary"]["action_gain_db"])
    arm = report["summary"]["arm"]  # the collection's robot masks and states, read by the model's state channel
    assert {"arm_psnr", "arm_psnr_tokenizer", "tcp_error_cm", "tcp_error_share_of_moved", "retrieval_state"} <= set(arm)
    assert 0 <= arm["retrieval_state"] <= 1 and arm["tcp_error_cm"] >= 0
    assert all(len(start["arm"]["tcp_error_m"]) == SEQUENCES for start in report["starts"])
    assert report["summary"]["likelihood_retrieval"] == pytest.approx(
        np.mean([start["likelihood_retrieval"] for start in report["starts"]])
    )
    # The null-action model makes one rollout for all sequences: retrieval is exactly chance.
    assert report["summary"]["ignoring_actions"]["whole_frame"]["retrieval"] == pytest.approx(1 / SEQUENCES)
    # The model's retrieval: over the starts, the share of rollouts whose PSNR is highest to their own real future.
    hits = []
    for start in report["starts"]:
        psnr = np.asarray(start["world_model"]["whole_frame"]["psnr"])
        hits += [float(row.argmax() == i) for i, row in enumerate(psnr)]  # random weights: no exact ties
    assert report["summary"]["world_model"]["whole_frame"]["retrieval"] == pytest.approx(np.mean(hits))
    with pytest.raises(ValueError, match="need"):
        evaluate_controllability(
            ControllabilityReportConfig(cfg.dataset, cfg.tokenizer, cfg.world_model, tmp_path, horizon=STEPS + 3)
        )


def test_action_model_training_reads_retrieval_and_action_gain_on_the_control_set(
    control_set, demo_dataset, trained_tokenizer, token_cache, tmp_path
):
    """fit's held-out evaluation: every eval_freq steps, retrieval and action gain on the controllability set, on a
    clock that counts training only."""
    import draccus

    from lerobot_roboscape.training.loop import read_curve
    from lerobot_roboscape.world_model.train import TrainWorldModelConfig, train_world_model
    from tests.world_model.test_training import train_args

    _, root = control_set
    # The same set read once and saved, as the device machine (without the videos) gets it: measured beside it.
    from lerobot_roboscape.world_model.measures.controllability import load_control_starts, save_control_starts

    saved = tmp_path / "sets" / "ind.safetensors"
    saved.parent.mkdir()
    reader = VisualTokenizer.from_pretrained(str(trained_tokenizer)).eval()
    read = read_control_set(open_dataset("local/roboscape_controllability", root), reader, 4, 4, "cpu")
    save_control_starts(read, saved, frame_skip=4)
    loaded = load_control_starts(saved, frame_skip=4)
    assert [(s.start, s.episodes, s.task) for s in loaded] == [(s.start, s.episodes, s.task) for s in read]
    assert all(
        torch.equal(a.real, b.real) and torch.equal(a.actions, b.actions) for a, b in zip(read, loaded, strict=True)
    )
    with pytest.raises(ValueError, match="read for frame_skip=4"):
        load_control_starts(saved, frame_skip=2)
    args = train_args(demo_dataset, trained_tokenizer, token_cache, tmp_path / "run", steps=4) + [
        "--heldout_control.repo_id=local/roboscape_controllability",
        f"--heldout_control.root={root}",
        "--heldout_horizon=4",
        "--train.eval_freq=2",
        f"--heldout_starts=[{saved}]",
    ]
    train_world_model(draccus.parse(TrainWorldModelConfig, args=args))
    tmp_path = tmp_path / "run"
    curve = read_curve(tmp_path)
    assert [point["step"] for point in curve] == [2, 4]
    # The last reading is the final model's (the done head's refit after training leaves the frames as they are).
    from lerobot_roboscape.world_model.measures.controllability import control_summary

    model = STWorldModel.from_pretrained(str(tmp_path / "pretrained_model")).eval()
    tokenizer = VisualTokenizer.from_pretrained(str(trained_tokenizer)).eval()
    starts = read_control_set(
        open_dataset("local/roboscape_controllability", root), tokenizer, model.config.frame_skip, 4, "cpu"
    )
    final = control_summary(model, tokenizer, starts)
    for key in ("retrieval_whole_frame", "retrieval_object", "action_gain_db", "likelihood_retrieval"):
        assert curve[-1][key] == pytest.approx(final[key], abs=1e-4), key
        assert curve[-1][f"ind/{key}"] == pytest.approx(final[key], abs=1e-4), key  # the same starts, saved
    assert curve[0]["seconds"] <= curve[1]["seconds"]


def test_a_model_deaf_to_its_actions_retrieves_by_likelihood_at_chance(control_set, trained_tokenizer, world_models):
    _, root = control_set
    dataset = open_dataset("local/roboscape_controllability", root)
    tokenizer = VisualTokenizer.from_pretrained(trained_tokenizer).eval()
    model = STWorldModel.from_pretrained(world_models["action"]).eval()
    start = read_control_set(dataset, tokenizer, model.config.frame_skip, STEPS - 1, "cpu")[0]
    episode_control = model.episode_control
    model.episode_control = lambda *a, **k: model.null_control(episode_control(*a, **k))
    # The same likelihood under every sequence: each future's own is tied with all others, 1/K.
    assert likelihood_retrieval(model, tokenizer, start) == pytest.approx(1 / SEQUENCES)


def test_eval_wm_reads_controllability_over_both_horizons(
    control_set, trained_tokenizer, world_models, tmp_path, capsys
):
    from lerobot_roboscape.cli.eval_wm import main

    _, root = control_set
    dataset = ["--dataset.repo_id=local/roboscape_controllability", f"--dataset.root={root}"]
    control = ["--controllability.repo_id=local/roboscape_controllability", f"--controllability.root={root}"]
    args = [f"--tokenizer={trained_tokenizer}", f"--world_model={world_models['action']}", f"--output_dir={tmp_path}"]
    main(
        [*dataset, *control, *args, "--prompt_frames=1", "--horizon=4", "--long_horizon=4", "--allow_random_lpips=true"]
    )
    printed = capsys.readouterr().out
    assert "retrieval over 4 control steps (world_model)" in printed and "action gain over 4 control steps" in printed
    report = json.loads((tmp_path / "fidelity.json").read_text())
    assert report["controllability_long"]["action_gain_db"] == pytest.approx(
        report["controllability"]["action_gain_db"]
    )
    assert (tmp_path / "long_horizon" / "controllability.json").is_file()
