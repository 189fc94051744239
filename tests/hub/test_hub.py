"""The Hub round trip without a network: pushes are checked up to the folder and card they upload (the HfApi
calls that would send them are recorded), pulls run huggingface_hub's offline code on a populated cache."""

import hashlib
import json
import os
import shutil
import subprocess
import sys
from fnmatch import fnmatch
from pathlib import Path

import huggingface_hub.repocard
import numpy as np
import pytest
from huggingface_hub import DatasetCard, HfApi, ModelCard, constants
from huggingface_hub.repocard import RepoCard

from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.envs.world_model_env import RoboscapeWorldModelEnv
from lerobot_roboscape.hub.pull import ArtifactNotFoundError, pull_world_models
from lerobot_roboscape.hub.push import PushConfig, push_dataset, push_policy, push_world_models
from lerobot_roboscape.rl.policy_loading import load_policy
from tests.conftest import IMAGE_SIZE


def populate_hub_cache(folder: Path, repo_id: str, cache: Path, repo_type: str = "model") -> None:
    """Lay `folder` out in the Hugging Face cache as a download would: blobs, a snapshot of links, refs/main."""
    repo = cache / f"{repo_type}s--{repo_id.replace('/', '--')}"
    commit = hashlib.sha1(repo_id.encode()).hexdigest()
    for file in sorted(p for p in folder.rglob("*") if p.is_file()):
        blob = repo / "blobs" / hashlib.sha256(file.read_bytes()).hexdigest()
        blob.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(file, blob)
        link = repo / "snapshots" / commit / file.relative_to(folder)
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to(os.path.relpath(blob, link.parent))
    (repo / "refs").mkdir(parents=True, exist_ok=True)
    (repo / "refs" / "main").write_text(commit)


@pytest.fixture
def offline_cache(tmp_path, monkeypatch):
    cache = tmp_path / "hf_cache"
    cache.mkdir()
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(cache))
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    return cache


@pytest.fixture
def recorded_hub(monkeypatch):
    """Every HfApi call a push makes, with a copy of what it would upload taken at call time."""
    calls = []

    def record(name):
        def call(self, *args, **kwargs):
            entry = {"call": name, **kwargs}
            if name == "upload_folder":
                folder = Path(kwargs["folder_path"])
                entry["files"] = sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())
                if (folder / "README.md").is_file():
                    entry["card"] = (folder / "README.md").read_text()
            if name == "upload_file":
                entry["content"] = Path(kwargs["path_or_fileobj"]).read_text()
            calls.append(entry)
            if name == "create_repo":
                return type("RepoUrl", (), {"repo_id": kwargs["repo_id"]})()

        return call

    for name in ("create_repo", "upload_folder", "upload_file", "create_tag", "delete_tag"):
        monkeypatch.setattr(HfApi, name, record(name))
    # repocard bound the default HfApi's upload_file at import.
    monkeypatch.setattr(huggingface_hub.repocard, "upload_file", lambda **kw: record("upload_file")(None, **kw))
    monkeypatch.setattr(RepoCard, "validate", lambda self, repo_type=None: calls.append({"call": "validate"}))
    return calls


def _models(trained_tokenizer, world_models):
    return dict(
        tokenizer=trained_tokenizer, action_world_model=world_models["action"], text_world_model=world_models["text"]
    )


def test_world_models_repo_and_card(trained_tokenizer, world_models, tmp_path):
    url = push_world_models("me/roboscape_wm", local_dir=tmp_path / "hub", **_models(trained_tokenizer, world_models))
    repo = Path(url)
    assert repo == tmp_path / "hub" / "me" / "roboscape_wm"
    for folder in ("tokenizer", "action_world_model", "text_world_model"):
        assert {"config.json", "model.safetensors", "train_config.json"} <= {p.name for p in (repo / folder).iterdir()}
        assert not (repo / folder / "README.md").exists()  # save_pretrained's own card is replaced by the repo's
    assert (repo / "text_world_model" / "text_encoder" / "config.json").is_file()
    assert json.loads((repo / "roboscape_wm.json").read_text())["dataset_repo_id"] == "test/demos"
    assert not list(repo.rglob("*.bin")) and not list(repo.rglob("*.pt")) and not list(repo.rglob("*.pkl"))

    card = ModelCard.load(repo / "README.md")
    assert card.data.library_name == "lerobot-roboscape"
    assert card.data.license == "apache-2.0"
    assert card.data.datasets == ["test/demos"]
    assert {"lerobot", "robotics", "world-model", "reinforcement-learning"} <= set(card.data.tags)
    assert "--env.world_models=me/roboscape_wm" in card.text
    assert '"steps": 20' in card.text  # the training config of the world models
    assert "No fidelity report" in card.text
    action_config = json.loads((repo / "action_world_model" / "config.json").read_text())
    std_row = "| std | " + " | ".join(f"{v:.4g}" for v in action_config["action_std"]) + " |"
    assert std_row in card.text  # the action statistics the model normalises by
    assert f"Each model frame stands for k = {action_config['frame_skip']} control steps" in card.text


