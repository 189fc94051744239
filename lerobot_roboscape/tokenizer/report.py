"""The tokenizer's report on held-out frames, per camera view: does the reconstruction keep the task object?

Per view: whole-frame PSNR, object-region PSNR and the share of frames in which the object survives
(metrics/image_fidelity.py, from the masks recorded with the dataset), and codebook use (share of codes used,
perplexity).
Writes tokenizer_report.json, tokenizer_report.md, reconstruction.png (real above reconstructed, a column per frame
that shows the object) and, when the training run recorded them, its held-out curves (heldout_curve.png).
"""

import json
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import imageio.v3 as iio
import matplotlib
import numpy as np
import torch
from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.dataset.reader import FrameBank, camera_names, open_dataset
from lerobot_roboscape.dataset.segmentation import OBJECT, has_masks
from lerobot_roboscape.io.templates import render_report
from lerobot_roboscape.metrics.image_fidelity import MIN_OBJECT_PIXELS, codebook_use, frame_measures, psnr, summarise
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.training.loop import read_curve, resolve_device

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

REPORT_JSON = "tokenizer_report.json"


def read_tokenizer_report(folder: Path) -> dict:
    """The report `evaluate_tokenizer` wrote into `folder`."""
    return json.loads((Path(folder) / REPORT_JSON).read_text())


def results_entry(report: dict) -> dict:
    """What a run's results.json keeps of a tokenizer report: each view's measures."""
    return report["views"]


@dataclass(frozen=True)
class ViewReading:
    """One view's measures on the held-out frames (the object's None where the dataset has no masks), and the share
    of the picture's columns in which the object survives."""

    psnr: float
    object_psnr: float | None = None
    object_survival: float | None = None
    picture_object_survives: float | None = None


def view_readings(report: dict) -> dict[str, ViewReading]:
    """camera -> its readings, from a tokenizer report."""
    return {
        camera: ViewReading(m["psnr"], m.get("object_psnr"), m.get("object_survival"), m.get("picture_object_survives"))
        for camera, m in report["views"].items()
    }


logger = logging.getLogger(__name__)
CURVE_MEASURES = ("psnr", "object_psnr", "object_survival")


@dataclass
class TokenizerReportConfig:
    """Args:
    dataset: held-out episodes, recorded with --segmentation=true for the object measures.
    tokenizer: the tokenizer (local directory or Hub repo id).
    output_dir: where the report goes.
    training_dir: the tokenizer's training run, whose held-out curves the report plots (optional).
    frame_stride: every n-th frame of each episode is measured.
    columns: frames in the side-by-side picture.
    device: "auto", "cpu" or "cuda".
    """

    dataset: DatasetConfig = field(default_factory=lambda: DatasetConfig(repo_id="local/roboscape_heldout"))
    tokenizer: str = "outputs/tokenizer/pretrained_model"
    output_dir: Path = Path("outputs/tokenizer_report")
    training_dir: Path | None = None
    frame_stride: int = 1
    columns: int = 8
    device: str = "auto"


@torch.no_grad()
def reconstruct(tokenizer: VisualTokenizer, images: torch.Tensor, batch_size: int = 256):
    """(N, H, W, 3) uint8 -> (reconstructions (N, 3, H, W) in [0, 1], codes (N, h, w)), on the tokenizer's device."""
    device = next(tokenizer.parameters()).device
    recon, codes = [], []
    for start in range(0, len(images), batch_size):
        x = images[start : start + batch_size].to(device).permute(0, 3, 1, 2).float() / 255
        indices = tokenizer.encode(x)
        codes.append(indices)
        recon.append(tokenizer.decode(indices))
    return torch.cat(recon), torch.cat(codes)


@torch.no_grad()
def measure_tokenizer(tokenizer: VisualTokenizer, bank: FrameBank, cameras: list[str]) -> dict[str, dict]:
    """camera -> whole-frame and object measures (image_fidelity.summarise; object ones None without masks) and
    codebook use, over every frame of `bank`."""
    views = {}
    for v, camera in enumerate(cameras):
        recon, codes = reconstruct(tokenizer, bank.images[:, v])
        real = bank.images[:, v].to(recon.device).permute(0, 3, 1, 2).float() / 255
        if bank.masks is None:
            summary = {"psnr": float(psnr(recon, real).mean()), "object_psnr": None, "object_survival": None}
        else:
            summary = summarise(frame_measures(recon, real, bank.masks[:, v].to(recon.device)))
        views[camera] = summary | {"codebook": codebook_use(codes, tokenizer.config.codebook_size)}
    return views


def curve_point(views: dict[str, dict]) -> dict[str, float | None]:
    """The measures of `measure_tokenizer` as one flat held-out curve point ("wrist/object_psnr": ...)."""
    point = {}
    for camera, m in views.items():
        point |= {f"{camera}/{k}": m[k] for k in CURVE_MEASURES}
        point[f"{camera}/codebook_share_used"] = m["codebook"]["share_used"]
        point[f"{camera}/perplexity"] = m["codebook"]["perplexity"]
    return point


