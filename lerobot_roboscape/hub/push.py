"""Artifacts to the Hugging Face Hub, or to a local folder shaped like it.

Every model push first builds, in a temporary directory, the exact folder that the Hub repo will hold (weights,
configs, processors, card), then uploads it in one commit, or, with `local_dir`, moves it to
`local_dir/<repo_id>` (datasets: `local_dir/datasets/<repo_id>`), a dry run that can be inspected or uploaded
later with `hf upload`. Datasets go through LeRobotDataset's own push, with the card of `cards.dataset_card`.
"""

import json
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from huggingface_hub import HfApi
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_roboscape.dataset.writer import DATASET_FOLDERS
from lerobot_roboscape.hub.cards import (
    DATASET_TAGS,
    LICENSE,
    dataset_card,
    dataset_description,
    model_card,
    parameter_count,
    read_json,
)
from lerobot_roboscape.hub.pull import WORLD_MODELS_MANIFEST
from lerobot_roboscape.io.weights import looks_like_repo_id
from lerobot_roboscape.training.checkpoints import PPO_CONFIG_JSON
from lerobot_roboscape.world_model.measures.fidelity import REPORT_JSON as FIDELITY_JSON
from lerobot_roboscape.world_model.measures.fidelity import read_fidelity
from roboscape_core.errors import InvalidInputError, MissingInputError

WORLD_MODEL_FOLDERS = {
    "tokenizer": "tokenizer",
    "action_world_model": "action_world_model",
    "text_world_model": "text_world_model",
}
POLICY_FILES = ("config.json", "model.safetensors", "train_config.json")


def _require(path: Path, what: str, how_to_make: str) -> Path:
    if not (path / "config.json").is_file():
        raise MissingInputError(f"no {what} at {path} (config.json missing); {how_to_make}")
    return path


def _copy_model(source: Path, target: Path) -> None:
    # The card written by save_pretrained is replaced by the repo's own card.
    shutil.copytree(source, target, ignore=shutil.ignore_patterns("README.md"))


def _training_config(pretrained_model: Path) -> dict | None:
    """The train_config.json that training writes beside a pretrained_model directory, if any."""
    path = pretrained_model.parent / "train_config.json"
    return read_json(path) if path.is_file() else None


def _fidelity_summary(report_dir: Path) -> dict:
    report = read_fidelity(report_dir)
    summary = {
        key: f"{value:.3f}" if "ssim" in key or "lpips" in key else f"{value:.2f}"
        for key, value in report["mean"].items()
    }
    return {
        **summary,
        "episodes": len(report.get("episodes", [])) or "-",
        "prompt_frames": report["prompt_frames"],
        "lpips": report["lpips_trunk"],
        "retrieval": f"{report['controllability']['world_model']['whole_frame']['retrieval']:.3f}"
        if "controllability" in report
        else "- (not measured: no controllability set)",
    }


