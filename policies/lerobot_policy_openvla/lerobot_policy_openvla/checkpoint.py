"""Load OpenVLA checkpoints in the published layout of `openvla/openvla-7b` (config.json, sharded safetensors
with an index, a Llama tokenizer), and make tiny ones in the same layout.

The published weights come from OpenVLA's remote code, which renamed timm's LayerScale parameter `gamma` to
`scale_factor` (transformers used to rewrite any key containing "gamma"); that rename is the only difference
between its keys and `PrismaticVLA`'s. Loading is exact: a missing, unexpected or misshapen key is an error.
"""

import contextlib
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import torch
from huggingface_hub import hf_hub_download, snapshot_download
from safetensors import safe_open
from safetensors.torch import save_file
from tokenizers import Tokenizer, decoders, models, normalizers, processors
from transformers import LlamaTokenizerFast, PreTrainedTokenizerBase

from lerobot_policy_openvla.prismatic import PrismaticArchitecture, PrismaticVLA
from roboscape_core.errors import InvalidInputError

TINY = "tiny"
RANDOM_7B = "random-7b"
CHECKPOINT_PATTERNS = ["*.json", "*.safetensors", "tokenizer.model"]
SPIECE_SPACE = "\u2581"  # sentencepiece's word boundary, token 29871 in Llama-2


class OpenVLACheckpointError(InvalidInputError):
    """A checkpoint whose files or tensors do not match the published layout."""


@dataclass
class OpenVLACheckpoint:
    path: str  # where it came from (local dir, Hub id or "tiny")
    config: dict  # the published config.json
    state_dict: dict[str, torch.Tensor] | None  # published key names; None: random weights (a preset)
    tokenizer: PreTrainedTokenizerBase
    init_seed: int = 0  # of the random weights

    @property
    def architecture(self) -> PrismaticArchitecture:
        return architecture_from_config(self.config, self.path)

    @property
    def norm_stats(self) -> dict:
        return self.config.get("norm_stats") or {}


def checkpoint_key_to_module_key(key: str) -> str:
    return re.sub(r"\.ls([12])\.scale_factor$", r".ls\1.gamma", key)


def module_key_to_checkpoint_key(key: str) -> str:
    return re.sub(r"\.ls([12])\.gamma$", r".ls\1.scale_factor", key)


def checkpoint_state_dict(vla: PrismaticVLA) -> dict[str, torch.Tensor]:
    """The network's weights under the published checkpoint's names (what `build_vla` reads back)."""
    return {module_key_to_checkpoint_key(key): tensor for key, tensor in vla.state_dict().items()}


def select_action_stats(norm_stats: dict, unnorm_key: str | None, source: str) -> dict:
    """The action statistics (q01, q99, mask, ...) of one dataset of a checkpoint's `norm_stats`, chosen as
    OpenVLA's `predict_action` chooses them: `unnorm_key`, or the only dataset when there is one."""
    names = sorted(norm_stats)
    if unnorm_key is None:
        if len(names) != 1:
            raise InvalidInputError(
                f"{source} was trained on {len(names)} datasets: pass --policy.unnorm_key=<one of {names}> to "
                f"choose the statistics that un-normalise its actions"
            )
        unnorm_key = names[0]
    if unnorm_key not in norm_stats:
        raise InvalidInputError(f"unnorm_key={unnorm_key!r} is not among the datasets of {source}: {names}")
    return norm_stats[unnorm_key]["action"]


def architecture_from_config(config: dict, source: str) -> PrismaticArchitecture:
    if config.get("model_type") != "openvla":
        raise OpenVLACheckpointError(
            f"{source}: config.json has model_type={config.get('model_type')!r}, expected 'openvla'"
        )
    if not config.get("use_fused_vision_backbone", False):
        raise OpenVLACheckpointError(f"{source}: only the fused DINOv2 + SigLIP backbone is supported")
    if config.get("arch_specifier") != "no-align+fused-gelu-mlp":
        raise OpenVLACheckpointError(f"{source}: unsupported projector {config.get('arch_specifier')!r}")
    overrides = config.get("timm_model_kwargs") or [{}, {}]  # absent from published configs: tiny ones only
    sizes = set(config["image_sizes"])
    if len(sizes) != 1:
        raise OpenVLACheckpointError(f"{source}: both backbones must see one image size, got {sizes}")
    return PrismaticArchitecture(
        timm_model_ids=tuple(config["timm_model_ids"]),
        vision_overrides=tuple(overrides),
        image_size=sizes.pop(),
        llm=dict(config.get("text_config") or {}),
    )


def read_checkpoint(name_or_path: str, revision: str | None = None, init_seed: int = 0) -> OpenVLACheckpoint:
    """A local directory, a Hub repo id (downloaded once, then read from the cache), or a random preset:
    "tiny" (toy sizes) or "random-7b" (the published sizes, for memory and speed measurements)."""
    if name_or_path in RANDOM_PRESETS:
        return OpenVLACheckpoint(name_or_path, RANDOM_PRESETS[name_or_path](), None, tiny_tokenizer(), init_seed)
    path = Path(name_or_path)
    if not path.is_dir():
        path = from_hub(name_or_path, revision)
    config = read_config_file(path / "config.json")
    tokenizer = LlamaTokenizerFast.from_pretrained(path)
    return OpenVLACheckpoint(str(name_or_path), config, read_safetensors(path), tokenizer)


