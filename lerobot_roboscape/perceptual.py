"""Perceptual similarity, loaded without network access: LPIPS or the tokenizer-feature distance.

The `lpips` wheel ships only the small linear heads; the AlexNet/VGG trunk comes from torchvision's download,
which is not available offline. `load_lpips` builds the metric with an empty trunk and fills it from the torch
hub cache or a file the user names. A random trunk (not a perceptual metric) is used only when asked for.
`load_similarity` picks between LPIPS and `TokenizerPerceptualDistance`, which needs no download.
"""

import logging
import warnings
from pathlib import Path

import lpips
import torch
import torchvision
from torch import nn

from lerobot_roboscape.errors import InvalidInputError, MissingInputError
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.tokenizer.similarity import TokenizerPerceptualDistance

logger = logging.getLogger(__name__)

# torchvision's published trunk weights, as they are named in the torch hub cache.
TRUNK_FILES = {"alex": "alexnet-owt-7be5be79.pth", "vgg": "vgg16-397923af.pth"}
TRUNK_BUILDERS = {"alex": torchvision.models.alexnet, "vgg": torchvision.models.vgg16}
SIMILARITIES = ("auto", "lpips", "tokenizer")


class LPIPSTrunkMissingError(MissingInputError):
    pass


def default_trunk_path(net: str) -> Path:
    return Path(torch.hub.get_dir()) / "checkpoints" / TRUNK_FILES[net]


def _read_trunk_state_dict(path: Path) -> dict[str, torch.Tensor]:
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        return load_file(path)
    # weights_only refuses anything but tensors, so a .pth from torchvision loads without unpickling code.
    return torch.load(path, map_location="cpu", weights_only=True)


def load_lpips(
    net: str = "alex", trunk_path: str | Path | None = None, allow_random_trunk: bool = False
) -> lpips.LPIPS:
    """An `lpips.LPIPS` metric in eval mode with frozen weights. Inputs are images in [-1, 1], (B, 3, H, W).

    Args:
        net: "alex" or "vgg".
        trunk_path: torchvision's trunk weights (.pth or .safetensors); default: the torch hub cache.
        allow_random_trunk: use a random trunk when no weights are found (tests, offline demos).
    """
    if net not in TRUNK_FILES:
        raise InvalidInputError(f"LPIPS net must be one of {sorted(TRUNK_FILES)}, got {net!r}")
    with warnings.catch_warnings():  # lpips still calls torchvision with its deprecated `pretrained=` argument
        warnings.simplefilter("ignore", UserWarning)
        metric = lpips.LPIPS(net=net, pretrained=True, pnet_rand=True, verbose=False)
    path = Path(trunk_path) if trunk_path is not None else default_trunk_path(net)
    if path.is_file():
        state = _read_trunk_state_dict(path)
        features = TRUNK_BUILDERS[net]().features
        features.load_state_dict(
            {k.removeprefix("features."): v for k, v in state.items() if k.startswith("features.")}
        )
        # LPIPS splits the trunk's `features` into slices that keep the original layer indices as names.
        for slice_ in (getattr(metric.net, f"slice{i}") for i in range(1, metric.net.N_slices + 1)):
            for name, module in slice_.named_children():
                module.load_state_dict(features[int(name)].state_dict())
    elif trunk_path is not None:
        raise LPIPSTrunkMissingError(f"LPIPS trunk weights not found at {path}")
    elif allow_random_trunk:
        logger.warning(
            "LPIPS trunk weights not found at %s: using a random %s trunk (not a perceptual metric).", path, net
        )
    else:
        raise LPIPSTrunkMissingError(
            f"LPIPS needs torchvision's {net} weights at {path}. Copy {TRUNK_FILES[net]} there (or pass its path), "
            "or allow a random trunk explicitly (allow_random_lpips=true), which is not a perceptual metric."
        )
    metric.random_trunk = not path.is_file()
    # Reports name the similarity they used, and say when their LPIPS is not perceptual.
    metric.name = f"lpips ({net}, random trunk: not perceptual)" if metric.random_trunk else f"lpips ({net})"
    metric.eval().requires_grad_(False)
    return metric


def load_similarity(
    kind: str,
    tokenizer: VisualTokenizer | None,
    lpips_net: str = "alex",
    lpips_weights: str | Path | None = None,
    allow_random_lpips: bool = False,
) -> nn.Module:
    """The perceptual distance a reward or report should use, frozen and in eval mode.

    Every metric returned takes two (B, 3, H, W) image batches in [-1, 1] and returns (B, 1, 1, 1) distances, 0 for
    identical images, and has a `name` saying which similarity it is ("lpips (alex)", "tokenizer", ...).

    Args:
        kind: one of `SIMILARITIES`. "lpips": LPIPS (see `load_lpips`), refused without trunk weights unless
            `allow_random_lpips`. "tokenizer": `TokenizerPerceptualDistance` on `tokenizer`'s encoder. "auto": LPIPS
            when its trunk weights are found (`lpips_weights`, else the torch hub cache), else the tokenizer
            distance; it never picks a random trunk, and a named `lpips_weights` that is missing is an error.
        tokenizer: the trained tokenizer; needed by "tokenizer", and by "auto" when no LPIPS weights are found.
        lpips_net: LPIPS trunk, "alex" or "vgg".
        lpips_weights: torchvision's trunk weights (.pth or .safetensors); default: the torch hub cache.
        allow_random_lpips: with kind="lpips", use a random trunk when no weights are found (not perceptual).
    """
    if kind not in SIMILARITIES:
        raise InvalidInputError(f"similarity must be one of {SIMILARITIES}, got {kind!r}")
    if kind == "auto":
        cached = default_trunk_path(lpips_net)
        if lpips_weights is not None or cached.is_file():
            kind = "lpips"
            logger.info("Perceptual similarity (auto): LPIPS (%s) from %s", lpips_net, lpips_weights or cached)
        else:
            kind = "tokenizer"
            logger.info("Perceptual similarity (auto): tokenizer features (no LPIPS weights at %s)", cached)
    if kind == "lpips":
        return load_lpips(lpips_net, lpips_weights, allow_random_lpips)
    if tokenizer is None:
        raise InvalidInputError("the tokenizer similarity needs a trained tokenizer, got None")
    return TokenizerPerceptualDistance(tokenizer)
