"""Measures that see the arm, of the rollouts of one controllability start (world_model/measures/controllability.py): a
model can keep the table and lose the arm and still score well on the whole frame.

- the state (a model with a state channel): the TCP position the rollout predicts against the simulator's, at the
  horizon's last frame (median, in cm and as a share of the distance the real TCP moved from the start), and the
  retrieval by state (each rollout's predicted TCP path nearest its own future's);
- the arm region's PSNR: each rollout against its own future inside the robot's mask (dilated as the object's),
  beside the tokenizer's reconstruction of the real future in the same region (the best a rollout can do);
- the motion ratio: the rollout's mean change from frame to frame over the real future's. A model that stops moving
  keeps a good PSNR; this ratio falls towards 0;
- the scene's PSNR (outside the arm's region) over the frames generated while the start was in the model's window and
  over those generated after it left, with the arm's PSNR there: a rollout that drifts once it no longer sees the
  real start loses the scene past its window (issue 72).
"""

import numpy as np
import torch

from lerobot_roboscape.dataset.segmentation import ROBOT
from lerobot_roboscape.metrics.image_fidelity import OBJECT_DILATION, dilate, psnr
from lerobot_roboscape.robot import TCP_POSITION
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.world_model.measures.retrieval import retrieval_accuracy


@torch.no_grad()
def arm_measures(tokenizer: VisualTokenizer, start, pred, predicted_states, window: int) -> dict:
    """The measures that see the arm, of the K rollouts (K, T, n, 3, H, W) of one start by a model that sees
    `window` frames: the arm region's PSNR (rollout and tokenizer, mean over the sequences), the motion ratio, the
    scene's and the arm's PSNR in and past the window (where the horizon reaches it), and with predicted states
    (K, T, D) the TCP's error at the last frame (per sequence, metres), the distance the real TCP moved (per sequence)
    and the retrieval by state."""
    K, T, n = pred.shape[:3]
    real = start.real.float() / 255
    region = dilate((start.masks == ROBOT).flatten(0, 2), OBJECT_DILATION).unflatten(0, (K, T, n))
    recon = torch.stack(
        [tokenizer.decode_views(tokenizer.encode_views([real[j, :, c] for c in range(n)]), n) for j in range(K)]
    )
    seen = region.flatten(3).sum(3) > 0  # (K, T, n): views where the arm is
    out = {}
    for name, images in (("arm_psnr", pred), ("arm_psnr_tokenizer", recon)):
        values = psnr(images[seen], real[seen], region[seen])
        out[name] = float(values.mean()) if seen.any() else float("nan")
    if T > 1:
        change = lambda x: (x[:, 1:] - x[:, :-1]).abs().mean()  # noqa: E731
        out["motion_ratio"] = float(change(pred) / change(real).clamp_min(1e-6))
    out.update(_in_and_past_window(pred, real, region, seen, window))
    if predicted_states is not None:
        tcp_pred, tcp_real = predicted_states[..., TCP_POSITION].float(), start.states[..., TCP_POSITION].float()
        out["tcp_error_m"] = (tcp_pred[:, -1] - tcp_real[:, -1]).norm(dim=-1).tolist()
        out["tcp_moved_m"] = (tcp_real[:, -1] - start.first_state[:, TCP_POSITION].float()).norm(dim=-1).tolist()
        distance = (tcp_pred[:, None] - tcp_real[None]).norm(dim=-1).mean(-1)  # (K, K): rollout i, future j
        out["retrieval_state"] = retrieval_accuracy(-distance.cpu().numpy())
    return out


def _in_and_past_window(pred, real, region, seen, window: int) -> dict[str, float]:
    """Frame t of the rollouts (the start's frame t + 1) is generated with the start in its window while
    t + 1 < window: the scene's PSNR (outside the arm's region) over those frames and over the rest, and the arm's
    PSNR over the rest."""
    T = pred.shape[1]
    out = {}
    for name, frames in (("in_window", slice(0, window - 1)), ("past_window", slice(window - 1, T))):
        p, r, arm = pred[:, frames].flatten(0, 2), real[:, frames].flatten(0, 2), region[:, frames].flatten(0, 2)
        if len(p):
            out[f"scene_psnr_{name}"] = float(psnr(p, r, ~arm).mean())
    late = seen[:, window - 1 :]
    if late.any():
        values = psnr(pred[:, window - 1 :][late], real[:, window - 1 :][late], region[:, window - 1 :][late])
        out["arm_psnr_past_window"] = float(values.mean())
    return out


def summarise_arm(measured: list[dict]) -> dict[str, float]:
    """The arm's measures over starts: mean PSNRs (the arm's, the scene's) and motion ratio; the TCP's median error
    (cm) and its median share of the distance the real TCP moved; mean retrieval by state."""
    out = {}
    for name in (
        "arm_psnr",
        "arm_psnr_tokenizer",
        "motion_ratio",
        "retrieval_state",
        "scene_psnr_in_window",
        "scene_psnr_past_window",
        "arm_psnr_past_window",
    ):
        values = [m[name] for m in measured if name in m and not np.isnan(m[name])]
        if values:
            out[name] = float(np.mean(values))
    if any("tcp_error_m" in m for m in measured):
        error = np.concatenate([m["tcp_error_m"] for m in measured])
        moved = np.concatenate([m["tcp_moved_m"] for m in measured])
        out["tcp_error_cm"] = float(np.median(error) * 100)
        out["tcp_error_share_of_moved"] = float(np.median(error / np.maximum(moved, 1e-3)))
    return out