def read_config(name_or_path: str, revision: str | None = None) -> dict:
    """A checkpoint's config.json (or a random preset's) without its weights, e.g. for its `norm_stats`."""
    if name_or_path in RANDOM_PRESETS:
        return RANDOM_PRESETS[name_or_path]()
    path = Path(name_or_path)
    if path.is_dir():
        return read_config_file(path / "config.json")
    return read_config_file(from_hub(name_or_path, revision, filename="config.json"))


def from_hub(repo_id: str, revision: str | None, filename: str | None = None) -> Path:
    """The checkpoint's folder (or one file of it) in the Hub cache, downloaded the first time."""
    try:
        if filename is not None:
            return Path(hf_hub_download(repo_id, filename, revision=revision))
        return Path(snapshot_download(repo_id, revision=revision, allow_patterns=CHECKPOINT_PATTERNS))
    except Exception as error:
        raise OpenVLACheckpointError(
            f"OpenVLA base checkpoint {repo_id!r} is neither a local directory nor downloadable from the Hub "
            f"({type(error).__name__}: {error}). Pass --policy.base_model=<dir or repo id>, or "
            f"--policy.base_model=tiny for the random tiny preset."
        ) from error


def read_config_file(config_file: Path) -> dict:
    if not config_file.exists():
        raise OpenVLACheckpointError(f"{config_file.parent} has no config.json: not an OpenVLA checkpoint")
    return json.loads(config_file.read_text())


def read_safetensors(path: Path) -> dict[str, torch.Tensor]:
    index = path / "model.safetensors.index.json"
    if index.exists():
        shards = sorted(set(json.loads(index.read_text())["weight_map"].values()))
    elif (path / "model.safetensors").exists():
        shards = ["model.safetensors"]
    else:
        raise OpenVLACheckpointError(f"{path} has neither model.safetensors nor model.safetensors.index.json")
    state_dict = {}
    for shard in shards:
        with safe_open(path / shard, framework="pt") as file:
            state_dict.update({key: file.get_tensor(key) for key in file.keys()})
    return state_dict


@contextlib.contextmanager
def default_dtype(dtype: torch.dtype):
    previous = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        yield
    finally:
        torch.set_default_dtype(previous)


def build_vla(checkpoint: OpenVLACheckpoint, device: str | torch.device, dtype: torch.dtype) -> PrismaticVLA:
    """Build the network on `device` in `dtype` and copy the checkpoint's weights in, checking every key (or
    draw them from `init_seed` for a random preset)."""
    device = torch.device(device)
    if checkpoint.state_dict is None:
        accelerators = [] if device.type == "cpu" else None  # None: every device of device_type
        rng = torch.random.fork_rng(devices=accelerators, device_type="cuda" if device.type == "cpu" else device.type)
        with rng, torch.device(device), default_dtype(dtype):
            torch.manual_seed(checkpoint.init_seed)
            return PrismaticVLA(checkpoint.architecture)
    with torch.device(device), default_dtype(dtype):
        vla = PrismaticVLA(checkpoint.architecture)
    expected = checkpoint_state_dict(vla)
    missing = sorted(set(expected) - set(checkpoint.state_dict))
    unexpected = sorted(set(checkpoint.state_dict) - set(expected))
    misshapen = [
        f"{key}: checkpoint {tuple(checkpoint.state_dict[key].shape)} vs model {tuple(expected[key].shape)}"
        for key in sorted(set(expected) & set(checkpoint.state_dict))
        if checkpoint.state_dict[key].shape != expected[key].shape
    ]
    if missing or unexpected or misshapen:
        raise OpenVLACheckpointError(
            f"{checkpoint.path}: weights do not match the OpenVLA architecture of its config.json. "
            f"missing={missing[:10]} ({len(missing)}), unexpected={unexpected[:10]} ({len(unexpected)}), "
            f"misshapen={misshapen[:10]}"
        )
    mapped = {checkpoint_key_to_module_key(key): tensor for key, tensor in checkpoint.state_dict.items()}
    vla.load_state_dict(mapped, strict=True)
    return vla


# Random presets: the published config.json, at its own sizes or at toy sizes. The tiny one's larger
# initializer_range lets a 64-wide model behind its frozen random LM head reach confident action tokens.


