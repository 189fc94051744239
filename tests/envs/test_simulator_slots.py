"""The simulator's envs spread over worker processes give the episodes of one process, bit for bit."""

import numpy as np
import pytest

from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig
from lerobot_roboscape.envs.maniskill_env import RoboscapeManiSkillEnv
from lerobot_roboscape.envs.simulator_slots import SlotSpec, SlotWorkers
from lerobot_roboscape.tasks import SCENES
from roboscape_core.errors import InvalidInputError
from tests.conftest import IMAGE_SIZE

pytestmark = pytest.mark.slow  # the simulator in worker processes


def rollout(workers: int) -> list:
    config = RoboscapeManiSkillEnvConfig(
        families=["pick_place", "push"], image_size=IMAGE_SIZE, episode_length=3, workers=workers
    )
    env = RoboscapeManiSkillEnv(config, num_envs=3)  # an uneven share: 2 slots in one worker, 1 in the other
    actions = np.random.default_rng(0).uniform(-1, 1, (3, 3, 7)).astype(np.float32)
    steps = [env.reset(seed=4)]
    steps += [env.step(a) for a in actions]
    env.close()
    return steps


def test_any_number_of_workers_gives_the_same_episodes():
    one, two = rollout(1), rollout(2)
    assert one[0][1]["task"] == two[0][1]["task"]
    for step_1, step_2 in zip(one, two, strict=True):
        for camera in step_1[0]["pixels"]:
            np.testing.assert_array_equal(step_1[0]["pixels"][camera], step_2[0]["pixels"][camera])
    for step_1, step_2 in zip(one[1:], two[1:], strict=True):
        for a, b in zip(step_1[1:4], step_2[1:4], strict=True):  # reward, terminated, truncated
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(step_1[4]["is_success"], step_2[4]["is_success"])


def test_a_failing_worker_names_itself_and_the_cause():
    spec = SlotSpec(SCENES[0].id, IMAGE_SIZE, 10)
    with pytest.raises(RuntimeError, match=r"simulator worker 1 \(slots \[1\]\) failed:(.|\n)*no_such_family"):
        SlotWorkers(["push", "no_such_family"], spec, workers=2)


def test_workers_must_be_positive():
    with pytest.raises(InvalidInputError, match="workers must be >= 1 or null"):
        RoboscapeManiSkillEnvConfig(workers=0)