def evaluate_tokenizer(cfg: TokenizerReportConfig) -> dict:
    dataset = open_dataset(cfg.dataset.repo_id, cfg.dataset.root, cfg.dataset.episodes)
    masks = has_masks(dataset.root)
    if not masks:
        logger.warning("%s has no segmentation masks: the report gives no object measures", dataset.root)
    tokenizer = VisualTokenizer.from_pretrained(cfg.tokenizer).to(resolve_device(cfg.device)).eval()
    cameras = camera_names(dataset)
    bank = FrameBank.load(dataset, masks=masks, stride=cfg.frame_stride)
    report = {
        "config": json.loads(json.dumps(asdict(cfg), default=str)),
        "tokenizer": asdict(tokenizer.config),
        "episodes": len(set(bank.episode_index.tolist())),
        "min_object_pixels": MIN_OBJECT_PIXELS,
        "views": measure_tokenizer(tokenizer, bank, cameras),
        "curve": read_curve(cfg.training_dir) if cfg.training_dir else [],
    }
    out = Path(cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    picture = reconstruction_figure(tokenizer, bank, cameras, out / "reconstruction.png", cfg.columns)
    for camera, share in picture.items():
        report["views"][camera]["picture_object_survives"] = share
    (out / REPORT_JSON).write_text(json.dumps(report, indent=2))
    (out / "tokenizer_report.md").write_text(markdown(report))
    if report["curve"]:
        curve_figure(report["curve"], cameras, out / "heldout_curve.png")
    return report


def object_columns(bank: FrameBank, columns: int) -> list[int]:
    """Frames of `bank` for the side-by-side picture, spread over its episodes: each the frame of its episode where
    the object covers the most pixels of its least-covered view (every view shows it, when a frame does)."""
    episodes = np.unique(bank.episode_index)
    picked = []
    for episode in episodes[np.linspace(0, len(episodes) - 1, min(columns, len(episodes))).round().astype(int)]:
        frames = np.flatnonzero(bank.episode_index == episode)
        if bank.masks is None:
            picked.append(int(frames[len(frames) // 2]))
            continue
        least = (bank.masks[frames] == OBJECT).flatten(2).sum(2).min(1).values  # (frames,)
        picked.append(int(frames[int(least.argmax())]))
    return picked


def reconstruction_figure(tokenizer, bank: FrameBank, cameras: list[str], path: Path, columns: int) -> dict:
    """Real frames (top) above their reconstructions (bottom), a row pair per view, at 3x size. Returns, per view,
    the share of the columns showing the object (>= MIN_OBJECT_PIXELS) in which it survives (None: none shows it)."""
    picked = object_columns(bank, columns)
    rows, survives = [], {}
    for v, camera in enumerate(cameras):
        real = bank.images[picked, v]
        recon, _ = reconstruct(tokenizer, real)
        if bank.masks is not None:
            real_float = real.to(recon.device).permute(0, 3, 1, 2).float() / 255
            kept = summarise(frame_measures(recon, real_float, bank.masks[picked, v].to(recon.device)))
            survives[camera] = kept["object_survival"]
        recon = (recon.clamp(0, 1).permute(0, 2, 3, 1).cpu() * 255).round().to(torch.uint8)
        rows += [torch.cat(list(real), 1), torch.cat(list(recon), 1)]
    grid = torch.cat(rows, 0).numpy()
    iio.imwrite(path, np.kron(grid, np.ones((3, 3, 1), np.uint8)))
    return survives


def curve_figure(curve: list[dict], cameras: list[str], path: Path) -> None:
    steps = [p["step"] for p in curve]
    fig, axes = plt.subplots(1, len(CURVE_MEASURES), figsize=(12, 3.2))
    for ax, measure in zip(axes, CURVE_MEASURES, strict=True):
        for camera in cameras:
            values = [np.nan if p.get(f"{camera}/{measure}") is None else p[f"{camera}/{measure}"] for p in curve]
            ax.plot(steps, values, "-o", markersize=3, label=camera)
        ax.set_title(f"held-out {measure.replace('_', ' ')}")
        ax.set_xlabel("training step")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def headline(report: dict) -> str:
    """The report in one line, for a run's console."""
    return ", ".join(f"{view} PSNR {m.psnr:.1f} dB, {_survival(m)}" for view, m in view_readings(report).items())


def _survival(m: ViewReading) -> str:
    if m.object_survival is None:  # no segmentation masks, or no frame where the object covers >= 4 px
        return "object survival not measured (no object masks in these frames)"
    return f"object survives in {m.object_survival:.0%} of frames"


def markdown(report: dict) -> str:
    sized = {camera: m["object_survival_by_size"] for camera, m in report["views"].items() if m.get("frames")}
    return render_report("tokenizer_report.md", report=report, sized=sized)
