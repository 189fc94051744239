"""A light render mesh for the wrist camera's body (a RealSense D415 on `panda_wristcam`).

The mesh ManiSkill ships for it has 425,160 triangles, 73% of the scene's, inside and out. Software rendering
(lavapipe, on machines without a GPU) pays per triangle whatever the image size, so this one part made each camera
frame cost about 40 ms instead of 10. The camera body is a rounded box: its convex hull (about 12,600 triangles),
shaded with the normals of the original surface, renders the same to within a few pixels of its outline
(tests/tasks/test_wrist_camera_mesh.py). Physics is untouched: only the visual shape is replaced.
"""

import numpy as np
import sapien
import trimesh
from mani_skill.agents.base_agent import BaseAgent
from scipy.spatial import cKDTree

WRIST_CAMERA_LINK = "camera_link"
NORMAL_NEIGHBOURS = 16  # original faces searched for each hull vertex's normal


# Robot uid -> the light mesh's (vertices, triangles, normals): made once per process, as every reset rebuilds the
# robot from its URDF.
_LIGHT_MESHES: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def light_mesh(
    vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, triangles, normals) of the convex hull of a triangle soup, as a soup again (flat triangles), each
    vertex taking the normal of the nearby original face that faces the same way (so the rounded edges shade as
    before)."""
    hull = trimesh.Trimesh(vertices, triangles).convex_hull
    soup = np.asarray(hull.vertices, np.float32)[hull.faces].reshape(-1, 3)  # (3F, 3)
    soup_normals = np.repeat(np.asarray(hull.face_normals, np.float32), 3, axis=0)
    centres = vertices[triangles].mean(axis=1)  # (F_original, 3)
    face_normals = normals[triangles[:, 0]]  # an STL soup has one normal per face
    distance, index = cKDTree(centres).query(soup, k=NORMAL_NEIGHBOURS)
    candidates = face_normals[index]  # (3F, k, 3)
    # The closest face that faces the hull's way; 20 per metre trades a 5 cm step against a reversed normal.
    score = (candidates * soup_normals[:, None]).sum(-1) - 20 * distance
    chosen = candidates[np.arange(len(soup)), score.argmax(1)]
    return soup, np.arange(len(soup), dtype=np.uint32).reshape(-1, 3), chosen.astype(np.float32)


def lighten_wrist_camera(agent: BaseAgent) -> None:
    """Replace the render mesh of the wrist camera's body with its light version (in every sub-scene)."""
    for link in agent.robot.links_map[WRIST_CAMERA_LINK]._objs:
        entity = link.entity
        body = entity.find_component_by_type(sapien.render.RenderBodyComponent)
        (shape,) = body.render_shapes  # the URDF gives the camera body one mesh of one part
        (part,) = shape.parts
        if agent.uid not in _LIGHT_MESHES:
            _LIGHT_MESHES[agent.uid] = light_mesh(part.vertices, part.triangles, part.get_vertex_normal())
        vertices, triangles, normals = _LIGHT_MESHES[agent.uid]
        mesh = sapien.render.RenderShapeTriangleMesh(
            vertices, triangles, normals, np.zeros((len(vertices), 2), np.float32), part.material
        )
        mesh.local_pose = shape.local_pose
        light = sapien.render.RenderBodyComponent()
        light.attach(mesh)
        entity.remove_component(body)
        entity.add_component(light)
