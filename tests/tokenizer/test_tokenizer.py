import shutil

import imageio.v3 as iio
import numpy as np
import pytest
import torch
import torchvision
from lerobot.configs.default import DatasetConfig
from safetensors.torch import save_file

from lerobot_roboscape.dataset.reader import DatasetError, FrameBank
from lerobot_roboscape.dataset.segmentation import OBJECT
from lerobot_roboscape.metrics.perceptual import LPIPSTrunkMissingError, load_lpips
from lerobot_roboscape.tokenizer.configuration_tokenizer import PaperTokenizerConfig, TinyTokenizerConfig
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.tokenizer.report import TokenizerReportConfig, evaluate_tokenizer
from lerobot_roboscape.tokenizer.train import BankBatches, TrainTokenizerConfig, shift_hue, train_tokenizer, with_hue
from tests.conftest import TEST_TOKENIZER


def make_tokenizer(**overrides):
    torch.manual_seed(0)
    return VisualTokenizer(TinyTokenizerConfig(**{**TEST_TOKENIZER, **overrides})).eval()


def test_presets_give_the_documented_grids():
    assert TinyTokenizerConfig().tokens_per_side == 8 and TinyTokenizerConfig().codebook_size == 256
    assert PaperTokenizerConfig().tokens_per_side == 16 and PaperTokenizerConfig().codebook_size == 4096


def test_encode_decode_round_trip_through_indices():
    tok = make_tokenizer()
    images = torch.rand(3, 3, 32, 32)
    out = tok(images)
    indices = tok.encode(images)
    assert indices.shape == (3, 4, 4) and indices.dtype == torch.long
    assert indices.min() >= 0 and indices.max() < 64
    assert torch.equal(indices, out.indices)
    # The codes recovered from the indices are exactly the quantised latents, so decoding them reproduces forward().
    assert torch.allclose(tok.decode(indices), out.reconstruction.clamp(0, 1), atol=1e-5)


def test_uint8_input_equals_float_input():
    tok = make_tokenizer()
    images = torch.randint(0, 256, (2, 3, 32, 32), dtype=torch.uint8)
    assert torch.equal(tok.encode(images), tok.encode(images.float() / 255))


def test_save_load_round_trip(tmp_path):
    tok = make_tokenizer()
    tok.save_pretrained(tmp_path)
    loaded = VisualTokenizer.from_pretrained(tmp_path).eval()
    assert loaded.config.channel_multipliers == (1, 2, 2, 2)
    images = torch.rand(2, 3, 32, 32)
    assert torch.equal(loaded.encode(images), tok.encode(images))


def test_overfits_a_batch():
    tok = make_tokenizer().train()
    g = torch.Generator().manual_seed(1)
    images = torch.rand(4, 3, 1, 1, generator=g).expand(4, 3, 32, 32).contiguous()  # flat colours: quick to learn
    opt = torch.optim.Adam(tok.parameters(), 3e-3)
    first = None
    for _ in range(120):
        loss, logs = tok.compute_loss(images)
        first = first or logs["l1"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert logs["l1"] < first / 3


def test_bad_inputs_are_named():
    tok = make_tokenizer()
    with pytest.raises(ValueError, match=r"\(B, 3, 32, 32\).*\(2, 3, 64, 64\)"):
        tok.encode(torch.rand(2, 3, 64, 64))
    with pytest.raises(ValueError, match="token ids must be in"):
        tok.decode(torch.full((1, 4, 4), 64))
    with pytest.raises(ValueError, match="divisible"):
        TinyTokenizerConfig(image_size=36)


def test_lpips_trunk_loads_from_a_file_and_is_refused_when_missing(tmp_path):
    trunk = torchvision.models.alexnet()
    path = tmp_path / "alexnet.safetensors"
    save_file(trunk.state_dict(), path)
    metric = load_lpips("alex", trunk_path=path)
    assert not metric.random_trunk
    assert torch.equal(metric.net.slice1[0].weight, trunk.features[0].weight)
    assert torch.equal(getattr(metric.net.slice5, "10").weight, trunk.features[10].weight)
    with pytest.raises(LPIPSTrunkMissingError, match="not found"):
        load_lpips("alex", trunk_path=tmp_path / "missing.pth")
    random_metric = load_lpips("alex", trunk_path=None, allow_random_trunk=True)  # tests only: said so by the flag
    assert random_metric.random_trunk
    # The same random trunk in every process, whatever the caller drew before, and the caller's stream untouched.
    torch.manual_seed(123)
    state = torch.random.get_rng_state()
    again = load_lpips("alex", trunk_path=None, allow_random_trunk=True)
    assert torch.equal(torch.random.get_rng_state(), state)
    assert torch.equal(again.net.slice1[0].weight, random_metric.net.slice1[0].weight)
    image, other = torch.rand(2, 1, 3, 32, 32) * 2 - 1
    assert random_metric(image, image).item() == pytest.approx(0.0, abs=1e-6)
    assert random_metric(image, other).item() > 0


def test_object_weight_adds_the_error_on_the_objects_pixels():
    images = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(2))
    masks = torch.zeros(2, 32, 32, dtype=torch.uint8)
    masks[:, 10:13, 10:13] = OBJECT  # 3x3, dilated by a pixel to 5x5
    plain, _ = make_tokenizer().compute_loss(images, masks=masks)
    weighted_model = make_tokenizer(object_weight=10.0)  # same seed: the same weights
    weighted, logs = weighted_model.compute_loss(images, masks=masks)
    error = (weighted_model(images).reconstruction - images).abs().mean(1)[:, 9:14, 9:14]
    assert torch.isclose(weighted - plain, 10 * error.sum() / (2 * 32 * 32), rtol=1e-4)
    assert logs["object_l1"] == pytest.approx(error.mean().item(), rel=1e-4)
    with pytest.raises(ValueError, match="needs the frames' segmentation masks"):
        weighted_model.compute_loss(images)


