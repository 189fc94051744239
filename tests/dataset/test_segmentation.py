import numpy as np
import pytest
import torch

from lerobot_roboscape.dataset.episode import Episode
from lerobot_roboscape.dataset.reader import CameraFrames, FrameBank, read_episode
from lerobot_roboscape.dataset.segmentation import CONTAINER, OBJECT, ROBOT, has_masks, mask_path, read_masks
from lerobot_roboscape.dataset.writer import write_dataset
from roboscape_core.errors import InvalidInputError
from tests.dataset import still_episode

CAMERAS = ["third_view", "wrist"]


def test_masks_are_stored_beside_the_dataset_and_mark_the_red_cube(demo_dataset):
    ds, root = demo_dataset
    assert has_masks(root)
    for index in range(ds.meta.total_episodes):
        episode = read_episode(ds, index)
        masks = read_masks(root, index, CAMERAS, len(episode.action))
        for camera in CAMERAS:
            labels, images = masks[camera], episode.images[camera]
            assert labels.shape == images.shape[:3] and labels.dtype == np.uint8
            assert set(np.unique(labels)) <= {0, OBJECT, CONTAINER, ROBOT}
        # The third view sees the object on the table at the start; its pixels are the red cube's (the video's
        # compression blurs its outline, so only the pixels well inside the mask are compared).
        third = masks["third_view"][0] == OBJECT
        assert third.sum() >= 2
        object_colour = episode.images["third_view"][0][third].mean(0)
        # the rest of the view (the table, the container and the arm, now labelled on its own)
        background = episode.images["third_view"][0][masks["third_view"][0] != OBJECT].mean(0)
        assert (masks["third_view"][0] == ROBOT).sum() >= 20  # the arm is in view and labelled
        assert object_colour[0] > object_colour[1] + 40 and object_colour[0] > object_colour[2] + 40, object_colour
        assert np.abs(object_colour - background).sum() > 60


def test_frame_bank_holds_frames_with_their_masks(demo_dataset):
    ds, root = demo_dataset
    bank = FrameBank.load(ds, masks=True, stride=3)
    lengths = [ds.meta.episodes[i]["length"] for i in range(ds.meta.total_episodes)]
    assert len(bank) == sum(len(range(0, n, 3)) for n in lengths)
    assert bank.images.shape[1:] == (2, 32, 32, 3) and bank.masks.shape == bank.images.shape[:-1]
    k = int(np.flatnonzero(bank.episode_index == 1)[1])  # episode 1, frame 3
    assert bank.frame_index[k] == 3
    assert np.array_equal(bank.masks[k, 1].numpy(), read_masks(root, 1, CAMERAS, lengths[1])["wrist"][3])


def test_a_missing_or_wrong_mask_file_is_named(demo_dataset, tmp_path):
    _, root = demo_dataset
    with pytest.raises(InvalidInputError, match="episode_000000.npy is missing"):
        read_masks(tmp_path, 0, ["wrist"], 5)
    path = mask_path(tmp_path, "wrist", 0)
    path.parent.mkdir(parents=True)
    np.save(path, np.zeros((4, 8, 8), np.uint8))
    with pytest.raises(InvalidInputError, match=r"episode_000000.npy: expected \(5, H, W\)"):
        read_masks(tmp_path, 0, ["wrist"], 5)


def _episode(masks: bool, n: int = 3) -> Episode:
    return still_episode(
        {"wrist": np.zeros((n, 32, 32, 3), np.uint8)}, {"wrist": np.ones((n, 32, 32), np.uint8)} if masks else None
    )


def test_episode_masks_round_trip_and_are_checked(tmp_path):
    episode = _episode(masks=True)
    episode.save(tmp_path / "e.npz")
    loaded = Episode.load(tmp_path / "e.npz")
    assert np.array_equal(loaded.masks["wrist"], episode.masks["wrist"])
    assert _episode(masks=False).masks is None
    episode.masks["wrist"] = episode.masks["wrist"][:2]
    with pytest.raises(InvalidInputError, match="here: masks of camera 'wrist' must be"):
        episode.validate("here")


def test_a_dataset_has_masks_for_every_episode_or_none(tmp_path):
    with pytest.raises(InvalidInputError, match="episode 1 for .* has no segmentation masks"):
        write_dataset([_episode(True), _episode(False)], "test/mixed", tmp_path / "mixed", fps=20)
    assert not (tmp_path / "mixed").exists()  # nothing half-written


def test_streamed_frames_carry_the_same_masks_as_the_bank(demo_dataset):
    ds, _ = demo_dataset
    bank = FrameBank.load(ds, masks=True)
    streamed = CameraFrames(ds, masks=True)
    for i in (0, len(bank) // 2, len(bank) - 1):
        item = streamed[i]
        assert item["images"].shape == (2, 3, 32, 32)
        assert torch.equal(item["masks"], bank.masks[i])
