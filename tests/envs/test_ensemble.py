"""roboscape_wm with an ensemble of action models: their disagreement (mutual information) penalises and halts an
episode, and so does a predicted state that leaves the data's range."""

import numpy as np
import pytest
import torch

from lerobot_roboscape.dataset.reader import open_dataset, read_episode
from lerobot_roboscape.envs.world_model_env import RoboscapeWorldModelEnv
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from roboscape_core.errors import InvalidInputError


def test_an_ensemble_that_agrees_changes_nothing_and_one_that_parts_penalises_and_halts(env_config, tmp_path):
    """The env's own model as the ensemble's member agrees everywhere: the rewards are those of no ensemble. A member
    with other weights disagrees: the reward drops by exactly lambda x the reported disagreement, and a threshold
    below it halts every episode at its first frame (terminated, nothing paid after)."""
    from lerobot_roboscape.world_model.modeling_world_model import STWorldModel

    own = env_config().action_world_model
    other = STWorldModel.from_pretrained(own)
    with torch.no_grad():
        torch.manual_seed(0)
        for p in other.parameters():
            p.add_(p.abs().mean() * torch.randn_like(p))
    other.save_pretrained(tmp_path / "other")

    def run(**overrides):
        env = RoboscapeWorldModelEnv(env_config(precision="float32", episode_length=8, **overrides), num_envs=2)
        env.reset(seed=0)
        steps = [env.step(np.full((2, 7), 0.3, np.float32)) for _ in range(8)]
        return [(reward, terminated, info) for _, reward, terminated, _, info in steps]

    plain, same = run(), run(ensemble=[own], disagreement_penalty=5.0)
    assert "disagreement" not in plain[0][2]  # no ensemble: nothing to report (PPO logs none)
    for (reward, _, _), (reward_same, _, info) in zip(plain, same, strict=True):
        np.testing.assert_allclose(reward_same, reward, atol=1e-4)
        assert (info["disagreement"] < 1e-4).all()
    other = [str(tmp_path / "other")]
    free, paid = run(ensemble=other), run(ensemble=other, disagreement_penalty=2)
    parted = np.stack([info["disagreement"] for _, _, info in free])
    assert parted.max() > 1e-3 and parted.max() <= np.log(2) + 1e-4  # two models: log 2 nats at most
    for (reward, _, _), (reward_paid, _, info) in zip(free, paid, strict=True):
        np.testing.assert_allclose(reward_paid, reward - 2 * info["disagreement"], atol=1e-4)
    first = next(t for t, (_, _, info) in enumerate(free) if (info["disagreement"] > 0).all())
    halted = run(ensemble=other, disagreement_threshold=float(parted[first].min()) / 2)
    _, terminated, info = halted[first]
    assert terminated.all() and info["halted"].all()
    assert np.array_equal(info["is_success"], free[first][2]["is_success"])  # the halted frame's own success stands
    assert all((reward == 0).all() for reward, _, _ in halted[first + 1 :])
    with pytest.raises(InvalidInputError, match="need ensemble"):
        env_config(disagreement_penalty=1.0)


def test_a_state_margin_halts_an_episode_whose_predicted_state_leaves_the_datas_range(
    env_config, demo_dataset, tmp_path
):
    """The action model keeps its training states' range. A margin that the rollout cannot leave changes nothing; a
    range the first predicted state lies outside halts every episode at that frame: terminated, unpaid, no success,
    although the done (theta near 0) calls every frame a success."""
    _, root = demo_dataset
    own = env_config().action_world_model
    model = STWorldModel.from_pretrained(own)
    dataset = open_dataset("test/demos", root)
    states = np.concatenate([read_episode(dataset, e).state for e in range(dataset.meta.total_episodes)])
    np.testing.assert_allclose(model.config.state_min, states.min(0), atol=1e-5)  # the data's range, saved
    np.testing.assert_allclose(model.config.state_max, states.max(0), atol=1e-5)
    model.config.state_min = model.config.state_max = (states.min(0) - 1).tolist()  # no state lies there
    model.save_pretrained(tmp_path / "walled")

    def run(**overrides):
        env = RoboscapeWorldModelEnv(env_config(precision="float32", episode_length=8, theta=1e-6, **overrides), 2)
        env.reset(seed=0)
        return [env.step(np.full((2, 7), 0.9, np.float32))[1:] for _ in range(8)]

    plain, wide = run(), run(state_margin=1e6)
    for (reward, *_), (reward_wide, terminated_wide, _, info_wide) in zip(plain, wide, strict=True):
        np.testing.assert_array_equal(reward_wide, reward)
        assert not terminated_wide.any() and not info_wide["halted"].any()
    assert wide[-1][3]["is_success"].all()  # from the first generated frame on
    walled = run(action_world_model=str(tmp_path / "walled"), state_margin=0.0)
    k = RoboscapeWorldModelEnv(env_config(), 1).frame_skip
    reward, terminated, _, info = walled[k - 1]  # the first generated frame
    assert terminated.all() and info["halted"].all() and not info["is_success"].any() and (reward == 0).all()
    assert all((reward == 0).all() and not info["is_success"].any() for reward, _, _, info in walled[k:])
    model.config.state_min = model.config.state_max = None
    model.save_pretrained(tmp_path / "unbounded")
    with pytest.raises(InvalidInputError, match="carries no range of its training data's states"):
        RoboscapeWorldModelEnv(env_config(action_world_model=str(tmp_path / "unbounded"), state_margin=0.1), 1)
    with pytest.raises(InvalidInputError, match="state_margin must be >= 0"):
        env_config(state_margin=-0.1)


def test_mutual_information_of_models_that_agree_and_of_models_sure_of_different_tokens():
    from lerobot_roboscape.envs.ensemble import mutual_information

    logits = torch.randn(3, 5, 16)
    assert torch.allclose(mutual_information([logits, logits, logits]), torch.zeros(3), atol=1e-6)
    sure = torch.full((1, 5, 16), -1e4)
    a, b = sure.clone(), sure.clone()
    a[..., 0], b[..., 1] = 0.0, 0.0  # each certain, of another token
    torch.testing.assert_close(mutual_information([a, b]), torch.tensor([np.log(2)], dtype=torch.float32))
