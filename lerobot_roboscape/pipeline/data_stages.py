"""The data stages: planner demonstrations, held-out, validation and exploratory collections, controllability sets
and a recorded ManiSkill trajectory file converted; each collected once into its folder under output_dir."""

import shutil
from dataclasses import dataclass, replace
from pathlib import Path

from lerobot.configs.default import DatasetConfig
from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

from lerobot_roboscape.dataset.convert import ConvertConfig, convert
from lerobot_roboscape.dataset.writer import missing_video_frames
from lerobot_roboscape.demos.collect import CollectConfig, collect, episodes_dir
from lerobot_roboscape.demos.controllability import ControllabilityConfig, collect_controllability
from lerobot_roboscape.demos.exploration import EXPLORATORY_KINDS
from lerobot_roboscape.demos.record import record_maniskill_trajectories
from lerobot_roboscape.pipeline.config import DataConfig
from lerobot_roboscape.pipeline.layout import (
    CONTROL_DIR,
    CONTROL_IND_DIR,
    CONVERTED_DIR,
    DEMOS_DIR,
    DEMOS_REPO_ID,
    EXPLORE_DIR,
    EXPLORE_REPO_ID,
    HELDOUT_DIR,
    INITIAL_SCENE_DIR,
    INITIAL_SCENE_REPO_ID,
    TRAJECTORIES_DIR,
    VALIDATION_DIR,
)
from lerobot_roboscape.pipeline.methods import initial_scene
from lerobot_roboscape.pipeline.resume import is_done, mark_done, run_once, start
from lerobot_roboscape.tasks import select_scenes
from roboscape_core.errors import InvalidInputError

HELDOUT_SEED = 50_000  # held-out episodes get initial states that the training collection (seeds from 0) lacks
VALIDATION_SEED = 60_000  # so do the validation episodes the done threshold is chosen on
CONTROL_SEED = 70_000  # and the starts of the controllability set
CONTROL_IND_SEED = 75_000  # and those of its twin in the training scenes
EXPLORE_SEED = 80_000  # and the exploratory episodes
INITIAL_SCENE_SEED = 300_000  # and the initial scene's own demonstrations, beyond the evaluations' (100,000, 200,000)


# ---- data --------------------------------------------------------------------------------------------------------


@dataclass
class Datasets:
    """train: the demonstrations (IND scenes; successful, suboptimal and failed attempts). heldout: episodes the
    models never saw, for the fidelity and reward reports (OOD scenes, half failed; or one converted episode).
    validation: episodes the done threshold is chosen on (IND scenes, new initial states, half failed; the
    demonstrations themselves at the scales without held-out scenes). controllability: K action sequences from
    each of some OOD starts (demos/controllability.py), or None; controllability_ind: the same from new initial
    states of the training scenes (where RL runs, so where the world model must first be faithful), or None.
    trajectory_file: the recorded ManiSkill .h5 that
    `roboscape-convert` read. exploration: exploratory episodes in the IND scenes (demos/exploration.py) for the
    action world model only, or None."""

    train: DatasetConfig
    heldout: DatasetConfig
    validation: DatasetConfig
    controllability: DatasetConfig | None
    trajectory_file: Path
    exploration: DatasetConfig | None = None
    controllability_ind: DatasetConfig | None = None


def _collect(cfg: CollectConfig, fresh: bool) -> DatasetConfig:
    folder = Path(cfg.root)
    if fresh:
        shutil.rmtree(episodes_dir(folder), ignore_errors=True)
    # a killed collection continues from the episodes it saved (its planned jobs must match, or collect says so)
    run_once(folder, cfg, fresh, lambda: collect(replace(cfg, overwrite=True, resume=True)))
    return whole_dataset(DatasetConfig(repo_id=cfg.repo_id, root=str(folder)))


def whole_dataset(dataset: DatasetConfig) -> DatasetConfig:
    """`dataset`, once its videos hold every frame: a dataset found complete may come from a writer that dropped
    frames (LeRobot's streaming encoder did, before dataset/writer.py stopped it), which shifts later frames
    against their actions."""
    if missing := missing_video_frames(LeRobotDatasetMetadata(dataset.repo_id, root=dataset.root)):
        raise InvalidInputError(
            f"{dataset.root}: videos short of their episodes' frames ({'; '.join(missing)}); delete it and run again "
            "to collect it again"
        )
    return dataset


def _unseen_episodes(
    data: DataConfig, fresh: bool, root: Path, split: str, scenes: int | None, per_scene: int, seed: int
) -> DatasetConfig:
    """Episodes no model trains on, from initial states the demonstrations lack: half of them failed attempts,
    with the object's masks (the held-out and the validation collections)."""
    return _collect(
        CollectConfig(
            repo_id=f"local/{root.name}",
            root=str(root),
            families=data.families,
            split=split,
            max_scenes=scenes,
            episodes_per_scene=per_scene,
            failed_fraction=0.5,
            seed=seed,
            image_size=data.image_size,
            workers=data.workers,
            keep_failed=True,
            segmentation=True,
        ),
        fresh,
    )