def published_config() -> dict:
    """openvla/openvla-7b's config.json without its 25 datasets' norm_stats."""
    return {
        "architectures": ["OpenVLAForActionPrediction"],
        "model_type": "openvla",
        "vision_backbone_id": "dinosiglip-vit-so-224px",
        "llm_backbone_id": "llama2-7b-pure",
        "hf_llm_id": "meta-llama/Llama-2-7b-hf",
        "arch_specifier": "no-align+fused-gelu-mlp",
        "use_fused_vision_backbone": True,
        "image_resize_strategy": "resize-naive",
        "image_sizes": [224, 224],
        "timm_model_ids": ["vit_large_patch14_reg4_dinov2.lvd142m", "vit_so400m_patch14_siglip_224"],
        "timm_override_act_layers": [None, None],
        "text_config": {"model_type": "llama", "pad_token_id": 32000, "torch_dtype": "bfloat16", "vocab_size": 32064},
        "llm_max_length": 2048,
        "pad_token_id": 32000,
        "pad_to_multiple_of": 64,
        "n_action_bins": 256,
        "norm_stats": {},
        "output_projector_states": False,
        "torch_dtype": "bfloat16",
    }


TINY_VISION = [{"embed_dim": 32, "depth": 3, "num_heads": 2}, {"embed_dim": 48, "depth": 3, "num_heads": 2}]
TINY_LLM = dict(
    vocab_size=32064,
    hidden_size=64,
    intermediate_size=128,
    num_hidden_layers=2,
    num_attention_heads=2,
    num_key_value_heads=2,
    max_position_embeddings=512,
    rms_norm_eps=1e-6,
    pad_token_id=32000,
    initializer_range=0.1,
)


def tiny_config() -> dict:
    return {
        **published_config(),
        "timm_model_kwargs": TINY_VISION,
        "llm_max_length": 512,
        "text_config": {"model_type": "llama", **TINY_LLM},
        "torch_dtype": "float32",
    }


RANDOM_PRESETS = {TINY: tiny_config, RANDOM_7B: published_config}


def tiny_checkpoint(seed: int = 0) -> OpenVLACheckpoint:
    """The tiny preset with its weights drawn and renamed to the published keys (to write or test loading)."""
    preset = read_checkpoint(TINY, init_seed=seed)
    vla = build_vla(preset, "cpu", torch.float32)
    return OpenVLACheckpoint(TINY, preset.config, checkpoint_state_dict(vla), preset.tokenizer)


def tiny_tokenizer() -> LlamaTokenizerFast:
    """A Llama-2-shaped tokenizer (32000 ids, <unk>/<s>/</s> at 0/1/2, byte fallback, <PAD> at 32000) whose
    vocabulary is bytes, characters and placeholders: no sentencepiece model needed."""
    vocab = {"<unk>": 0, "<s>": 1, "</s>": 2}
    vocab.update({f"<0x{b:02X}>": 3 + b for b in range(256)})
    for char in SPIECE_SPACE + "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789:?.,'-":
        vocab[char] = len(vocab)
    vocab.update({f"<unused{i}>": i for i in range(len(vocab), 32000)})
    tokenizer = Tokenizer(models.BPE(vocab=vocab, merges=[], unk_token="<unk>", byte_fallback=True))
    tokenizer.normalizer = normalizers.Sequence(
        [normalizers.Prepend(SPIECE_SPACE), normalizers.Replace(" ", SPIECE_SPACE)]
    )
    tokenizer.decoder = decoders.Sequence(
        [decoders.Replace(SPIECE_SPACE, " "), decoders.ByteFallback(), decoders.Fuse(), decoders.Strip(" ", 1, 0)]
    )
    tokenizer.post_processor = processors.TemplateProcessing(single="<s> $A", special_tokens=[("<s>", 1)])
    fast = LlamaTokenizerFast(
        tokenizer_object=tokenizer,
        bos_token="<s>",
        eos_token="</s>",
        unk_token="<unk>",
        padding_side="right",
        model_max_length=512,
    )
    fast.add_special_tokens({"pad_token": "<PAD>"})
    return fast


def write_checkpoint(checkpoint: OpenVLACheckpoint, directory: str | Path, max_shard_bytes: int = 2**20) -> Path:
    """Write `checkpoint` as the Hub repo is laid out: config.json, model-0000k-of-0000n.safetensors shards with
    model.safetensors.index.json, and the tokenizer files. Written to a temporary folder, then moved."""
    directory = Path(directory)
    staging = directory.with_name(directory.name + ".tmp")
    staging.mkdir(parents=True, exist_ok=False)
    shards, current, size = [], {}, 0
    for key, tensor in checkpoint.state_dict.items():
        if current and size + tensor.nbytes > max_shard_bytes:
            shards.append(current)
            current, size = {}, 0
        current[key], size = tensor.contiguous(), size + tensor.nbytes
    shards.append(current)
    weight_map = {}
    for k, shard in enumerate(shards, start=1):
        name = f"model-{k:05d}-of-{len(shards):05d}.safetensors"
        save_file(shard, staging / name, metadata={"format": "pt"})
        weight_map.update(dict.fromkeys(shard, name))
    total = sum(tensor.nbytes for tensor in checkpoint.state_dict.values())
    index = {"metadata": {"total_size": total}, "weight_map": weight_map}
    (staging / "model.safetensors.index.json").write_text(json.dumps(index, indent=2))
    (staging / "config.json").write_text(json.dumps(checkpoint.config, indent=2))
    checkpoint.tokenizer.save_pretrained(staging)
    os.replace(staging, directory)
    return directory
