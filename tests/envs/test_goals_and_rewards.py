"""roboscape_wm's goals and rewards: goal frames generated, saved and read back, or taken from the dataset; a reward
that is higher at the goal, and frames that reach it return more."""

import logging

import numpy as np
import pytest
import torch

from lerobot_roboscape.dataset.reader import episode_facts, open_dataset, read_episode
from lerobot_roboscape.envs.goal_bank import GoalBank, goal_generation_seconds
from lerobot_roboscape.envs.reward_report import replay_rewards
from lerobot_roboscape.envs.world_model_env import RoboscapeWorldModelEnv
from lerobot_roboscape.metrics.perceptual import load_lpips
from lerobot_roboscape.reward.world_model_reward import WorldModelReward
from lerobot_roboscape.world_model.clips import model_frames
from roboscape_core.errors import InvalidInputError


def test_goal_never_reached_is_explicit(env_config, caplog):
    env = RoboscapeWorldModelEnv(env_config(theta=1.0, max_goal_steps=2), num_envs=2)
    with caplog.at_level(logging.WARNING):
        _, info = env.reset(seed=0, options={"episode_index": [0, 2]})
    assert not info["goal_from_text_model"].any()
    assert "done stayed below theta=1.00 for 2 control steps" in caplog.text


def test_goal_file_holds_every_start_and_is_read_back(env_config, tmp_path, monkeypatch):
    path = tmp_path / "goals.safetensors"
    env = RoboscapeWorldModelEnv(env_config(goal_file=str(path)), num_envs=2)
    assert path.is_file() and set(env.goal_bank.cache) == {s.episode_index for s in env.starts}  # made at creation
    assert goal_generation_seconds(path) > 0
    _, info = env.reset(seed=0, options={"episode_index": [0, 2]})

    def no_generation(*args):
        raise AssertionError("goals were generated again")

    monkeypatch.setattr(GoalBank, "_fill", no_generation)
    again = RoboscapeWorldModelEnv(env_config(goal_file=str(path)), num_envs=2)
    _, info_again = again.reset(seed=0, options={"episode_index": [0, 2]})
    np.testing.assert_array_equal(info_again["goal"]["wrist"], info["goal"]["wrist"])
    with pytest.raises(InvalidInputError, match=r"goals.safetensors was made with other settings \{'theta'"):
        RoboscapeWorldModelEnv(env_config(goal_file=str(path), theta=0.5), num_envs=2)
    # A text model retrained in the same folder: its weights differ, so the goals of the one it replaced are refused.
    retrained = again.text_model
    with torch.no_grad():
        next(retrained.parameters()).add_(1.0)
    monkeypatch.setattr(
        "lerobot_roboscape.envs.world_model_env.load_models",
        lambda *args, **kwargs: (again.tokenizer, again.action_model, retrained),
    )
    with pytest.raises(InvalidInputError, match=r"goals.safetensors was made with other settings \{'weights'"):
        RoboscapeWorldModelEnv(env_config(goal_file=str(path)), num_envs=2)


def test_goal_from_the_dataset_episode(env_config, token_cache):
    env = RoboscapeWorldModelEnv(env_config(goal_source="dataset_last_frame", text_world_model=None), num_envs=1)
    _, info = env.reset(seed=0, options={"episode_index": 1})
    row = next(r for r in token_cache.episodes if r["episode_index"] == 1)
    last = torch.from_numpy(token_cache.tokens[row["start"] + row["length"] - 1].astype(np.int64)).reshape(1, -1)
    expected = env._pixels(env.decode(last))
    np.testing.assert_array_equal(info["goal"]["wrist"], expected["wrist"])


def test_reward_is_higher_at_the_goal():
    reward = WorldModelReward(load_lpips(allow_random_trunk=True), alpha=0.5, beta=0.5, theta_sps=0.9)
    g = torch.Generator().manual_seed(0)
    goal = torch.rand(4, 2, 3, 32, 32, generator=g)
    other = torch.rand(4, 2, 3, 32, 32, generator=g)
    at_goal = reward(goal, goal, torch.zeros(4))
    elsewhere = reward(other, goal, torch.zeros(4))
    assert torch.allclose(at_goal.dense, torch.ones(4)) and (at_goal.reward > elsewhere.reward).all()
    done = reward(other, goal, torch.tensor([0.95, 0.5, 0.9, 0.0]))
    assert done.sparse.tolist() == [10.0, 0.0, 10.0, 0.0]
    torch.testing.assert_close(done.reward, 0.5 * done.sparse + 0.5 * done.dense)


@pytest.mark.parametrize("terminate_on_success", [False, True])
def test_frames_that_reach_the_goal_return_more(env_config, demo_dataset, terminate_on_success):
    """The default reward along a real successful episode (done where the recording shows success) against the
    same start standing still: reaching the goal must pay more, whether success ends the episode or not."""
    _, root = demo_dataset
    config = env_config(
        goal_source="dataset_last_frame",
        text_world_model=None,
        episode_length=None,
        terminate_on_success=terminate_on_success,
    )
    env = RoboscapeWorldModelEnv(config, num_envs=1)
    data = open_dataset("test/demos", root)
    k = env.frame_skip
    episode = next(
        e
        for e in map(lambda i: read_episode(data, i), range(data.meta.total_episodes))
        if e.done_label[::k].max() > 0 and e.info["task_family"] == "push"  # success shows in a model frame
    )
    start = next(s for s in env.starts if s.episode_index == episode.index)
    facts = [episode_facts(data, i) for i in range(data.meta.total_episodes)]
    assert start.horizon == max(
        data.meta.episodes[i]["length"] for i, f in enumerate(facts) if f["task_family"] == "push" and f["success"]
    )  # the longest successful push
    frames = model_frames(len(episode.action), k)  # what the action model would have made, a frame per k steps
    tokens = env.encode({cam: episode.images[cam][frames] for cam in env.cameras})
    reached, reached_success = replay_rewards(env, episode.index, tokens, torch.from_numpy(episode.done_label[frames]))
    still, still_success = replay_rewards(env, episode.index, tokens[:1].expand(2, -1), torch.zeros(2))
    assert reached_success and not still_success
    assert len(reached) == len(still) == start.horizon
    assert reached.sum() > still.sum()
    assert (reached[np.arange(start.horizon) % k != k - 1] == 0).all()  # paid at each chunk's last step only
