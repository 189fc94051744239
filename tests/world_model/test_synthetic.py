"""The control path on synthetic worlds where nothing but the control predicts the change (world_model/synthetic.py):
the tiny world model must follow its actions and instructions, and the same model trained on controls unlinked from
their frames must not."""

import numpy as np
import pytest
import torch

from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from lerobot_roboscape.world_model.synthetic import SyntheticWorld, drift, retrieval, train_on_world, world_model

pytestmark = [pytest.mark.slow, pytest.mark.e2e]  # the tiny model trained to solve three worlds: minutes on 2 cores
GRID, WINDOW, HORIZON = 5, 5, 4
# Training stops once retrieval reaches SOLVED twice in a row (read every EVAL_EVERY steps), at most MAX_STEPS; the
# model trained on unlinked controls then trains as many steps. On 8x8 grids the tiny model with AdaLN reached 0.9
# on motion after 1,000-1,200 steps (docs/results/world_model/control_levers.md).
SOLVED, EVAL_EVERY, MAX_STEPS = 0.95, 50, {"wiring": 2000, "motion": 2000, "text": 600}


def tiny_model(world: SyntheticWorld, seed: int = 0) -> STWorldModel:
    """The tiny preset sized to the world's grid, a frame per action."""
    return world_model(world, WINDOW, seed)


@pytest.fixture(scope="module")
def trained():
    """kind -> (world, model trained on it, the same model trained as long on controls unlinked from the frames:
    shuffled actions for motion, one instruction for both for text)."""
    out = {}
    for kind, max_steps in MAX_STEPS.items():
        world = SyntheticWorld(kind, grid=GRID)
        model = tiny_model(world)
        curve = train_on_world(model, world, max_steps, eval_every=EVAL_EVERY, until=SOLVED)
        unlinked = None
        if kind != "wiring":
            unlinked = tiny_model(world)
            train_on_world(unlinked, world, curve[-1]["step"], shuffle=True)
        out[kind] = (world, model, unlinked)
    return out


def measure(model, world):
    return retrieval(model, world, starts=32, horizon=HORIZON, seed=99)  # starts the training never saw


def test_worlds_move_only_by_their_control():
    rng = np.random.default_rng(0)
    for kind in ("wiring", "motion"):
        world = SyntheticWorld(kind, grid=GRID)
        background, position = world.random_starts(rng, 8, 3)
        actions = world.random_controls(rng, 8, 3)
        a = world.episodes(rng, 8, 3, controls=actions, starts=(background, position))["tokens"]
        b = world.episodes(rng, 8, 3, controls=actions, starts=(background, position))["tokens"]
        assert np.array_equal(a, b)  # the same start and actions: the same future
        assert (a == world.square_token).sum(-1).min() == 4  # one 2 x 2 square, always whole
        assert np.abs(actions).max() <= 0.35  # small, as the planner's
    motion = SyntheticWorld("motion", grid=GRID)
    right = np.zeros((1, 7), np.float32)
    right[0, 0] = 0.35
    assert motion.next_position(np.array([[0, 0]]), right).tolist() == [[1, 0]]
    assert motion.next_position(np.array([[3, 2]]), right).tolist() == [[3, 2]]  # clamped at the border
    text = SyntheticWorld("text", grid=GRID)
    assert text.next_position(np.array([[0, 0], [0, 0]]), np.array([0, 1])).tolist() == [[1, 0], [0, 1]]


class _Replay:
    """A rollout that is the world's own future (`frozen`: its first frame, held), as drift() reads a model."""

    def __init__(self, world: SyntheticWorld, frozen: bool):
        self.world, self.frozen = world, frozen
        self.weight = torch.nn.Parameter(torch.zeros(1))

    def parameters(self):
        return iter([self.weight])

    def generate(self, prompt, n_frames, actions, states):
        real = self.world.episodes(np.random.default_rng(4321), len(prompt), n_frames)["tokens"]
        frames = np.repeat(real[:, :1], n_frames, 1) if self.frozen else real[:, 1:]
        return type("Generated", (), {"tokens": torch.from_numpy(frames)})


def test_drift_reads_a_kept_world_as_kept_and_a_held_frame_as_losing_the_square():
    world = SyntheticWorld("motion", grid=GRID)
    real = drift(_Replay(world, frozen=False), world, starts=16, horizon=12)
    assert all(min(real[name]) == 1.0 for name in ("background", "uncovered", "square"))
    held = drift(_Replay(world, frozen=True), world, starts=16, horizon=12)
    assert min(held["background"]) == 1.0  # the first frame's background is the real one wherever it shows
    assert held["square"][0] < 1 and max(held["square"][4:]) < 0.5  # the square stays while the real one moves


@pytest.mark.parametrize("kind", ["wiring", "motion"])
def test_action_model_follows_its_actions(trained, kind):
    world, model, _ = trained[kind]
    assert measure(model, world)[0] >= 0.9


def test_action_model_trained_on_shuffled_actions_is_at_chance(trained):
    world, _, shuffled = trained["motion"]
    assert measure(shuffled, world)[0] <= 0.35  # K = 4: chance is 0.25


def test_permuting_the_actions_permutes_the_rollouts(trained):
    world, model, _ = trained["motion"]
    rng = np.random.default_rng(5)
    background, position = world.random_starts(rng, 1, HORIZON)
    actions = torch.from_numpy(world.random_controls(rng, 4, HORIZON))
    prompt = torch.from_numpy(world.render(background, position))[:, None].expand(4, 1, -1)
    state = torch.from_numpy(position).float()[:, None].expand(4, 1, -1)
    rollouts, _, states = model.generate(prompt, HORIZON, actions=actions, states=state)
    order = torch.tensor([2, 0, 3, 1])
    permuted, _, permuted_states = model.generate(prompt, HORIZON, actions=actions[order], states=state)
    assert torch.equal(permuted, rollouts[order])
    torch.testing.assert_close(permuted_states, states[order])


def test_text_model_tells_its_instructions_apart(trained):
    world, model, one_instruction = trained["text"]
    assert measure(model, world)[0] >= 0.9  # each rollout nearer its own instruction's future in >= 90% of starts
    assert measure(one_instruction, world)[0] <= 0.6  # trained with one instruction for both: chance (0.5)
