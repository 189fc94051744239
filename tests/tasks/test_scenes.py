from lerobot_roboscape.tasks.scenes import (
    CONTAINERS,
    OBJECTS,
    OOD_OBJECTS,
    SCENES,
    TABLES,
    TASK_FAMILIES,
    get_scene,
    select_scenes,
)


def test_catalogue_matches_paper_scale():
    assert len(OBJECTS) >= 10 and len(CONTAINERS) == 2 and len(TABLES) == 2
    assert len(SCENES) == len(OBJECTS) * len(CONTAINERS) * len(TABLES)
    assert len({o.shape for o in OBJECTS}) >= 3 and len({o.color for o in OBJECTS}) == len(OBJECTS)
    assert len({scene.id for scene in SCENES}) == len(SCENES)


def test_ood_split_holds_unseen_objects_and_unseen_combinations():
    ood = select_scenes("ood")
    ind = select_scenes("ind")
    assert 0.15 <= len(ood) / len(SCENES) <= 0.25
    ind_objects = {s.object.name for s in ind}
    assert OOD_OBJECTS.isdisjoint(ind_objects)
    combos_ind = {(s.object.name, s.container.name) for s in ind}
    unseen_combos = [s for s in ood if s.object.name in ind_objects]
    assert unseen_combos, "OOD must include seen objects in unseen combinations"
    assert all((s.object.name, s.container.name) not in combos_ind for s in unseen_combos)


def test_instructions_name_object_and_container():
    scene = get_scene("red_cube-plate-wooden")
    assert scene.instruction("pick_place") == "pick up the red cube and place it in the plate"
    assert all(scene.object.name in scene.instruction(f) for f in TASK_FAMILIES)


def test_unknown_scene_is_named():
    import pytest

    with pytest.raises(ValueError, match="no_such_scene"):
        get_scene("no_such_scene")
