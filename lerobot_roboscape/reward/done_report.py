"""Which done signal to trust, at which threshold (`roboscape-eval-done`).

Two sources say "the task is accomplished in this frame": the action world model's done head (the paper's) and a
success classifier on the decoded frames (DIAMOND's termination head, RLinf's reward classifier). For each, on
held-out episodes with failures:

- teacher-forced: the source reads the real frames (through the tokenizer) one after the other;
- open loop: the action model generates the whole episode from its prompt frames and the recorded actions, and the
  source reads the generated frames, as inside `roboscape_wm`.

Frame scores are judged against the recorded done labels (ROC-AUC); an episode's score is its highest frame score,
judged against the episode's success. The threshold and the source are chosen on separate validation episodes
(teacher-forced), never on the episodes reported: the threshold maximises true-positive minus false-positive rate
over validation episodes, the source has the larger validation frame ROC-AUC. At that threshold the report gives
each source's confusion matrix of episodes, the share of failed episodes it calls done among them.
"""

import json
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import matplotlib
import numpy as np
import torch
from lerobot.configs.default import DatasetConfig
from torchmetrics.functional.classification import binary_auroc

from lerobot_roboscape.dataset.reader import camera_names, episode_indices, open_dataset, read_episode
from lerobot_roboscape.io.templates import render_report
from lerobot_roboscape.io.tensor_files import load_tensors, save_tensors
from lerobot_roboscape.reward.baselines import RewardModel
from lerobot_roboscape.reward.done_readings import MODES, DoneReport
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.training.loop import resolve_device
from lerobot_roboscape.world_model.clips import model_frames
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from roboscape_core.errors import InvalidInputError

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

logger = logging.getLogger(__name__)
SOURCES = ("world_model", "classifier")  # as the env's done_source
REPORT_JSON = "done_report.json"
DEFAULT_THETA = 0.5  # when the validation episodes hold one kind only (tiny runs): no threshold can be chosen


@dataclass
class DoneReportConfig:
    """Args:
    dataset: held-out episodes, successful and failed (--dataset.episodes to pick some).
    validation: other episodes, successful and failed, on which the threshold and the source are chosen.
    tokenizer: the world models' tokenizer.
    world_model: the action world model (its done head, and the open-loop frames).
    dataset_tokens: the held-out episodes as a token episodes file (`save_token_episodes`), read instead of
        `dataset` on a machine without it.
    validation_tokens: the validation episodes likewise, instead of `validation`.
    success_classifier: a success classifier (`roboscape-train-reward --reward.kind=success`); None: the done head
        only.
    output_dir: where done_report.json, done_report.md and done_curves.png go.
    open_loop: also generate every reported episode open loop (the costly part).
    batch_size: episodes generated at once.
    device: "auto", "cpu" or "cuda".
    """

    dataset: DatasetConfig = field(default_factory=lambda: DatasetConfig(repo_id="local/roboscape_heldout"))
    validation: DatasetConfig = field(default_factory=lambda: DatasetConfig(repo_id="local/roboscape_validation"))
    dataset_tokens: str | None = None
    validation_tokens: str | None = None
    tokenizer: str = "outputs/tokenizer/pretrained_model"
    world_model: str = "outputs/world_model_action/pretrained_model"
    success_classifier: str | None = None
    output_dir: Path = Path("outputs/done_report")
    open_loop: bool = True
    batch_size: int = 16
    device: str = "auto"


@dataclass
class EpisodeScores:
    index: int
    task: str
    success: bool
    labels: np.ndarray  # (T,) recorded done
    scores: dict  # (source, mode) -> (T,) done probabilities