def stage_world_models(
    folder: Path,
    repo_id: str,
    tokenizer: Path,
    action_world_model: Path,
    text_world_model: Path,
    dataset_repo_id: str | None = None,
    fidelity_dir: Path | None = None,
) -> Path:
    """Build the world-models repo in `folder`: three model folders, a manifest, the fidelity report, the card."""
    sources = {
        "tokenizer": _require(Path(tokenizer), "tokenizer", "train one with roboscape-train-tokenizer"),
        "action_world_model": _require(
            Path(action_world_model), "action world model", "train one with roboscape-train-wm --wm.control=action"
        ),
        "text_world_model": _require(
            Path(text_world_model), "text world model", "train one with roboscape-train-wm --wm.control=text"
        ),
    }
    configs = {key: read_json(path / "config.json") for key, path in sources.items()}
    for key in ("action_world_model", "text_world_model"):
        control = key.split("_")[0]
        if configs[key].get("control") != control:
            raise InvalidInputError(
                f"{sources[key]} is a {configs[key].get('control')} world model, not a {control} one"
            )
    trained = {key: _training_config(path) for key, path in sources.items()}
    if dataset_repo_id is None:
        dataset_repo_id = next((t["dataset"]["repo_id"] for t in trained.values() if t and "dataset" in t), None)
        if dataset_repo_id is None:
            raise InvalidInputError(
                "dataset_repo_id is needed: no training config beside the models names their dataset"
            )

    for key, source in sources.items():
        _copy_model(source, folder / WORLD_MODEL_FOLDERS[key])
        if trained[key] is not None:
            (folder / WORLD_MODEL_FOLDERS[key] / "train_config.json").write_text(json.dumps(trained[key], indent=2))
    (folder / WORLD_MODELS_MANIFEST).write_text(
        json.dumps({"dataset_repo_id": dataset_repo_id, **WORLD_MODEL_FOLDERS}, indent=2)
    )
    fidelity = None
    if fidelity_dir is not None:
        for name in ("fidelity.md", FIDELITY_JSON, "fidelity.png"):
            if (Path(fidelity_dir) / name).is_file():
                shutil.copy2(Path(fidelity_dir) / name, folder / name)
        fidelity = _fidelity_summary(Path(fidelity_dir))

    tok = configs["tokenizer"]
    grid = tok["image_size"] // 2 ** (len(tok["channel_multipliers"]) - 1)

    def wm_fields(key):
        c = configs[key]
        stats = {name: [f"{v:.4g}" for v in c.get(name) or []] for name in ("action_mean", "action_std")}
        return {
            "size": f"d_model {c['d_model']}, {c['n_layer']} layers",
            "parameters": parameter_count(sources[key] / "model.safetensors"),
            "frame_skip": c.get("frame_skip", 1),
            "dims": list(range(len(stats["action_mean"]))),
            **stats,
        }

    card = model_card(
        "world_models.md",
        repo_id=repo_id,
        dataset_repo_id=dataset_repo_id,
        fidelity=fidelity,
        tokenizer={
            "image_size": tok["image_size"],
            "grid": grid,
            "codebook": 2 ** tok["codebook_bits"],
            "parameters": parameter_count(sources["tokenizer"] / "model.safetensors"),
        },
        action=wm_fields("action_world_model"),
        text=wm_fields("text_world_model"),
        training={key: json.dumps(t, indent=2) for key, t in trained.items() if t is not None},
    )
    card.save(folder / "README.md")
    return folder


def stage_policy(
    folder: Path, repo_id: str, pretrained_model: Path, eval_dir: Path | None = None, dataset_repo_id: str | None = None
) -> Path:
    """Build a policy repo in `folder`: what lerobot-eval loads (config, weights, processors) and the card.

    `pretrained_model` is a checkpoint of lerobot-train (SFT) or roboscape-ppo; `eval_dir` a roboscape-eval output.
    """
    pretrained_model = Path(pretrained_model)
    _require(pretrained_model, "policy", "train one with lerobot-train or roboscape-ppo")
    config = read_json(pretrained_model / "config.json")
    _copy_model(pretrained_model, folder)
    ppo_path = pretrained_model.parent / PPO_CONFIG_JSON
    training, method, reward = {}, "sft", None
    if ppo_path.is_file():
        ppo = read_json(ppo_path)
        shutil.copy2(ppo_path, folder / PPO_CONFIG_JSON)
        training["roboscape-ppo"] = json.dumps(ppo, indent=2)
        method = ppo["env"]["type"]
        dataset_repo_id = dataset_repo_id or ppo["env"].get("dataset_repo_id")
        if (reward_path := pretrained_model.parent / "reward.txt").is_file():
            reward = reward_path.read_text().strip()
    if (pretrained_model / "train_config.json").is_file():
        train = read_json(pretrained_model / "train_config.json")
        training["lerobot-train"] = json.dumps(train, indent=2)
        if method == "sft":
            dataset_repo_id = dataset_repo_id or train["dataset"]["repo_id"]
    method_text, method_details = {
        "sft": (
            "supervised fine-tuning",
            "Trained by behaviour cloning of planner demonstrations with `lerobot-train`.",
        ),
        "roboscape_wm": (
            "PPO in the world model",
            "Fine-tuned from its SFT checkpoint by PPO inside the learned world "
            "models (`roboscape_wm`), with the world models' own reward, as in RoboScape-R.",
        ),
        "roboscape_maniskill": (
            "PPO in ManiSkill",
            "Fine-tuned from its SFT checkpoint by PPO in the ManiSkill "
            "simulator (`roboscape_maniskill`), the paper's baseline.",
        ),
    }.get(method, (f"PPO in {method}", f"Fine-tuned from its SFT checkpoint by PPO in `{method}`."))
    results = None
    if eval_dir is not None:
        if not (Path(eval_dir) / "eval.md").is_file():
            raise MissingInputError(f"no roboscape-eval results in {eval_dir} (eval.md missing)")
        results = (Path(eval_dir) / "eval.md").read_text().split("\n", 1)[1].strip()  # drop the local path line
        for path in Path(eval_dir).glob("eval.*"):  # roboscape-eval's results, as it names them
            shutil.copy2(path, folder / path.name)
    base_model = config.get("base_model")  # a Hub id, a local folder or a random preset ("tiny")
    card = model_card(
        "policy.md",
        repo_id=repo_id,
        policy_type=config["type"],
        method=method,
        method_text=method_text,
        method_details=method_details,
        dataset_repo_id=dataset_repo_id,
        base_model=base_model,
        base_model_repo=base_model if base_model and looks_like_repo_id(base_model) else None,
        results=results,
        training=training,
        reward=reward,
    )
    card.save(folder / "README.md")
    return folder