def test_world_models_push_uploads_the_staged_folder(trained_tokenizer, world_models, recorded_hub):
    assert (
        push_world_models("me/roboscape_wm", **_models(trained_tokenizer, world_models))
        == "https://huggingface.co/me/roboscape_wm"
    )
    create, upload = recorded_hub
    assert create["call"] == "create_repo" and create["repo_id"] == "me/roboscape_wm"
    assert upload["call"] == "upload_folder" and upload["repo_id"] == "me/roboscape_wm"
    assert {
        "README.md",
        "roboscape_wm.json",
        "tokenizer/model.safetensors",
        "action_world_model/config.json",
        "text_world_model/text_encoder/config.json",
    } <= set(upload["files"])
    assert "world-model" in ModelCard(upload["card"]).data.tags


def test_roboscape_wm_pulls_world_models_offline(
    demo_dataset, trained_tokenizer, world_models, tmp_path, offline_cache
):
    _, root = demo_dataset
    repo = push_world_models("me/roboscape_wm", local_dir=tmp_path / "hub", **_models(trained_tokenizer, world_models))
    populate_hub_cache(Path(repo), "me/roboscape_wm", offline_cache)

    bundle = pull_world_models("me/roboscape_wm")
    assert str(bundle.root).startswith(str(offline_cache)) and bundle.dataset_repo_id == "test/demos"
    # No dataset_repo_id: the world-models repo names it.
    env = RoboscapeWorldModelEnv(
        RoboscapeWorldModelEnvConfig(
            world_models="me/roboscape_wm",
            dataset_root=str(root),
            image_size=IMAGE_SIZE,
            allow_random_lpips=True,
            episode_length=3,
            max_goal_steps=2,
        ),
        num_envs=2,
    )
    obs, _ = env.reset(seed=0)
    assert obs["pixels"]["third_view"].shape == (2, IMAGE_SIZE, IMAGE_SIZE, 3)
    _, reward, *_ = env.step(np.zeros((2, 7), np.float32))
    assert np.isfinite(reward).all()

    with pytest.raises(
        ArtifactNotFoundError,
        match=r"'me/absent' is not in the Hugging Face cache .*"
        r"HF_HUB_OFFLINE=1.*roboscape-push --artifact=world_models",
    ):
        pull_world_models("me/absent")
    with pytest.raises(ArtifactNotFoundError, match=r"tokenizer 'me/absent'.*not in the Hugging Face cache"):
        RoboscapeWorldModelEnv(
            RoboscapeWorldModelEnvConfig(
                tokenizer="me/absent", dataset_repo_id="test/demos", dataset_root=str(root), image_size=IMAGE_SIZE
            )
        )


