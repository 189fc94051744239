"""LPIPS, loaded without network access.

The `lpips` wheel ships only the small linear heads; the AlexNet/VGG trunk comes from torchvision's download,
which is not available offline. `load_lpips` builds the metric with an empty trunk and fills it from the torch
hub cache or a file the user names. A random trunk (not a perceptual metric) is used only when asked for.
`tokenizer.similarity.load_similarity` picks between LPIPS and the tokenizer-feature distance.
"""

import logging
import warnings
from pathlib import Path

import lpips
import torch
import torchvision

from lerobot_roboscape.io.console import say_once
from roboscape_core.errors import InvalidInputError, MissingInputError

logger = logging.getLogger(__name__)
# Each env, report and training run loads LPIPS: a missing trunk is said once.
say_once(__name__)

# torchvision's published trunk weights, as they are named in the torch hub cache.
TRUNK_FILES = {"alex": "alexnet-owt-7be5be79.pth", "vgg": "vgg16-397923af.pth"}
TRUNK_BUILDERS = {"alex": torchvision.models.alexnet, "vgg": torchvision.models.vgg16}
RANDOM_TRUNK_SEED = 0


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
    # A random trunk is the same in every process, and building it leaves the caller's random stream alone: a
    # report resumed in a new process measures what an uninterrupted run measures.
    with warnings.catch_warnings(), torch.random.fork_rng(devices=[]):
        warnings.simplefilter("ignore", UserWarning)  # lpips still calls torchvision with `pretrained=`
        torch.manual_seed(RANDOM_TRUNK_SEED)
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
