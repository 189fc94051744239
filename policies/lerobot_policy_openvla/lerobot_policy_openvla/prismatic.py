"""OpenVLA's network (Prismatic VLM) built natively on timm and transformers.

    image (B, 3, H, W) in [0, 1]
      -> resize to 224, normalise twice (DINOv2's ImageNet statistics, SigLIP's 0.5/0.5), in fp32, then cast
      -> DINOv2 ViT-L/14-reg4 and SigLIP So400m/14 side by side, patch features of each one's second-to-last
         block, concatenated on channels (B, 256, 1024 + 1152)
      -> projector MLP to the LLM width (B, 256, 4096)
      -> Llama-2 reads [BOS, image patches, prompt tokens] and writes the action tokens.

The submodule names (`vision_backbone.featurizer`, `vision_backbone.fused_featurizer`, `projector.fc1..3`,
`language_model`) are the published checkpoint's, so its weights map onto this module almost one to one
(`checkpoint.py` holds the differences).
"""

from dataclasses import dataclass, field

import timm
import torch
import torch.nn.functional as F
from timm.models.vision_transformer import VisionTransformer
from torch import Tensor, nn
from transformers import LlamaConfig, LlamaForCausalLM

# ImageNet statistics as the published processor stores them (rounded to bf16 when it was converted); SigLIP's
# are 0.5 / 0.5.
DINO_MEAN = (0.484375, 0.455078125, 0.40625)
DINO_STD = (0.228515625, 0.2236328125, 0.224609375)


@dataclass
class PrismaticArchitecture:
    """Everything needed to build the network; read from a checkpoint's config.json (`checkpoint.py`).

    Args:
        timm_model_ids: timm names of the featurizer (DINOv2) and the fused featurizer (SigLIP).
        vision_overrides: keyword arguments for each timm model beyond the published ones (tiny sizes only).
        image_size: side of the square input image.
        llm: the Llama config (transformers' `LlamaConfig.to_dict()`).
    """

    timm_model_ids: tuple[str, str] = ("vit_large_patch14_reg4_dinov2.lvd142m", "vit_so400m_patch14_siglip_224")
    vision_overrides: tuple[dict, dict] = field(default_factory=lambda: ({}, {}))
    image_size: int = 224
    llm: dict = field(default_factory=dict)


class PrismaticVisionBackbone(nn.Module):
    def __init__(self, arch: PrismaticArchitecture):
        super().__init__()
        dino_id, siglip_id = arch.timm_model_ids
        dino_kwargs, siglip_kwargs = arch.vision_overrides
        common = dict(pretrained=False, num_classes=0, img_size=arch.image_size)
        self.featurizer: VisionTransformer = timm.create_model(dino_id, **common, **dino_kwargs)
        self.fused_featurizer: VisionTransformer = timm.create_model(siglip_id, **common, **siglip_kwargs)
        self.image_size = arch.image_size
        # Exact in bf16 too (they were rounded to it), so a cast of the module keeps their values.
        self.register_buffer("dino_mean", torch.tensor(DINO_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("dino_std", torch.tensor(DINO_STD).view(1, 3, 1, 1), persistent=False)

    @property
    def embed_dim(self) -> int:
        return self.featurizer.embed_dim + self.fused_featurizer.embed_dim

    def preprocess(self, images_B3HW: Tensor) -> tuple[Tensor, Tensor]:
        """Images in [0, 1] -> the two normalised 224 px inputs (OpenVLA's "resize-naive" strategy), computed
        in fp32 as OpenVLA's image processor does, then cast to the weights' dtype."""
        dtype = self.featurizer.patch_embed.proj.weight.dtype
        images_B3HW = images_B3HW.float()
        size = (self.image_size, self.image_size)
        if images_B3HW.shape[-2:] != size:
            images_B3HW = F.interpolate(images_B3HW, size=size, mode="bicubic", antialias=True).clamp(0, 1)
        dino = (images_B3HW - self.dino_mean.float()) / self.dino_std.float()
        siglip = (images_B3HW - 0.5) / 0.5
        return dino.to(dtype), siglip.to(dtype)

    def forward(self, images_B3HW: Tensor) -> Tensor:
        """(B, 3, H, W) in [0, 1] -> patch features (B, N, D_dino + D_siglip)."""
        dino, siglip = self.preprocess(images_B3HW)
        patches = [
            model.get_intermediate_layers(pixels, n=[len(model.blocks) - 2])[0]  # (B, N, D), second-to-last
            for model, pixels in ((self.featurizer, dino), (self.fused_featurizer, siglip))
        ]
        return torch.cat(patches, dim=-1)


class PrismaticProjector(nn.Module):
    """Fused-backbone projector: vision D -> 4D -> LLM width -> LLM width, GELU between."""

    def __init__(self, vision_dim: int, llm_dim: int):
        super().__init__()
        self.fc1 = nn.Linear(vision_dim, 4 * vision_dim)
        self.fc2 = nn.Linear(4 * vision_dim, llm_dim)
        self.fc3 = nn.Linear(llm_dim, llm_dim)

    def forward(self, patches_BND: Tensor) -> Tensor:
        return self.fc3(F.gelu(self.fc2(F.gelu(self.fc1(patches_BND)))))


class PrismaticVLA(nn.Module):
    def __init__(self, arch: PrismaticArchitecture):
        super().__init__()
        self.vision_backbone = PrismaticVisionBackbone(arch)
        llm_config = LlamaConfig(**arch.llm)
        self.projector = PrismaticProjector(self.vision_backbone.embed_dim, llm_config.hidden_size)
        self.language_model = LlamaForCausalLM(llm_config)

    def embed(self, images_B3HW: Tensor, input_ids_BL: Tensor, attention_mask_BL: Tensor) -> tuple[Tensor, ...]:
        """Sequence [BOS, image patches, rest of input_ids]: (embeddings (B, L', C), mask (B, L'), positions).

        Positions count only unmasked tokens, so left padding inside the text (after the patches) changes
        nothing for the real tokens and every sequence of a batch ends at the same index.
        """
        patches = self.projector(self.vision_backbone(images_B3HW))  # (B, N, C)
        tokens = self.language_model.get_input_embeddings()(input_ids_BL)  # (B, L, C)
        embeddings = torch.cat([tokens[:, :1], patches.to(tokens.dtype), tokens[:, 1:]], dim=1)
        patch_mask = attention_mask_BL.new_ones(patches.shape[:2])
        mask = torch.cat([attention_mask_BL[:, :1], patch_mask, attention_mask_BL[:, 1:]], dim=1)
        return embeddings, mask, (mask.cumsum(-1) - 1).clamp(min=0)
