"""The scene catalogue: objects, containers, tables, task families, instructions and the IND/OOD split.

A *scene* is one object x one container x one table (paper, section 4.1). Every task family runs in every
scene; the split is by scene, so the same scenes are held out for all families. This module is the only place
that defines them.
"""

from dataclasses import dataclass
from typing import Literal

from roboscape_core.errors import InvalidInputError

Shape = Literal["cube", "box", "sphere", "cylinder"]


@dataclass(frozen=True)
class ObjectSpec:
    """A graspable object built from one primitive.

    Args:
        name: words used in instructions ("red cube").
        shape: primitive type.
        size: half extents (x, y, z) for cube/box; (radius,) for sphere; (radius, half_height) for cylinder.
        color: RGBA in [0, 1].
    """

    name: str
    shape: Shape
    size: tuple[float, ...]
    color: tuple[float, float, float, float]

    @property
    def slug(self) -> str:
        return self.name.replace(" ", "_")

    @property
    def half_height(self) -> float:
        """Height of the centre above the table when resting."""
        return {"cube": self.size[-1], "box": self.size[-1], "sphere": self.size[0], "cylinder": self.size[-1]}[
            self.shape
        ]


@dataclass(frozen=True)
class ContainerSpec:
    name: str
    radius: float
    wall_height: float  # 0 for a flat plate
    color: tuple[float, float, float, float]


@dataclass(frozen=True)
class TableSpec:
    name: str
    style: Literal["maniskill_wood", "box"]
    color: tuple[float, float, float, float] = (1, 1, 1, 1)


# Half sizes are kept <= 0.025 m across the gripper's closing axis (y) so that a panda grasp always fits.
OBJECTS: tuple[ObjectSpec, ...] = (
    ObjectSpec("red cube", "cube", (0.02, 0.02, 0.02), (0.85, 0.1, 0.1, 1)),
    ObjectSpec("green cube", "cube", (0.02, 0.02, 0.02), (0.1, 0.7, 0.2, 1)),
    ObjectSpec("small blue cube", "cube", (0.015, 0.015, 0.015), (0.1, 0.25, 0.85, 1)),
    ObjectSpec("large yellow cube", "cube", (0.024, 0.024, 0.024), (0.95, 0.85, 0.1, 1)),
    ObjectSpec("magenta cube", "cube", (0.018, 0.018, 0.018), (0.85, 0.1, 0.75, 1)),
    ObjectSpec("orange ball", "sphere", (0.02,), (1.0, 0.5, 0.05, 1)),
    ObjectSpec("purple ball", "sphere", (0.02,), (0.5, 0.15, 0.7, 1)),
    ObjectSpec("small cyan ball", "sphere", (0.016,), (0.1, 0.8, 0.85, 1)),
    ObjectSpec("large pink ball", "sphere", (0.024,), (1.0, 0.55, 0.7, 1)),
    ObjectSpec("teal ball", "sphere", (0.02,), (0.0, 0.5, 0.5, 1)),
    ObjectSpec("red can", "cylinder", (0.018, 0.03), (0.8, 0.05, 0.15, 1)),
    ObjectSpec("green can", "cylinder", (0.018, 0.03), (0.2, 0.55, 0.1, 1)),
    ObjectSpec("short blue can", "cylinder", (0.02, 0.018), (0.2, 0.3, 0.7, 1)),
    ObjectSpec("tall white can", "cylinder", (0.016, 0.04), (0.92, 0.92, 0.9, 1)),
    ObjectSpec("gold can", "cylinder", (0.02, 0.025), (0.85, 0.65, 0.15, 1)),
    ObjectSpec("brown block", "box", (0.035, 0.018, 0.02), (0.45, 0.28, 0.12, 1)),
    ObjectSpec("grey block", "box", (0.03, 0.02, 0.015), (0.5, 0.5, 0.5, 1)),
    ObjectSpec("lime block", "box", (0.04, 0.015, 0.015), (0.6, 0.9, 0.1, 1)),
    ObjectSpec("navy block", "box", (0.025, 0.02, 0.025), (0.05, 0.1, 0.4, 1)),
    ObjectSpec("black block", "box", (0.03, 0.017, 0.018), (0.08, 0.08, 0.08, 1)),
)

CONTAINERS: tuple[ContainerSpec, ...] = (
    ContainerSpec("plate", radius=0.075, wall_height=0.0, color=(0.95, 0.95, 0.95, 1)),
    ContainerSpec("bowl", radius=0.07, wall_height=0.035, color=(0.3, 0.55, 0.85, 1)),
)

TABLES: tuple[TableSpec, ...] = (
    TableSpec("wooden table", "maniskill_wood"),
    TableSpec("grey table", "box", color=(0.42, 0.45, 0.48, 1)),
)

TASK_FAMILIES: tuple[str, ...] = ("pick_place", "push", "pull", "move_to_aim")

INSTRUCTIONS: dict[str, str] = {
    "pick_place": "pick up the {object} and place it in the {container}",
    "push": "push the {object} forward",
    "pull": "pull the {object} back",
    "move_to_aim": "move the {object} onto the target carpet",
}

# OOD (paper, section 8.1): objects never seen in training, and seen objects in container combinations never
# seen in training. 2 objects x 2 containers x 2 tables + 4 objects x 1 container x 2 tables = 16 of 80 scenes.
OOD_OBJECTS: frozenset[str] = frozenset({"large pink ball", "gold can"})
OOD_COMBINATIONS: frozenset[tuple[str, str]] = frozenset(
    {("red cube", "bowl"), ("orange ball", "plate"), ("red can", "bowl"), ("brown block", "plate")}
)


@dataclass(frozen=True)
class Scene:
    object: ObjectSpec
    container: ContainerSpec
    table: TableSpec

    @property
    def id(self) -> str:
        return f"{self.object.slug}-{self.container.name}-{self.table.name.split()[0]}"

    @property
    def split(self) -> Literal["ind", "ood"]:
        held_out = self.object.name in OOD_OBJECTS or (self.object.name, self.container.name) in OOD_COMBINATIONS
        return "ood" if held_out else "ind"

    def instruction(self, family: str) -> str:
        if family not in INSTRUCTIONS:
            raise InvalidInputError(f"Unknown task family {family!r}; expected one of {TASK_FAMILIES}")
        return INSTRUCTIONS[family].format(object=self.object.name, container=self.container.name)


SCENES: tuple[Scene, ...] = tuple(Scene(o, c, t) for o in OBJECTS for c in CONTAINERS for t in TABLES)
_SCENES_BY_ID = {scene.id: scene for scene in SCENES}


def get_scene(scene_id: str) -> Scene:
    if scene_id not in _SCENES_BY_ID:
        raise InvalidInputError(
            f"Unknown scene {scene_id!r}; known scenes look like {SCENES[0].id!r} "
            "(see `roboscape-collect --list-scenes`)"
        )
    return _SCENES_BY_ID[scene_id]


def select_scenes(split: Literal["ind", "ood", "all"] = "all", scene_ids: list[str] | None = None) -> list[Scene]:
    """Scenes by explicit ids (in the given order) or by split."""
    if split not in ("ind", "ood", "all"):
        raise InvalidInputError(f"Unknown split {split!r}; expected 'ind', 'ood' or 'all'")
    scenes = [get_scene(s) for s in scene_ids] if scene_ids else list(SCENES)
    return [s for s in scenes if split == "all" or s.split == split]