class DoneSources:
    """The done sources of one set of models, scoring token frames."""

    def __init__(self, tokenizer: VisualTokenizer, model: STWorldModel, classifier: RewardModel | None):
        self.tokenizer, self.model, self.classifier = tokenizer, model, classifier
        self.names = SOURCES if classifier is not None else SOURCES[:1]

    @torch.no_grad()
    def classify(self, tokens_TS: torch.Tensor) -> torch.Tensor:
        images = self.tokenizer.decode_views(tokens_TS, self.model.config.n_cameras)
        return torch.cat([self.classifier.success_probability(chunk) for chunk in images.split(64)])

    @torch.no_grad()
    def teacher_forced(self, tokens_TS, actions_NA, states_TD) -> dict[str, np.ndarray]:
        """Scores of known model frames (T, S) read with the actions between them ((T - 1) * k, A) and their
        states (T, D)."""
        states = states_TD[None] if self.model.config.state else None
        done = self.model.teacher_forced(tokens_TS[None], actions_NA[None], states=states)[0][0]
        scores = {"world_model": done}
        if self.classifier is not None:
            scores["classifier"] = self.classify(tokens_TS)
        return {k: v.float().cpu().numpy() for k, v in scores.items()}

    @torch.no_grad()
    def open_loop(self, episodes: list["TokenEpisode"]) -> list[dict[str, np.ndarray]]:
        """Episodes generated from their prompt frames (and states) and recorded actions to their end, scored by
        each source; the prompt frames keep their teacher-forced scores."""
        P, k = self.model.config.prompt_frames, self.model.config.frame_skip
        length = max(len(e.tokens) for e in episodes)
        pad = lambda a: torch.cat([a, a[-1:].expand((length - 1) * k - len(a), -1)])  # noqa: E731  (hold the last)
        actions = torch.stack([pad(e.actions) for e in episodes])
        prompt = torch.stack([e.tokens[:P] for e in episodes])
        states = torch.stack([e.states[:P] for e in episodes]) if self.model.config.state else None
        frames, done, _ = self.model.generate(prompt, length - P, actions=actions, states=states)
        out = []
        for i, e in enumerate(episodes):
            T = len(e.tokens)
            forced = self.teacher_forced(e.tokens[:P], e.actions[: (P - 1) * k], e.states[:P])
            scores = {"world_model": np.concatenate([forced["world_model"], done[i, : T - P].float().cpu().numpy()])}
            if self.classifier is not None:
                generated = self.classify(frames[i, : T - P]).float().cpu().numpy()
                scores["classifier"] = np.concatenate([forced["classifier"], generated])
            out.append(scores)
        return out


@dataclass
class TokenEpisode:
    """An episode as the done sources read it: its model frames' tokens and states, the actions between them, its
    labels."""

    index: int
    task: str
    tokens: torch.Tensor  # (T, S): every k-th frame (the model's frame skip k)
    actions: torch.Tensor  # ((T - 1) * k, A): the recorded actions between them
    states: torch.Tensor  # (T, D): the robot's state in those frames
    labels: np.ndarray  # (T,) recorded done at those frames
    success: bool


def token_episodes(dataset, tokenizer: VisualTokenizer, frame_skip: int, device) -> list[TokenEpisode]:
    """Every episode of `dataset` tokenized at the model frames of a world model with this frame skip."""
    cameras, episodes = camera_names(dataset), []
    for index in episode_indices(dataset):
        episode = read_episode(dataset, index)
        frames = model_frames(len(episode.action), frame_skip)
        tokens = tokenizer.encode_frames([episode.images[c][frames] for c in cameras])
        actions = torch.from_numpy(episode.action[: (len(frames) - 1) * frame_skip]).to(device)
        success = bool(episode.done_label.max() > 0.5)
        states = torch.from_numpy(episode.state[frames]).to(device)
        episodes.append(TokenEpisode(index, episode.task, tokens, actions, states, episode.done_label[frames], success))
    return episodes


TOKEN_EPISODES_FORMAT = 2  # 2: the frames' states


def save_token_episodes(episodes: list[TokenEpisode], frame_skip: int, path: Path, source: str) -> Path:
    """`episodes` in one safetensors file, so a machine without the dataset (or its videos) can report on them."""
    tensors, rows = {}, []
    for i, e in enumerate(episodes):
        # Codes below 2**15 (the token cache keeps them in 16 bits too): a quarter of int64's bytes to carry.
        tensors |= {f"{i}.tokens": e.tokens.to(torch.int16), f"{i}.actions": e.actions, f"{i}.states": e.states}
        tensors[f"{i}.labels"] = torch.from_numpy(np.ascontiguousarray(e.labels))
        rows.append({"index": e.index, "task": e.task, "success": e.success})
    metadata = {"format": TOKEN_EPISODES_FORMAT, "frame_skip": frame_skip, "source": source, "episodes": rows}
    return save_tensors(path, tensors, {"episodes": json.dumps(metadata)})


def load_token_episodes(path: Path, frame_skip: int, device) -> list[TokenEpisode]:
    """The episodes `save_token_episodes` wrote, for a world model with this frame skip."""
    records, tensors = load_tensors(path, "save_token_episodes", ("episodes",))
    metadata = json.loads(records["episodes"])
    if metadata.get("format") != TOKEN_EPISODES_FORMAT or metadata["frame_skip"] != frame_skip:
        raise InvalidInputError(
            f"{path} holds episodes of format {metadata.get('format')} at frame skip {metadata.get('frame_skip')}; "
            f"this version reads format {TOKEN_EPISODES_FORMAT} and the world model's frame skip is {frame_skip}"
        )
    return [
        TokenEpisode(
            row["index"],
            row["task"],
            tensors[f"{i}.tokens"].to(device, torch.long),
            tensors[f"{i}.actions"].to(device),
            tensors[f"{i}.states"].to(device),
            tensors[f"{i}.labels"].numpy(),
            row["success"],
        )
        for i, row in enumerate(metadata["episodes"])
    ]


