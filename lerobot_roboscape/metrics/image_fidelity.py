"""How well a reconstructed or predicted frame keeps the task: whole-frame PSNR, and the task object's own pixels.

Whole-frame PSNR does not see a 7 px object on a 64 px view: a model that paints the table where the cube was
loses under 1% of the frame. So, with the object's mask from the simulator (dataset/segmentation.py), per frame:

- object-region PSNR: over the object's pixels dilated by `OBJECT_DILATION` px (its outline included);
- survival: the reconstructed object pixels' mean colour is nearer the real object's mean colour than the real
  surrounding background's (a ring `RING_WIDTH` px wide around the dilated object).

Both are defined only where the object covers at least `MIN_OBJECT_PIXELS` pixels of the view (NaN elsewhere).
"""

import numpy as np
import torch
import torch.nn.functional as F

from lerobot_roboscape.dataset.segmentation import OBJECT

MIN_OBJECT_PIXELS = 4
SIZE_BINS = (4, 16, 64)  # object pixels: survival is also given for [4, 16), [16, 64) and 64 or more
OBJECT_DILATION = 1
RING_WIDTH = 3


def dilate(mask: torch.Tensor, pixels: int) -> torch.Tensor:
    """(N, H, W) bool -> the mask grown by `pixels` in every direction (a square structuring element)."""
    if pixels <= 0:
        return mask
    return F.max_pool2d(mask[:, None].float(), 2 * pixels + 1, stride=1, padding=pixels)[:, 0] > 0


def _region_mean(images: torch.Tensor, region: torch.Tensor) -> torch.Tensor:
    """(N, 3, H, W), (N, H, W) bool -> (N, 3) mean colour over the region (NaN where it is empty)."""
    weights = region[:, None].float()
    return (images * weights).sum((2, 3)) / weights.sum((2, 3))


def psnr(pred: torch.Tensor, real: torch.Tensor, region: torch.Tensor | None = None) -> torch.Tensor:
    """(N, 3, H, W) images in [0, 1] -> (N,) PSNR in dB, over the whole frame or a (N, H, W) region."""
    error = (pred - real).pow(2).mean(1)  # (N, H, W)
    region = torch.ones_like(error, dtype=torch.bool) if region is None else region
    mse = (error * region).flatten(1).sum(1) / region.flatten(1).sum(1)
    return 10 * torch.log10(1 / mse.clamp_min(1e-10))


@torch.no_grad()
def frame_measures(pred: torch.Tensor, real: torch.Tensor, labels: torch.Tensor) -> dict[str, np.ndarray]:
    """Per frame: pred/real (N, 3, H, W) in [0, 1], labels (N, H, W) uint8 -> {"psnr", "object_psnr",
    "object_survives" (1.0/0.0), "object_pixels"}, the object's entries NaN where it covers < MIN_OBJECT_PIXELS."""
    pred, real = pred.float(), real.float()
    obj = labels == OBJECT
    pixels = obj.flatten(1).sum(1)
    seen = pixels >= MIN_OBJECT_PIXELS
    region = dilate(obj, OBJECT_DILATION)
    ring = dilate(region, RING_WIDTH) & ~region
    recon_colour = _region_mean(pred, obj)
    to_object = (recon_colour - _region_mean(real, obj)).norm(dim=1)
    to_background = (recon_colour - _region_mean(real, ring)).norm(dim=1)
    nan = torch.full_like(to_object, float("nan"))
    return {
        "psnr": psnr(pred, real).cpu().numpy(),
        "object_psnr": torch.where(seen, psnr(pred, real, region), nan).cpu().numpy(),
        "object_survives": torch.where(seen, (to_object < to_background).float(), nan).cpu().numpy(),
        "object_pixels": pixels.cpu().numpy(),
    }


def summarise(measures: dict[str, np.ndarray]) -> dict:
    """Means over frames of `frame_measures`' arrays (concatenated); object means over the frames that show it."""
    seen = measures["object_pixels"] >= MIN_OBJECT_PIXELS
    return {
        "psnr": float(np.mean(measures["psnr"])),
        "object_psnr": float(np.mean(measures["object_psnr"][seen])) if seen.any() else None,
        "object_survival": float(np.mean(measures["object_survives"][seen])) if seen.any() else None,
        "frames": int(len(seen)),
        "object_frames": int(seen.sum()),
        "object_survival_by_size": survival_by_size(measures),
    }


def survival_by_size(measures: dict[str, np.ndarray]) -> dict[str, dict]:
    """Object survival over the frames whose object covers each SIZE_BINS range of pixels: "lo-hi" -> {"frames",
    "survival"} (None for an empty range)."""
    edges = [*SIZE_BINS, np.inf]
    bins = {}
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        inside = (measures["object_pixels"] >= lo) & (measures["object_pixels"] < hi)
        name = f"{lo}-{int(hi) - 1} px" if hi < np.inf else f">= {lo} px"
        survival = float(np.mean(measures["object_survives"][inside])) if inside.any() else None
        bins[name] = {"frames": int(inside.sum()), "survival": survival}
    return bins


def codebook_use(indices: torch.Tensor, codebook_size: int) -> dict:
    """Codes of some frames (any shape) -> the share of the codebook they use and the codes' perplexity
    (exp of the entropy of their frequencies: the number of equally used codes with the same entropy)."""
    counts = torch.bincount(indices.flatten().long(), minlength=codebook_size).double()
    p = counts[counts > 0] / counts.sum()
    return {
        "used": int((counts > 0).sum()),
        "codebook_size": codebook_size,
        "share_used": float((counts > 0).double().mean()),
        "perplexity": float(torch.exp(-(p * p.log()).sum())),
    }