def test_training_with_object_weight_needs_a_dataset_with_masks(demo_dataset, tmp_path):
    _, root = demo_dataset
    unmasked = tmp_path / "unmasked"
    shutil.copytree(root, unmasked, ignore=shutil.ignore_patterns("segmentation", "roboscape_segmentation.json"))
    cfg = TrainTokenizerConfig(
        dataset=DatasetConfig(repo_id="test/demos", root=str(unmasked)),
        tokenizer=TinyTokenizerConfig(**TEST_TOKENIZER, object_weight=5.0),
        output_dir=tmp_path / "out",
    )
    missing = r"object_weight=5.0 needs .* \(meta/roboscape_segmentation.json is missing\)"
    with pytest.raises(DatasetError, match=missing):
        train_tokenizer(cfg)


def test_report_measures_the_object_per_view_and_plots_the_training_curve(demo_dataset, trained_tokenizer, tmp_path):
    _, root = demo_dataset
    report = evaluate_tokenizer(
        TokenizerReportConfig(
            dataset=DatasetConfig(repo_id="test/demos", root=str(root), episodes=[0, 4]),
            tokenizer=str(trained_tokenizer),
            output_dir=tmp_path,
            training_dir=trained_tokenizer.parent,
            columns=2,
        )
    )
    for name in ("tokenizer_report.json", "tokenizer_report.md", "reconstruction.png", "heldout_curve.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert report["episodes"] == 2
    for view in ("third_view", "wrist"):
        m = report["views"][view]
        assert 0 < m["object_frames"] <= m["frames"]
        assert 0 <= m["object_survival"] <= 1 and 0 <= m["picture_object_survives"] <= 1
        assert 5 < m["psnr"] < 60 and 0 < m["object_psnr"] < 60
        assert 0 < m["codebook"]["share_used"] <= 1 and 1 <= m["codebook"]["perplexity"] <= 64
    # The training fixture measured its held-out episodes every 4 of its 8 steps.
    assert [p["step"] for p in report["curve"]] == [4, 8]
    assert all(5 < p["wrist/psnr"] < 60 for p in report["curve"])
    picture = iio.imread(tmp_path / "reconstruction.png")
    assert picture.shape == (4 * 32 * 3, 2 * 32 * 3, 3)  # (real, reconstructed) x 2 views by 2 columns, at 3x


def test_hue_augmentation_rotates_colours_and_shifts_a_frames_views_alike():
    red = torch.zeros(2, 3, 4, 4)
    red[:, 0] = 1
    shifted = shift_hue(red, torch.tensor([0.5, 0.0]))
    assert torch.allclose(shifted[0, :, 0, 0], torch.tensor([0.0, 1.0, 1.0]), atol=1e-3)  # red -> cyan
    assert torch.equal(shifted[1], red[1])
    bank = FrameBank(torch.zeros(5, 2, 4, 4, 3, dtype=torch.uint8), None, np.zeros(5), np.arange(5))
    batches = with_hue(BankBatches(bank, batch_size=3, seed=0), hue_shift=0.2, seed=0)
    hue = batches(7)["hue"]
    assert hue.shape == (6,) and torch.equal(hue[0::2], hue[1::2]) and hue.abs().max() <= 0.2
    assert torch.equal(hue, batches(7)["hue"]) and not torch.equal(hue, batches(8)["hue"])