def publish(
    folder: Path, repo_id: str, local_dir: Path | None = None, private: bool | None = None, repo_type: str = "model"
) -> str:
    """Upload a staged folder as one commit, or move it to `local_dir/<repo_id>` (replacing an earlier copy)."""
    if local_dir is not None:
        target = Path(local_dir) / ("datasets" if repo_type == "dataset" else "") / repo_id
        target.parent.mkdir(parents=True, exist_ok=True)
        partial = target.with_name(f".{target.name}.partial")
        shutil.rmtree(partial, ignore_errors=True)
        shutil.copytree(folder, partial)
        shutil.rmtree(target, ignore_errors=True)
        partial.rename(target)
        return str(target)
    api = HfApi()
    repo_id = api.create_repo(repo_id=repo_id, repo_type=repo_type, private=private, exist_ok=True).repo_id
    api.upload_folder(
        folder_path=folder, repo_id=repo_id, repo_type=repo_type, commit_message="Upload with lerobot-roboscape"
    )
    return f"https://huggingface.co/{'datasets/' * (repo_type == 'dataset')}{repo_id}"


def push_world_models(repo_id: str, local_dir: Path | None = None, private: bool | None = None, **sources) -> str:
    with tempfile.TemporaryDirectory() as tmp:
        return publish(stage_world_models(Path(tmp), repo_id, **sources), repo_id, local_dir, private)


def push_policy(
    repo_id: str, pretrained_model: Path, local_dir: Path | None = None, private: bool | None = None, **card_sources
) -> str:
    with tempfile.TemporaryDirectory() as tmp:
        folder = stage_policy(Path(tmp) / "repo", repo_id, pretrained_model, **card_sources)
        return publish(folder, repo_id, local_dir, private)


def push_dataset(root: Path, repo_id: str, local_dir: Path | None = None, private: bool | None = None) -> str:
    """LeRobotDataset.push_to_hub with our card; with `local_dir`, the same files and card in a local folder."""
    root = Path(root)
    if not (root / "meta" / "info.json").is_file():
        raise MissingInputError(f"no LeRobot dataset at {root} (meta/info.json is missing)")
    if local_dir is None:
        LeRobotDataset(repo_id, root=root).push_to_hub(
            tags=DATASET_TAGS,
            license=LICENSE,
            private=private,
            allow_patterns=[f"{folder}/*" for folder in DATASET_FOLDERS],
            dataset_description=dataset_description(root, repo_id),
        )
        return f"https://huggingface.co/datasets/{repo_id}"
    card = dataset_card(root, repo_id)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "repo"
        for own in DATASET_FOLDERS:  # as push_to_hub uploads them, without images/
            if (root / own).is_dir():
                shutil.copytree(root / own, folder / own, ignore=shutil.ignore_patterns("images"))
        card.save(folder / "README.md")
        return publish(folder, repo_id, local_dir, repo_type="dataset")


