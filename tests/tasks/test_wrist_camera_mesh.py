"""The light wrist-camera mesh renders the same frames as ManiSkill's, but for a few pixels of the camera's outline."""

import numpy as np
import pytest
import sapien

from lerobot_roboscape.demos.rollout import EpisodeJob, run_planned_episode
from lerobot_roboscape.tasks import SCENES
from lerobot_roboscape.tasks.make import make_task_env
from lerobot_roboscape.tasks.wrist_camera_mesh import WRIST_CAMERA_LINK
from tests.conftest import IMAGE_SIZE

pytestmark = pytest.mark.slow  # the simulator


def camera_triangles(env) -> int:
    entity = env.unwrapped.agent.robot.links_map[WRIST_CAMERA_LINK]._objs[0].entity
    body = entity.find_component_by_type(sapien.render.RenderBodyComponent)
    return sum(len(part.triangles) for shape in body.render_shapes for part in shape.parts)


def test_light_mesh_renders_the_planner_episode_as_before():
    job = EpisodeJob("pick_place", SCENES[3].id, seed=5, kind="optimal", image_size=IMAGE_SIZE)
    episodes, triangles = {}, {}
    for light in (False, True):
        env = make_task_env("pick_place", SCENES[0].id, image_size=IMAGE_SIZE, light_wrist_camera=light)
        episodes[light] = run_planned_episode(env, job)
        triangles[light] = camera_triangles(env)
        env.close()
    assert triangles[True] < 0.05 * triangles[False]
    before, after = episodes[False], episodes[True]
    np.testing.assert_array_equal(before.action, after.action)  # physics untouched: the same plan, the same moves
    np.testing.assert_array_equal(before.state, after.state)
    np.testing.assert_array_equal(before.images["wrist"], after.images["wrist"])  # the body is out of its view
    old, new = before.images["third_view"].astype(float), after.images["third_view"].astype(float)
    changed = (np.abs(old - new).sum(-1) > 0).mean(axis=(1, 2))  # share of each frame's pixels
    assert changed.max() < 0.03, changed.max()
    psnr = 10 * np.log10(255**2 / ((old - new) ** 2).mean())
    assert psnr > 36, psnr