def score_episodes(
    episodes: list[TokenEpisode], sources: DoneSources, open_loop: bool, batch_size: int
) -> list[EpisodeScores]:
    scored, pending = [], []
    for e in episodes:
        forced = sources.teacher_forced(e.tokens, e.actions, e.states)
        scores = {(s, "teacher_forced"): v for s, v in forced.items()}
        scored.append(EpisodeScores(e.index, e.task, e.success, e.labels, scores))
        if open_loop and len(e.tokens) > sources.model.config.prompt_frames:
            pending.append((scored[-1], e))
    pending.sort(key=lambda item: len(item[1].actions))  # batches of similar lengths pad less
    for start in range(0, len(pending), batch_size):
        chunk = pending[start : start + batch_size]
        for (episode, _), scores in zip(chunk, sources.open_loop([e for _, e in chunk]), strict=True):
            episode.scores |= {(s, "open_loop"): v for s, v in scores.items()}
        logger.info("open loop: %d/%d episodes", min(start + batch_size, len(pending)), len(pending))
    return scored


def roc_auc(scores: np.ndarray, labels: np.ndarray) -> float | None:
    """ROC-AUC of scores against boolean labels; None with one class only."""
    labels = np.asarray(labels) > 0.5
    if labels.all() or not labels.any():
        return None
    return float(binary_auroc(torch.as_tensor(scores, dtype=torch.float32), torch.from_numpy(labels.astype(np.int64))))


def choose_threshold(episode_scores: np.ndarray, success: np.ndarray) -> float:
    """The threshold on episode scores (highest done probability) that maximises true-positive minus false-positive
    rate (Youden's J); among equals, the highest (fewest false alarms). Candidates: midpoints between scores."""
    values = np.unique(episode_scores)
    candidates = np.concatenate([(values[:-1] + values[1:]) / 2, [values[-1] + 1e-6]]) if len(values) > 1 else values
    success = success.astype(bool)
    best, best_j = float(candidates[-1]), -np.inf
    for theta in candidates[::-1]:
        called = episode_scores >= theta
        j = called[success].mean() - called[~success].mean() if success.any() and (~success).any() else 0.0
        if j > best_j + 1e-12:
            best, best_j = float(theta), j
    return best


def confusion(episode_scores: np.ndarray, success: np.ndarray, theta: float) -> dict:
    called, success = episode_scores >= theta, success.astype(bool)
    failed = int((~success).sum())
    return {
        "success_called_done": int((called & success).sum()),
        "success_missed": int((~called & success).sum()),
        "failed_called_done": int((called & ~success).sum()),
        "failed_not_done": int((~called & ~success).sum()),
        "failed_called_done_rate": float((called & ~success).sum() / failed) if failed else None,
    }


def summarise(episodes: list[EpisodeScores], source: str, mode: str, theta: float | None) -> dict | None:
    kept = [e for e in episodes if (source, mode) in e.scores]
    if not kept:
        return None
    frames = np.concatenate([e.scores[(source, mode)] for e in kept])
    labels = np.concatenate([e.labels for e in kept])
    best = np.array([e.scores[(source, mode)].max() for e in kept])
    success = np.array([e.success for e in kept])
    out = {
        "episodes": len(kept),
        "successful": int(success.sum()),
        "frames": int(len(frames)),
        "done_frames": int((labels > 0.5).sum()),
        "frame_roc_auc": roc_auc(frames, labels),
        "episode_roc_auc": roc_auc(best, success),
    }
    if theta is not None:
        out["confusion"] = confusion(best, success, theta)
    return out


@dataclass(frozen=True)
class DoneChoice:
    """The done signal the env trusts, chosen on the validation episodes: its source ("world_model" or
    "classifier") and threshold."""

    source: str
    theta: float

    @classmethod
    def read(cls, folder: Path) -> "DoneChoice":
        """The choice a finished report in `folder` made."""
        report = DoneReport.from_json(read_done_report(folder))
        return cls(report.source, report.theta)


def read_done_report(folder: Path) -> dict:
    """The report `evaluate_done` wrote into `folder`."""
    return json.loads((Path(folder) / REPORT_JSON).read_text())


def results_entry(report: dict) -> dict:
    """What a run's results.json keeps of a done report: the choice and every source's readings."""
    return {k: report[k] for k in ("chosen", "sources")}


