import logging

import lpips
import pytest
import torch
import torchvision
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_roboscape.dataset.reader import episode_indices, read_episode
from lerobot_roboscape.metrics.perceptual import TRUNK_FILES, LPIPSTrunkMissingError
from lerobot_roboscape.tokenizer.configuration_tokenizer import TinyTokenizerConfig
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.tokenizer.similarity import PixelDistance, TokenizerPerceptualDistance, load_similarity
from tests.conftest import IMAGE_SIZE, TEST_TOKENIZER


def random_tokenizer() -> VisualTokenizer:
    torch.manual_seed(0)
    return VisualTokenizer(TinyTokenizerConfig(**TEST_TOKENIZER))


def test_distance_to_the_last_frame_grows_with_the_steps_before_it(demo_dataset, trained_tokenizer):
    _, root = demo_dataset
    dataset = LeRobotDataset("test/demos", root=root)
    metric = TokenizerPerceptualDistance(VisualTokenizer.from_pretrained(trained_tokenizer))
    rows = []  # per episode and camera: distance to the goal (the last frame) of frames T-1, T-6, T-16 and 0
    for episode in episode_indices(dataset):
        for frames_THWC in read_episode(dataset, episode).images.values():
            x = torch.from_numpy(frames_THWC).permute(0, 3, 1, 2).float() / 255 * 2 - 1
            T = len(x)
            picks = x[[T - 1, T - 6, T - 16, 0]]
            rows.append(metric(picks, x[T - 1].expand_as(picks)).flatten())
    d = torch.stack(rows)
    assert d[:, 0].abs().max() < 1e-6
    # The robot rests only for the last few (settle) steps, so 5 steps before the end the view has changed.
    assert (d[:, 1] > 0.01).all(), d
    # Single views need not be monotonic (the wrist camera can look alike far apart), their average is.
    mean = d.mean(0)
    assert mean[1] < mean[2] < mean[3], mean


def test_a_random_tokenizer_still_gives_a_metric():
    tokenizer = random_tokenizer()
    metric = TokenizerPerceptualDistance(tokenizer)
    assert metric.name == "tokenizer" and not any(p.requires_grad for p in metric.parameters())
    assert all(p.requires_grad for p in tokenizer.parameters())  # the metric froze its own copy
    g = torch.Generator().manual_seed(1)
    images = torch.rand(4, 3, IMAGE_SIZE, IMAGE_SIZE, generator=g) * 2 - 1
    noise = torch.randn(images.shape, generator=g)
    d = [metric(images, (images + amplitude * noise).clamp(-1, 1)) for amplitude in (0.0, 0.05, 0.2, 0.8)]
    assert d[0].shape == (4, 1, 1, 1) and d[0].abs().max() < 1e-6
    assert (d[1] > 0).all() and (d[1] < d[2]).all() and (d[2] < d[3]).all() and (d[3] <= 1).all()
    other = (images + 0.2 * noise).clamp(-1, 1)
    assert torch.equal(metric(images, other), metric(other, images))


def test_pixel_distance_is_the_scaled_mean_squared_difference():
    metric = load_similarity("pixel", None)
    assert isinstance(metric, PixelDistance) and metric.name == "pixel"
    black, white = -torch.ones(2, 3, 8, 8), torch.ones(2, 3, 8, 8)
    half = black.clone()
    half[..., :4] = 1  # half of every image's pixels flipped from black to white
    assert metric(black, black).flatten().tolist() == [0.0, 0.0]
    assert metric(black, white).flatten().tolist() == [1.0, 1.0]  # the farthest two images in [-1, 1] are
    assert metric(black, half).flatten().tolist() == [0.5, 0.5]


def test_auto_picks_lpips_only_when_its_weights_are_found(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))  # an empty torch hub cache
    tokenizer = random_tokenizer()
    with caplog.at_level(logging.INFO, logger="lerobot_roboscape.tokenizer.similarity"):
        metric = load_similarity("auto", tokenizer)
    assert isinstance(metric, TokenizerPerceptualDistance) and "tokenizer features" in caplog.text
    with pytest.raises(LPIPSTrunkMissingError):
        load_similarity("lpips", tokenizer)
    assert load_similarity("lpips", tokenizer, allow_random_lpips=True).name == (
        "lpips (alex, random trunk: not perceptual)"
    )

    weights = tmp_path / "alexnet.pth"
    torch.save(torchvision.models.alexnet().state_dict(), weights)
    metric = load_similarity("auto", tokenizer, "alex", weights)
    assert isinstance(metric, lpips.LPIPS) and metric.name == "lpips (alex)"
    with pytest.raises(LPIPSTrunkMissingError, match="not found"):  # a named file that is missing is no fallback
        load_similarity("auto", tokenizer, "alex", tmp_path / "missing.pth")
    (tmp_path / "hub" / "checkpoints").mkdir(parents=True)
    weights.rename(tmp_path / "hub" / "checkpoints" / TRUNK_FILES["alex"])
    assert load_similarity("auto", tokenizer).name == "lpips (alex)"


def test_bad_choices_are_named():
    with pytest.raises(ValueError, match="similarity must be one of.*'ssim'"):
        load_similarity("ssim", random_tokenizer())
    with pytest.raises(ValueError, match="needs a trained tokenizer"):
        load_similarity("tokenizer", None)
