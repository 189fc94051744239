"""The text model's goals: made where the done crosses theta (the last frame when it never does), judged from held-out
starts, and read along the text model's training as its held-out curve."""

import draccus
import numpy as np
import pytest
import torch

from lerobot_roboscape.dataset.reader import open_dataset, read_frames
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.tokenizer.similarity import TokenizerPerceptualDistance, frame_distance
from lerobot_roboscape.training.loop import read_curve
from lerobot_roboscape.world_model.goals import (
    generate_goals,
    goal_summary,
    load_goal_starts,
    read_goal_starts,
    save_goal_starts,
)
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from lerobot_roboscape.world_model.train import TrainWorldModelConfig, train_world_model
from roboscape_core.errors import InvalidInputError
from tests.world_model.test_training import train_args

TASK = "push the red cube forward"


@pytest.fixture(scope="module")
def text_model(world_models):
    return STWorldModel.from_pretrained(str(world_models["text"])).eval()


def prompt_of(token_cache, B: int):
    tokens = torch.from_numpy(token_cache.tokens[:1].astype("int64")).reshape(1, -1).expand(B, -1)
    return tokens, torch.from_numpy(token_cache.states[:1]).reshape(1, -1).expand(B, -1)


def test_a_goal_is_the_frame_where_the_done_crosses_theta(text_model, token_cache):
    """Start 0's done crosses theta at its second frame, start 1's never: goal 0 is its second frame, reached after
    two frames of control steps; goal 1 is the last frame generated, its steps the whole budget."""
    frames, k = [], text_model.config.frame_skip

    def done_of(frame, model_done):
        frames.append(frame.clone())
        return torch.tensor([0.2, 0.1]) if len(frames) < 2 else torch.tensor([0.95, 0.3])

    prompt, states = prompt_of(token_cache, 2)
    goals = generate_goals(text_model, prompt, [TASK] * 2, 0.9, k, 4 * k, states, done_of)
    assert goals.reached.tolist() == [True, False]
    assert goals.steps.tolist() == [2 * k, 4 * k]
    assert len(frames) == 4  # start 1 never crossed: the whole budget was generated
    assert torch.equal(goals.tokens[0], frames[1][0]) and torch.equal(goals.tokens[1], frames[-1][1])
    assert goals.done_max.tolist() == pytest.approx([0.95, 0.3])
    assert goals.states is not None and goals.states.shape == states.shape


def test_goal_starts_are_saved_and_judged_by_the_done_and_the_distance(
    text_model, demo_dataset, trained_tokenizer, tmp_path
):
    _, root = demo_dataset
    dataset = open_dataset("test/demos", root)
    tokenizer = VisualTokenizer.from_pretrained(str(trained_tokenizer)).eval()
    starts = read_goal_starts(dataset, tokenizer, keep=2)
    assert len(starts) == 2 and all(s.horizon >= 1 for s in starts)
    last = tokenizer.encode_frames(list(read_frames(dataset, starts[0].episode_index, [-1]).values()))[0]
    assert torch.equal(starts[0].last, last.cpu())
    save_goal_starts(starts, tmp_path / "ind.safetensors")
    loaded = load_goal_starts(tmp_path / "ind.safetensors")
    assert [(s.episode_index, s.task, s.horizon, s.success) for s in loaded] == [
        (s.episode_index, s.task, s.horizon, s.success) for s in starts
    ]
    assert all(
        torch.equal(a.first, b.first) and torch.equal(a.last, b.last) for a, b in zip(starts, loaded, strict=True)
    )
    k, distance = text_model.config.frame_skip, TokenizerPerceptualDistance(tokenizer)
    # Any done crosses a threshold this low at the first frame, within every horizon; none crosses 1.
    at_once = goal_summary(text_model, tokenizer, distance, loaded, 1e-9, k)
    assert at_once["goal_reached"] == 1.0 and at_once["goal_steps_share"] == pytest.approx(
        np.median([k / s.horizon for s in loaded])
    )
    never = goal_summary(text_model, tokenizer, distance, loaded, 1.0, k)
    assert never["goal_reached"] == 0.0 and 0.0 < never["goal_done_max"] < 1.0 and never["goal_steps_share"] is None
    assert never["goal_nearer_final"] is None or 0.0 <= never["goal_nearer_final"] <= 1.0


def test_frame_distance_averages_the_views_and_is_zero_at_the_frame_itself(trained_tokenizer):
    tokenizer = VisualTokenizer.from_pretrained(str(trained_tokenizer)).eval()
    distance = TokenizerPerceptualDistance(tokenizer)
    frames = torch.rand(3, 2, 3, 32, 32)
    assert frame_distance(distance, frames, frames).abs().max() < 1e-6
    other = frames.clone()
    other[:, 1] = torch.rand(3, 3, 32, 32)  # the second view only
    one_view = distance(frames[:, 1] * 2 - 1, other[:, 1] * 2 - 1).reshape(-1)
    assert torch.allclose(frame_distance(distance, frames, other), one_view / 2, atol=1e-6)


def test_text_model_training_reads_its_goals_on_each_goal_set(demo_dataset, trained_tokenizer, token_cache, tmp_path):
    _, root = demo_dataset
    tokenizer = VisualTokenizer.from_pretrained(str(trained_tokenizer)).eval()
    starts = read_goal_starts(open_dataset("test/demos", root), tokenizer, keep=2)
    save_goal_starts(starts, tmp_path / "ind.safetensors")
    args = train_args(demo_dataset, trained_tokenizer, token_cache, tmp_path / "run", "text", 4)
    goals = [f"--heldout_goals=[{tmp_path / 'ind.safetensors'}]", "--heldout_theta=0.5", "--train.eval_freq=2"]
    train_world_model(draccus.parse(TrainWorldModelConfig, args=args + goals))
    curve = read_curve(tmp_path / "run")
    assert [point["step"] for point in curve] == [2, 4]
    final = STWorldModel.from_pretrained(str(tmp_path / "run" / "pretrained_model")).eval()
    read = goal_summary(final, tokenizer, TokenizerPerceptualDistance(tokenizer), starts, 0.5, final.config.frame_skip)
    for key, value in read.items():  # the last reading is the final model's
        assert curve[-1][f"ind/{key}"] == (value if value is None else pytest.approx(value, abs=1e-6)), key
    with pytest.raises(InvalidInputError, match="heldout_goals judge the text model's goals"):
        TrainWorldModelConfig(heldout_goals=[tmp_path / "ind.safetensors"])  # the action model's, by default
    with pytest.raises(InvalidInputError, match="heldout_theta must be in"):
        TrainWorldModelConfig(heldout_theta=1.5)
