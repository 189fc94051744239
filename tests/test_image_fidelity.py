import math

import numpy as np
import torch

from lerobot_roboscape.dataset.segmentation import OBJECT
from lerobot_roboscape.metrics.image_fidelity import codebook_use, dilate, frame_measures, summarise

TABLE, CUBE = torch.tensor([0.6, 0.4, 0.2]), torch.tensor([0.8, 0.1, 0.1])


def scene(cube_pixels: int = 7) -> tuple[torch.Tensor, torch.Tensor]:
    """A 64 px table with a red square of `cube_pixels` per side: (1, 3, 64, 64) image, (1, 64, 64) labels."""
    image = TABLE[:, None, None].expand(3, 64, 64).clone()
    labels = torch.zeros(64, 64, dtype=torch.uint8)
    image[:, 20 : 20 + cube_pixels, 30 : 30 + cube_pixels] = CUBE[:, None, None]
    labels[20 : 20 + cube_pixels, 30 : 30 + cube_pixels] = OBJECT
    return image[None], labels[None]


def test_erasing_a_small_object_barely_moves_whole_frame_psnr_but_is_seen():
    real, labels = scene()
    erased = TABLE[:, None, None].expand(1, 3, 64, 64) + 0.01  # the table everywhere, slightly off
    kept = real + 0.03 * torch.randn_like(real)
    e, k = frame_measures(erased, real, labels), frame_measures(kept, real, labels)
    # The whole frame hardly tells them apart; the object measures do.
    assert e["psnr"][0] > 20 and abs(e["psnr"][0] - k["psnr"][0]) < 12
    assert e["object_survives"][0] == 0 and k["object_survives"][0] == 1
    assert e["object_psnr"][0] < 17 < 25 < k["object_psnr"][0]  # 17 dB: the colours differ by about 0.2
    assert e["object_pixels"][0] == 49


def test_an_object_under_four_pixels_is_not_judged():
    real, labels = scene(cube_pixels=1)
    measures = frame_measures(real, real, labels)
    assert math.isnan(measures["object_psnr"][0]) and math.isnan(measures["object_survives"][0])
    summary = summarise(measures)
    assert summary["object_frames"] == 0 and summary["object_psnr"] is None and summary["frames"] == 1


def test_dilation_grows_a_pixel_into_a_square():
    mask = torch.zeros(1, 9, 9, dtype=torch.bool)
    mask[0, 4, 4] = True
    assert dilate(mask, 1).sum() == 9 and dilate(mask, 2).sum() == 25 and dilate(mask, 0).sum() == 1


def test_codebook_use_and_perplexity():
    uniform = codebook_use(torch.arange(16).repeat(4), 64)
    assert uniform["used"] == 16 and uniform["share_used"] == 0.25
    assert np.isclose(uniform["perplexity"], 16)
    assert np.isclose(codebook_use(torch.zeros(100, dtype=torch.long), 64)["perplexity"], 1)


def test_survival_is_also_given_by_the_objects_size():
    measures = {
        "psnr": np.zeros(4),
        "object_psnr": np.zeros(4),
        "object_survives": np.array([1.0, 0.0, 1.0, np.nan]),
        "object_pixels": np.array([5, 10, 100, 2]),
    }
    by_size = summarise(measures)["object_survival_by_size"]
    assert by_size == {
        "4-15 px": {"frames": 2, "survival": 0.5},
        "16-63 px": {"frames": 0, "survival": None},
        ">= 64 px": {"frames": 1, "survival": 1.0},
    }
