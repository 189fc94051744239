import json
import shutil

import numpy as np
import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_roboscape.dataset.reader import DatasetError, open_dataset
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.tokenizer.token_cache import (
    TokenCacheMismatchError,
    dataset_fingerprint,
    export_token_cache,
    import_token_cache,
    load_or_build_token_cache,
    open_token_cache,
    tokenizer_fingerprint,
)


def test_cache_holds_every_frame_with_labels(demo_dataset, trained_tokenizer, token_cache):
    dataset, root = demo_dataset
    assert token_cache.tokens.shape == (dataset.num_frames, 2, 4, 4)
    assert isinstance(token_cache.tokens, np.memmap)
    assert token_cache.cameras == ["third_view", "wrist"] and token_cache.vocab_size == 64
    tokenizer = VisualTokenizer.from_pretrained(trained_tokenizer).eval()
    row = token_cache.episodes[1]
    frame = dataset[row["start"] + 3]["observation.images.wrist"]
    cached = torch.from_numpy(token_cache.tokens[row["start"] + 3, 1].astype(np.int64))
    assert torch.equal(tokenizer.encode(frame[None])[0], cached)
    np.testing.assert_array_equal(
        token_cache.actions[row["start"] : row["start"] + row["length"]],
        np.stack([dataset[row["start"] + t]["action"].numpy() for t in range(row["length"])]),
    )
    for row in token_cache.episodes:
        done = token_cache.done[row["start"] : row["start"] + row["length"]]
        assert done[0] == 0 and (done.max() == 1) == row["success"]


def test_cache_is_reused_and_rebuilt_when_an_input_changes(demo_dataset, trained_tokenizer, token_cache, tmp_path):
    dataset, root = demo_dataset
    tokenizer = VisualTokenizer.from_pretrained(trained_tokenizer)
    again = load_or_build_token_cache(dataset, tokenizer, token_cache.root.parent)
    assert again.root == token_cache.root
    with torch.no_grad():
        tokenizer.decoder.layers[0].weight.add_(1.0)
    other = load_or_build_token_cache(dataset, tokenizer, token_cache.root.parent)
    assert other.root != token_cache.root
    with pytest.raises(TokenCacheMismatchError, match="different tokenizer"):
        open_token_cache(token_cache.root, dataset_fingerprint(root), tokenizer_fingerprint(tokenizer))


def test_dataset_fingerprint_reads_the_dataset_not_what_lies_beside_it(demo_dataset, tmp_path):
    _, root = demo_dataset
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    fingerprint = dataset_fingerprint(copy)
    (copy / "stage.json").write_text('{"seconds": 12.5}')  # a pipeline's record of the run that wrote it
    assert dataset_fingerprint(copy) == fingerprint
    info = json.loads((copy / "meta" / "info.json").read_text())
    (copy / "meta" / "info.json").write_text(json.dumps(info | {"fps": info["fps"] + 1}))
    assert dataset_fingerprint(copy) != fingerprint


def test_mismatched_or_broken_cache_is_named(token_cache, demo_dataset, tmp_path):
    with pytest.raises(TokenCacheMismatchError, match="different dataset"):
        open_token_cache(token_cache.root, dataset_fp="0" * 64)
    with pytest.raises(TokenCacheMismatchError, match="not a token cache"):
        open_token_cache(tmp_path)
    broken = tmp_path / "broken"
    shutil.copytree(token_cache.root, broken)
    manifest = json.loads((broken / "manifest.json").read_text())
    manifest["num_frames"] += 1
    (broken / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(TokenCacheMismatchError, match="tokens.npy has"):
        open_token_cache(broken)


def test_missing_or_empty_dataset_is_named(tmp_path):
    with pytest.raises(DatasetError, match="no LeRobot dataset at"):
        open_dataset("test/none", tmp_path / "nothing")
    features = {
        "observation.images.wrist": {"dtype": "video", "shape": (32, 32, 3), "names": ["height", "width", "channels"]},
        "action": {"dtype": "float32", "shape": (7,), "names": None},
    }
    LeRobotDataset.create("test/empty", fps=20, root=tmp_path / "empty", features=features).finalize()
    with pytest.raises(DatasetError, match="has no episodes"):
        open_dataset("test/empty", tmp_path / "empty")


def test_exported_cache_travels_whole_and_trains_without_its_dataset(
    demo_dataset, trained_tokenizer, token_cache, tmp_path
):
    """export -> import gives the cache back array for array, with its dataset's action statistics; the world model
    trained on it with no dataset at hand is the one trained on the original."""
    import draccus

    from lerobot_roboscape.training.checkpoints import FINAL
    from lerobot_roboscape.world_model.train import TrainWorldModelConfig, train_world_model
    from tests.harness import assert_same_weights
    from tests.world_model.test_training import train_args

    dataset, _ = demo_dataset
    stats = {key: dataset.meta.stats[key] for key in ("action", "observation.state")}
    size = export_token_cache(token_cache, tmp_path / "cache.xz", stats)
    raw = sum(getattr(token_cache, name).nbytes for name in ("tokens", "actions", "states", "done", "rewards"))
    assert size == (tmp_path / "cache.xz").stat().st_size < raw
    imported = open_token_cache(import_token_cache(tmp_path / "cache.xz", tmp_path / "there"))
    assert imported.root.name == token_cache.root.name and imported.manifest == token_cache.manifest
    assert imported.episodes == token_cache.episodes
    for name in ("tokens", "actions", "states", "done", "rewards"):
        assert np.array_equal(getattr(imported, name), getattr(token_cache, name)), name
    args = [
        *train_args(demo_dataset, trained_tokenizer, token_cache, tmp_path / "here", steps=3),
        "--done_tuning_steps=0",
    ]
    train_world_model(draccus.parse(TrainWorldModelConfig, args=args))
    away = [a.replace(str(token_cache.root), str(imported.root)) for a in args if not a.startswith("--dataset.root")]
    away = [a.replace(str(tmp_path / "here"), str(tmp_path / "away")) for a in away] + [
        f"--dataset.root={tmp_path}/none"
    ]
    train_world_model(draccus.parse(TrainWorldModelConfig, args=away))
    assert_same_weights(
        tmp_path / "here" / FINAL / "model.safetensors", tmp_path / "away" / FINAL / "model.safetensors"
    )
    (tmp_path / "broken.xz").write_bytes(b"not xz")
    with pytest.raises(ValueError, match="broken.xz: not a token cache exported"):
        import_token_cache(tmp_path / "broken.xz", tmp_path / "there")