def push_run(
    namespace: str,
    local_dir: Path | None,
    dataset_root: Path,
    world_models: dict[str, Path],
    policies: dict[str, tuple[Path, Path | None]],
) -> dict[str, str]:
    """Every repo of a pipeline run, under `namespace`: the demonstrations (`roboscape_demos`), the world models with
    their tokenizer and fidelity report (`roboscape_world_models`; world_models: tokenizer, action_world_model,
    text_world_model, fidelity_dir), and each policy checkpoint with its simulator evaluation (policies: {repo name:
    (pretrained_model, eval_dir)}). Returns {repo id: where it went}."""
    dataset_repo = f"{namespace}/roboscape_demos"
    pushed = {dataset_repo: push_dataset(dataset_root, dataset_repo, local_dir)}
    world_models_repo = f"{namespace}/roboscape_world_models"
    pushed[world_models_repo] = push_world_models(
        world_models_repo, local_dir, dataset_repo_id=dataset_repo, **world_models
    )
    for name, (checkpoint, eval_dir) in policies.items():
        repo = f"{namespace}/{name}"
        pushed[repo] = push_policy(repo, checkpoint, local_dir, eval_dir=eval_dir, dataset_repo_id=dataset_repo)
    return pushed


ARTIFACTS = ("dataset", "world_models", "policy")


@dataclass
class PushConfig:
    """Args:
    artifact: "dataset", "world_models" or "policy".
    repo_id: the Hub repo, `user_or_org/name`.
    local_dir: write the repo's folder under this directory instead of uploading.
    private: create the repo private (default: the Hub's default).
    dataset_root: (dataset) the LeRobotDataset directory.
    tokenizer: (world_models) the tokenizer's pretrained_model directory.
    action_world_model: (world_models) the action world model's pretrained_model directory.
    text_world_model: (world_models) the text world model's pretrained_model directory.
    fidelity_dir: (world_models) a roboscape-eval-wm report to publish with them.
    dataset_repo_id: (world_models, policy) the dataset they were trained on, as named on the Hub (default: the one
        in their training config).
    policy: (policy) a pretrained_model directory of lerobot-train or roboscape-ppo.
    eval_dir: (policy) a roboscape-eval output whose success table goes into the card.
    """

    artifact: str = "policy"
    repo_id: str = ""
    local_dir: Path | None = None
    private: bool | None = None
    dataset_root: Path | None = None
    tokenizer: Path | None = None
    action_world_model: Path | None = None
    text_world_model: Path | None = None
    fidelity_dir: Path | None = None
    dataset_repo_id: str | None = None
    policy: Path | None = None
    eval_dir: Path | None = None

    def __post_init__(self):
        if self.artifact not in ARTIFACTS:
            raise InvalidInputError(f"--artifact must be one of {ARTIFACTS}, got {self.artifact!r}")
        if self.repo_id.count("/") != 1:
            raise InvalidInputError(f"--repo_id must be `user_or_org/name`, got {self.repo_id!r}")
        needed = {
            "dataset": ["dataset_root"],
            "world_models": ["tokenizer", "action_world_model", "text_world_model"],
            "policy": ["policy"],
        }[self.artifact]
        missing = [f"--{name}" for name in needed if getattr(self, name) is None]
        if missing:
            raise InvalidInputError(f"--artifact={self.artifact} needs {', '.join(missing)}")


def push(cfg: PushConfig) -> str:
    if cfg.artifact == "dataset":
        return push_dataset(cfg.dataset_root, cfg.repo_id, cfg.local_dir, cfg.private)
    if cfg.artifact == "world_models":
        return push_world_models(
            cfg.repo_id,
            cfg.local_dir,
            cfg.private,
            tokenizer=cfg.tokenizer,
            action_world_model=cfg.action_world_model,
            text_world_model=cfg.text_world_model,
            dataset_repo_id=cfg.dataset_repo_id,
            fidelity_dir=cfg.fidelity_dir,
        )
    return push_policy(
        cfg.repo_id, cfg.policy, cfg.local_dir, cfg.private, eval_dir=cfg.eval_dir, dataset_repo_id=cfg.dataset_repo_id
    )