def test_policy_repo_pulled_offline_and_evaluated_by_lerobot(
    demo_dataset, trained_tokenizer, world_models, mlp_checkpoint, tmp_path, offline_cache
):
    _, root = demo_dataset
    hub = tmp_path / "hub"
    policy_repo = Path(push_policy("me/mlp_sft", mlp_checkpoint, local_dir=hub))
    assert {
        "config.json",
        "model.safetensors",
        "policy_preprocessor.json",
        "policy_postprocessor.json",
        "train_config.json",
    } <= {p.name for p in policy_repo.iterdir()}
    card = ModelCard.load(policy_repo / "README.md")
    assert card.data.library_name == "lerobot" and card.data.datasets == ["test/demos"]
    assert {"lerobot", "robotics", "roboscape_mlp"} <= set(card.data.tags)
    assert "reinforcement-learning" not in card.data.tags  # SFT only
    assert "lerobot-eval --policy.path=me/mlp_sft" in card.text

    wm_repo = Path(push_world_models("me/roboscape_wm", local_dir=hub, **_models(trained_tokenizer, world_models)))
    populate_hub_cache(policy_repo, "me/mlp_sft", offline_cache)
    populate_hub_cache(wm_repo, "me/roboscape_wm", offline_cache)
    policy, preprocessor, _ = load_policy("me/mlp_sft", "cpu")
    assert policy.config.type == "roboscape_mlp" and len(preprocessor.steps) > 0

    # LeRobot's own evaluation, policy and world models both given by repo id, offline.
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_HUB_CACHE": str(offline_cache)}
    out = tmp_path / "eval"
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "lerobot.scripts.lerobot_eval",
            "--policy.path=me/mlp_sft",
            "--env.type=roboscape_wm",
            "--env.world_models=me/roboscape_wm",
            f"--env.dataset_root={root}",
            f"--env.image_size={IMAGE_SIZE}",
            "--env.allow_random_lpips=true",
            "--env.episode_length=3",
            "--env.max_goal_steps=2",
            "--eval.n_episodes=2",
            "--eval.batch_size=2",
            "--policy.device=cpu",
            f"--output_dir={out}",
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert json.loads((out / "eval_info.json").read_text())["overall"]["n_episodes"] == 2


def test_dataset_push_is_lerobots_with_our_card(demo_dataset, recorded_hub, tmp_path):
    root = tmp_path / "demos"
    shutil.copytree(demo_dataset[1], root)
    (root / "stage.json").write_text('{"seconds": 3.0}')  # a pipeline's record beside the dataset: not pushed
    assert push_dataset(root, "me/demos") == "https://huggingface.co/datasets/me/demos"
    calls = {c["call"]: c for c in recorded_hub}
    assert calls["create_repo"]["repo_type"] == "dataset"
    upload = calls["upload_folder"]
    assert Path(upload["folder_path"]) == root and "images/" in upload["ignore_patterns"]
    uploaded = [f for f in upload["files"] if any(fnmatch(f, p) for p in upload["allow_patterns"])]
    assert "meta/info.json" in uploaded and any(f.startswith("videos/") for f in uploaded)
    assert "stage.json" in upload["files"] and "stage.json" not in uploaded
    card = DatasetCard(calls["upload_file"]["content"])
    assert calls["upload_file"]["path_in_repo"] == "README.md"
    assert {"LeRobot", "robotics", "roboscape"} <= set(card.data.tags) and card.data.license == "apache-2.0"
    assert "Task families:** pick_place, push" in card.text and 'LeRobotDataset("me/demos")' in card.text
    assert calls["create_tag"]["tag"] == "v3.0"  # LeRobot's codebase-version tag

    local = Path(push_dataset(root, "me/demos", local_dir=tmp_path / "hub"))
    assert local == tmp_path / "hub" / "datasets" / "me" / "demos"
    assert (local / "README.md").read_text() == calls["upload_file"]["content"]
    assert sorted(str(p.relative_to(local)) for p in local.rglob("*") if p.is_file() and p.name != "README.md") == [
        f for f in uploaded if not f.startswith("images/")
    ]


def test_push_errors_name_what_is_missing(tmp_path, mlp_checkpoint):
    with pytest.raises(ValueError, match="needs --policy"):
        PushConfig(artifact="policy", repo_id="me/x")
    with pytest.raises(ValueError, match="user_or_org/name"):
        PushConfig(artifact="policy", repo_id="x", policy=tmp_path)
    with pytest.raises(FileNotFoundError, match=f"no policy at {tmp_path}.*lerobot-train"):
        push_policy("me/x", tmp_path, local_dir=tmp_path / "hub")
    with pytest.raises(FileNotFoundError, match="no roboscape-eval results in .*eval.md"):
        push_policy("me/x", mlp_checkpoint, local_dir=tmp_path / "hub", eval_dir=tmp_path)
    with pytest.raises(FileNotFoundError, match=f"no LeRobot dataset at {tmp_path}"):
        push_dataset(tmp_path, "me/x", local_dir=tmp_path / "hub")
    assert not (tmp_path / "hub").exists()  # nothing half-written