def _controllability(
    data: DataConfig, fresh: bool, root: Path, split: str, scenes: int | None, seed: int, starts_per_scene: int = 2
) -> DatasetConfig:
    """A controllability set (K action sequences from each start) in the scenes of `split`."""
    control = ControllabilityConfig(
        repo_id=f"local/{root.name}",
        root=str(root),
        families=data.families,
        split=split,
        max_scenes=scenes,
        starts_per_scene=starts_per_scene,
        seed=seed,
        image_size=data.image_size,
        workers=data.workers,
        overwrite=True,
    )
    if fresh:
        shutil.rmtree(episodes_dir(root), ignore_errors=True)
    # a killed collection continues from the starts it saved
    run_once(root, control, fresh, lambda: collect_controllability(replace(control, resume=True)))
    return whole_dataset(DatasetConfig(repo_id=control.repo_id, root=control.root))


def initial_scene_demonstrations(data: DataConfig, out: Path, fresh: bool = False) -> DatasetConfig:
    """What the paper protocol's SFT imitates: `data.initial_scene_episodes` planner attempts per family in the
    initial scene, half of them suboptimal, the successful ones kept. The demonstrations hold about 16 per family
    and scene, too few to learn one scene from (docs/results/claim_paper)."""
    return _collect(
        CollectConfig(
            repo_id=INITIAL_SCENE_REPO_ID,
            root=str(out / INITIAL_SCENE_DIR),
            families=data.families,
            scenes=[initial_scene()],
            episodes_per_scene=data.initial_scene_episodes,
            failed_fraction=0.0,
            suboptimal_fraction=0.5,
            seed=INITIAL_SCENE_SEED,
            image_size=data.image_size,
            workers=data.workers,
            keep_failed=False,
        ),
        fresh,
    )


def demonstrations(data: DataConfig, out: Path, fresh: bool = False) -> Datasets:
    """Planner demonstrations in the IND scenes, a recorded ManiSkill trajectory file converted to a LeRobotDataset
    and, at the scales with held-out scenes, a held-out collection in OOD scenes, a validation collection in IND
    scenes and a controllability set from OOD starts."""
    train = _collect(
        CollectConfig(
            repo_id=DEMOS_REPO_ID,
            root=str(out / DEMOS_DIR),
            families=data.families,
            split="ind",
            max_scenes=data.max_scenes,
            episodes_per_scene=data.episodes_per_scene,
            image_size=data.image_size,
            workers=data.workers,
            keep_failed=True,
            segmentation=True,
        ),
        fresh,
    )
    family, scene = data.families[0], select_scenes("ind")[0].id
    record = {"family": family, "scene": scene, "image_size": data.image_size, "seed": HELDOUT_SEED}
    converted = out / CONVERTED_DIR
    h5_dir = out / TRAJECTORIES_DIR
    if not is_done(converted, record, fresh):
        start(h5_dir)
        h5 = record_maniskill_trajectories(
            h5_dir, family, scene, episodes=1, image_size=data.image_size, seed=HELDOUT_SEED
        )
        start(converted)
        convert(ConvertConfig(h5=str(h5), root=str(converted), repo_id="local/maniskill_converted", overwrite=True))
        mark_done(converted, record)
    h5 = next(h5_dir.glob("*.h5"))
    heldout = DatasetConfig(repo_id="local/maniskill_converted", root=str(converted))
    validation, controllability, controllability_ind = train, None, None
    if data.heldout_scenes:
        heldout = _unseen_episodes(data, fresh, out / HELDOUT_DIR, "ood", data.heldout_scenes, 4, HELDOUT_SEED)
        validation = _unseen_episodes(data, fresh, out / VALIDATION_DIR, "ind", data.max_scenes, 1, VALIDATION_SEED)
        controllability = _controllability(data, fresh, out / CONTROL_DIR, "ood", data.heldout_scenes, CONTROL_SEED)
    if data.heldout_scenes and data.ind_control_starts:
        # New initial states of the training scenes: where RL runs, the world model is judged first.
        controllability_ind = _controllability(
            data, fresh, out / CONTROL_IND_DIR, "ind", data.max_scenes, CONTROL_IND_SEED, data.ind_control_starts
        )
    exploration = None
    if data.explore_episodes_per_scene:
        exploration = _collect(
            CollectConfig(
                repo_id=EXPLORE_REPO_ID,
                root=str(out / EXPLORE_DIR),
                families=data.families,
                split="ind",
                max_scenes=data.max_scenes,
                episodes_per_scene=data.explore_episodes_per_scene,
                kinds=list(EXPLORATORY_KINDS),
                seed=EXPLORE_SEED,
                image_size=data.image_size,
                workers=data.workers,
                keep_failed=True,
            ),
            fresh,
        )
    return Datasets(train, heldout, validation, controllability, h5, exploration, controllability_ind)