def evaluate_done(cfg: DoneReportConfig) -> dict:
    device = resolve_device(cfg.device)
    tokenizer = VisualTokenizer.from_pretrained(cfg.tokenizer).to(device).eval()
    model = STWorldModel.from_pretrained(cfg.world_model).to(device).eval()
    if model.config.control != "action":
        raise InvalidInputError(f"{cfg.world_model} is a {model.config.control} world model, not an action one")
    classifier = None
    if cfg.success_classifier:
        classifier = RewardModel.from_pretrained(cfg.success_classifier).to(device).eval()
        if classifier.config.kind != "success":
            raise InvalidInputError(f"{cfg.success_classifier} is a {classifier.config.kind} model, not a success one")
    sources = DoneSources(tokenizer, model, classifier)

    def episodes_of(data: DatasetConfig, tokens: str | None, open_loop: bool) -> list[EpisodeScores]:
        k = model.config.frame_skip
        if tokens:
            episodes = load_token_episodes(Path(tokens), k, device)
        else:
            episodes = token_episodes(open_dataset(data.repo_id, data.root, data.episodes), tokenizer, k, device)
        return score_episodes(episodes, sources, open_loop, cfg.batch_size)

    validation = episodes_of(cfg.validation, cfg.validation_tokens, open_loop=False)
    chosen = {}
    for source in sources.names:
        best = np.array([e.scores[(source, "teacher_forced")].max() for e in validation])
        success = np.array([e.success for e in validation])
        both = success.any() and not success.all()
        if not both:
            logger.warning(
                "%s: %d of %d validation episodes succeeded; a threshold needs both kinds, %s keeps %.2f",
                cfg.validation_tokens or cfg.validation.root,
                int(success.sum()),
                len(success),
                source,
                DEFAULT_THETA,
            )
        chosen[source] = {
            # A probability threshold the env accepts, (0, 1]: "above every score" can land past 1.
            "theta": float(np.clip(choose_threshold(best, success), 1e-3, 1.0)) if both else DEFAULT_THETA,
            "theta_from": "validation" if both else "default (validation episodes of one kind)",
            "validation": summarise(validation, source, "teacher_forced", None),
        }
        chosen[source]["validation"]["confusion"] = confusion(best, success, chosen[source]["theta"])
    source = max(sources.names, key=lambda s: chosen[s]["validation"]["frame_roc_auc"] or 0.0)
    heldout = episodes_of(cfg.dataset, cfg.dataset_tokens, cfg.open_loop)
    report = {
        "config": json.loads(json.dumps(asdict(cfg), default=str)),
        "chosen": {"source": source, "theta": chosen[source]["theta"], "theta_from": chosen[source]["theta_from"]},
        "sources": {
            s: {
                "theta": chosen[s]["theta"],
                "theta_from": chosen[s]["theta_from"],
                "validation": chosen[s]["validation"],
                **{mode: summarise(heldout, s, mode, chosen[s]["theta"]) for mode in MODES},
            }
            for s in sources.names
        },
        "episodes": [
            {
                "episode_index": e.index,
                "task": e.task,
                "success": e.success,
                "scores": {f"{s}/{m}": v.round(4).tolist() for (s, m), v in e.scores.items()},
            }
            for e in heldout
        ],
    }
    out = Path(cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / REPORT_JSON).write_text(json.dumps(report, indent=2))
    (out / "done_report.md").write_text(markdown(report))
    plot_curves(heldout, report, out / "done_curves.png")
    return report


def markdown(report: dict) -> str:
    return render_report("done_report.md", report=report, modes=MODES)


def plot_curves(episodes: list[EpisodeScores], report: dict, path: Path, per_kind: int = 6) -> None:
    """Each source's done probability along held-out episodes, successful (solid) and failed (dashed), with the
    recorded first done frame marked and the chosen threshold drawn."""
    keys = sorted({k for e in episodes for k in e.scores})
    fig, axes = plt.subplots(1, len(keys), figsize=(4.5 * len(keys), 3.2), squeeze=False)
    picked = [e for e in episodes if e.success][:per_kind] + [e for e in episodes if not e.success][:per_kind]
    for ax, (source, mode) in zip(axes[0], keys, strict=True):
        for e in picked:
            if (source, mode) not in e.scores:
                continue
            (line,) = ax.plot(e.scores[(source, mode)], "-" if e.success else "--", lw=1)
            if e.success:
                ax.axvline(int(np.argmax(e.labels > 0.5)), color=line.get_color(), lw=0.5, alpha=0.6)
        ax.axhline(report["sources"][source]["theta"], color="k", lw=0.8)
        ax.set_title(f"{source}, {mode.replace('_', ' ')}", fontsize=9)
        ax.set_xlabel("frame")
        ax.set_ylim(-0.02, 1.02)
    axes[0][0].set_ylabel("done probability (solid: success, dashed: failure)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
