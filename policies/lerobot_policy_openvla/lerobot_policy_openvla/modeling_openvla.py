"""OpenVLA as a LeRobot policy: SFT by next-token prediction of the action tokens (`forward`), greedy actions
for evaluation (`select_action`), and RL4VLA's actor-critic for PPO (`sample_action`, `evaluate_actions`).

Every pass reads one sequence layout, [BOS, image patches, <pad>..., prompt, action tokens]: prompts are padded
on the left of the text (masked, positions skip the pads) so all prompts of a batch end at the same index P.
Action token k is predicted at P + k, and the value head reads the hidden state at P.
"""

import torch
import torch.nn.functional as F
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION, OBS_IMAGES
from peft import LoraConfig, inject_adapter_in_model
from safetensors import safe_open
from safetensors.torch import save_file
from torch import Tensor, nn
from torch.distributions import Categorical

from lerobot_policy_openvla.action_tokenizer import OpenVLAActionTokenizer
from lerobot_policy_openvla.checkpoint import SPIECE_SPACE, OpenVLACheckpointError, build_vla, read_checkpoint
from lerobot_policy_openvla.configuration_openvla import OpenVLAConfig
from roboscape_core.actor_critic import ActionEvaluation, PolicySample, scale_gradient

ACTION_DIM = 7
SAFETENSORS_FILE = "model.safetensors"


def openvla_prompt(instruction: str) -> str:
    """OpenVLA's prompt; the model was trained on lower-case instructions."""
    return f"In: What action should the robot take to {instruction.lower()}?\nOut:"


class OpenVLAPolicy(PreTrainedPolicy):
    config_class = OpenVLAConfig
    name = "openvla"

    def __init__(self, config: OpenVLAConfig, **kwargs):
        super().__init__(config)
        config.validate_features()
        self.config = config
        dtype = resolve_dtype(config.dtype, config.device)
        checkpoint = read_checkpoint(config.base_model, config.base_revision, init_seed=config.init_seed)
        self.tokenizer = checkpoint.tokenizer
        self.action_tokenizer = OpenVLAActionTokenizer(n_bins=256, vocab_size=self.tokenizer.vocab_size)
        self.space_token_id = self.tokenizer.convert_tokens_to_ids(SPIECE_SPACE)
        self.image_shape = tuple(config.input_features[config.camera].shape)
        self.vla = build_vla(checkpoint, config.device or "cpu", dtype)
        del checkpoint  # the weights now live in self.vla

        inject_adapter_in_model(self.lora_config(), self.vla)
        for name, parameter in self.vla.named_parameters():
            parameter.requires_grad_("lora_" in name)
            if "lora_" in name:
                parameter.data = parameter.data.float()  # adapters train in fp32 on a bf16 base
        self.value_head = OpenVLAValueHead(self.vla.language_model.config.hidden_size, config.value_head_dims)
        self.value_head.to(config.device or "cpu")
        if config.gradient_checkpointing:
            language_model = self.vla.language_model
            # transformers renamed the switch within 5.x; the plugin allows every 5.x, so it takes either name
            enable = getattr(language_model, "activation_checkpointing_enable", None)
            enable = enable or language_model.gradient_checkpointing_enable
            enable({"use_reentrant": False})
            self.vla.vision_backbone.featurizer.set_grad_checkpointing(True)
            self.vla.vision_backbone.fused_featurizer.set_grad_checkpointing(True)

    def lora_config(self) -> LoraConfig:
        """OpenVLA's finetune.py adapter: peft's "all-linear" (every linear layer but the output one, the LM
        head), gaussian-initialised as there and in RL4VLA (A ~ N(0, 1/r^2), B = 0)."""
        targets = self.config.lora_target_modules
        if targets == ["all-linear"]:
            # peft's "all-linear" minus SigLIP's attention-pool head, which the forward pass never reads (its
            # adapter would stay at its initial value). The LM head is left out, as peft leaves it out.
            targets = [
                name
                for name, module in self.vla.named_modules()
                if isinstance(module, nn.Linear) and name != "language_model.lm_head" and "attn_pool" not in name
            ]
        return LoraConfig(
            r=self.config.lora_r,
            lora_alpha=self.config.lora_alpha,
            lora_dropout=self.config.lora_dropout,
            target_modules=targets,
            init_lora_weights="gaussian",
        )

    # Checkpoints hold the trainable weights only: the LoRA adapter and the value head.

    def trainable_state_dict(self) -> dict[str, Tensor]:
        return {name: p.detach() for name, p in self.named_parameters() if p.requires_grad}

    def _save_pretrained(self, save_directory, state_dict=None) -> None:
        self.config._save_pretrained(save_directory)
        tensors = {name: t.contiguous() for name, t in self.trainable_state_dict().items()}
        metadata = {"format": "pt", "base_model": self.config.base_model}
        save_file(tensors, str(save_directory / SAFETENSORS_FILE), metadata=metadata)

    @classmethod
    def _load_as_safetensor(cls, model: "OpenVLAPolicy", model_file: str, map_location: str, strict: bool):
        expected = set(model.trainable_state_dict())
        with safe_open(model_file, framework="pt", device=str(map_location)) as file:
            tensors = {key: file.get_tensor(key) for key in file.keys()}
        missing, unexpected = sorted(expected - set(tensors)), sorted(set(tensors) - expected)
        if missing or unexpected:
            raise OpenVLACheckpointError(
                f"{model_file} does not fit this policy's adapter (base {model.config.base_model!r}, LoRA r="
                f"{model.config.lora_r}, targets {model.config.lora_target_modules}): missing {missing[:5]} "
                f"({len(missing)}), unexpected {unexpected[:5]} ({len(unexpected)})"
            )
        model.load_state_dict(tensors, strict=False)
        return model

    def wrap_with_peft(self, peft_config=None, peft_cli_overrides=None):
        raise ValueError(
            "openvla applies LoRA itself: use --policy.lora_r/lora_alpha/lora_target_modules, not --peft.*"
        )

    # LeRobot's policy API.

    def get_optim_params(self) -> list[dict]:
        return [{"params": [p for p in self.parameters() if p.requires_grad]}]

    def reset(self):
        pass  # no observation history, no action queue

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """SFT: cross-entropy of the 7 action tokens and the closing </s> given image and prompt (OpenVLA)."""
        target_ids = self.action_tokenizer.encode(batch[ACTION])  # (B, 7)
        eos = torch.full_like(target_ids[:, :1], self.tokenizer.eos_token_id)
        suffix = torch.cat([target_ids, eos], dim=1)  # (B, 8)
        logits, _ = self.predict_suffix(batch, suffix)  # (B, 8, V)
        loss = F.cross_entropy(logits.flatten(0, 1).float(), suffix.flatten())
        predicted = logits[:, :ACTION_DIM].argmax(-1)
        accuracy = (predicted == target_ids).float().mean()
        l1 = (self.action_tokenizer.decode(predicted) - self.action_tokenizer.decode(target_ids)).abs().mean()
        return loss, {"action_accuracy": accuracy.item(), "action_l1": l1.item()}

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        return self.select_action(batch).unsqueeze(1)  # (B, 1, 7)

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """Greedy action tokens -> normalised actions (B, 7): OpenVLA's float64 bin centres, which the
        postprocessor un-normalises as `predict_action` does."""
        slots, _, _ = self.generate_action_slots(batch, greedy=True)
        return self.action_tokenizer.decode(self.action_tokenizer.slots_to_action_ids(slots))

    # What PPO needs (lerobot_roboscape.rl.ActorCritic), as RL4VLA computes it.

    def sample_action(self, batch: dict) -> PolicySample:
        slots, log_prob, value = self.generate_action_slots(batch, greedy=False)
        action = self.action_tokenizer.decode(self.action_tokenizer.slots_to_action_ids(slots))
        return PolicySample(action, slots, log_prob, value)

    def evaluate_actions(self, batch: dict, raw_action: Tensor) -> ActionEvaluation:
        logits, hidden = self.predict_suffix(batch, self.action_tokenizer.slots_to_action_ids(raw_action))
        distribution = Categorical(logits=self.action_logits(logits))  # batch shape (B, 7)
        return ActionEvaluation(
            log_prob=distribution.log_prob(raw_action).sum(-1),
            entropy=distribution.entropy().sum(-1),
            value=self.value(hidden),
        )

    def predict_value(self, batch: dict) -> Tensor:
        input_ids, mask = self.prompt_ids(batch)
        embeddings, mask, positions = self.vla.embed(self.image(batch), input_ids, mask)
        output = self.vla.language_model.model(
            inputs_embeds=embeddings, attention_mask=mask, position_ids=positions, use_cache=False
        )
        return self.value(output.last_hidden_state[:, -1])

    # Internals.

    def action_logits(self, logits: Tensor) -> Tensor:
        """Full-vocabulary logits (..., V) -> the 256 action tokens' logits at the sampling temperature."""
        first = self.action_tokenizer.first_token_id
        return logits[..., first : first + self.action_tokenizer.n_bins].float() / self.config.temperature

    def value(self, hidden_BC: Tensor) -> Tensor:
        return self.value_head(scale_gradient(hidden_BC.float(), self.config.value_grad_scale))

    def predict_suffix(self, batch: dict, suffix_ids: Tensor) -> tuple[Tensor, Tensor]:
        """Teacher-forced pass over prompt + `suffix_ids` (B, K): the logits predicting each suffix token
        (B, K, V) and the hidden state of the last prompt token (B, C)."""
        input_ids, mask = self.prompt_ids(batch)
        input_ids = torch.cat([input_ids, suffix_ids], dim=1)
        mask = torch.cat([mask, torch.ones_like(suffix_ids)], dim=1)
        embeddings, mask, positions = self.vla.embed(self.image(batch), input_ids, mask)
        output = self.vla.language_model(
            inputs_embeds=embeddings,
            attention_mask=mask,
            position_ids=positions,
            output_hidden_states=True,
            use_cache=False,
        )
        n = suffix_ids.shape[1]
        prompt_end = embeddings.shape[1] - n - 1  # P
        return output.logits[:, prompt_end : prompt_end + n], output.hidden_states[-1][:, prompt_end]

    def generate_action_slots(self, batch: dict, greedy: bool) -> tuple[Tensor, Tensor, Tensor]:
        """Decode the 7 action tokens one by one with the KV cache, restricted to the 256 action tokens:
        (slots (B, 7) in 0..255, summed log-prob (B,), value (B,))."""
        was_training = self.training
        self.eval()  # transformers turns the KV cache off while training with gradient checkpointing
        try:
            return self._generate_action_slots(batch, greedy)
        finally:
            self.train(was_training)

    def _generate_action_slots(self, batch: dict, greedy: bool) -> tuple[Tensor, Tensor, Tensor]:
        input_ids, mask = self.prompt_ids(batch)
        embeddings, mask, positions = self.vla.embed(self.image(batch), input_ids, mask)
        llm = self.vla.language_model
        output = llm(
            inputs_embeds=embeddings,
            attention_mask=mask,
            position_ids=positions,
            use_cache=True,
            output_hidden_states=True,
        )
        value = self.value(output.hidden_states[-1][:, -1])
        slots, log_prob = [], torch.zeros(len(input_ids), device=input_ids.device)
        for k in range(ACTION_DIM):
            distribution = Categorical(logits=self.action_logits(output.logits[:, -1]))
            slot = distribution.probs.argmax(-1) if greedy else distribution.sample()
            slots.append(slot)
            log_prob = log_prob + distribution.log_prob(slot)
            if k == ACTION_DIM - 1:
                break
            token = self.action_tokenizer.slots_to_action_ids(slot)[:, None]
            mask = torch.cat([mask, torch.ones_like(token)], dim=1)
            positions = positions[:, -1:] + 1
            output = llm(
                inputs_embeds=llm.get_input_embeddings()(token),
                attention_mask=mask,
                position_ids=positions,
                past_key_values=output.past_key_values,
                use_cache=True,
            )
        return torch.stack(slots, dim=1), log_prob, value

    def prompt_ids(self, batch: dict) -> tuple[Tensor, Tensor]:
        """Token ids (B, L) and mask of [BOS, <pad>..., prompt + the word-boundary token], padded after BOS."""
        task = batch.get("task")
        if task is None:
            raise KeyError("openvla needs the instruction under the batch key 'task'")
        batch_size = batch[self.config.camera].shape[0] if self.config.camera in batch else 1
        tasks = [task] * batch_size if isinstance(task, str) else list(task)
        rows = []
        for instruction in tasks:
            ids = self.tokenizer(openvla_prompt(instruction)).input_ids
            rows.append(ids if ids[-1] == self.space_token_id else [*ids, self.space_token_id])
        length = max(len(ids) for ids in rows)
        pad = self.tokenizer.pad_token_id
        input_ids = [[ids[0]] + [pad] * (length - len(ids)) + ids[1:] for ids in rows]
        mask = [[1] + [0] * (length - len(ids)) + [1] * (len(ids) - 1) for ids in rows]
        device = self.value_head.layers[0].weight.device
        return torch.tensor(input_ids, device=device), torch.tensor(mask, device=device)

    def image(self, batch: dict) -> Tensor:
        key = self.config.camera
        if key not in batch:
            cameras = sorted(k for k in batch if k.startswith(f"{OBS_IMAGES}."))
            raise KeyError(f"openvla expects camera {key!r}; the batch has {cameras}")
        images = batch[key]
        if tuple(images.shape[1:]) != self.image_shape:
            raise ValueError(
                f"{key} has images of shape {tuple(images.shape[1:])}, but this policy was built for "
                f"{self.image_shape} (C, H, W)"
            )
        return images.float()  # resized and normalised in fp32, then cast to the weights' dtype (prismatic.py)


class OpenVLAValueHead(nn.Module):
    """RL4VLA's critic: an MLP (4096 -> 512 -> 128 -> 1, GELU) on the LLM's last-layer hidden state of the last
    prompt token, kaiming-initialised with a small, bias-free output layer."""

    def __init__(self, hidden_size: int, dims: tuple[int, ...]):
        super().__init__()
        sizes = (hidden_size, *dims)
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes, sizes[1:], strict=False))
        self.out = nn.Linear(sizes[-1], 1, bias=False)
        for layer in self.layers:
            nn.init.kaiming_normal_(layer.weight, mode="fan_out", nonlinearity="relu")
            nn.init.zeros_(layer.bias)
        nn.init.normal_(self.out.weight, std=0.02)

    def forward(self, hidden_BC: Tensor) -> Tensor:
        for layer in self.layers:
            hidden_BC = F.gelu(layer(hidden_BC))
        return self.out(hidden_BC).squeeze(-1)


def resolve_dtype(name: str, device: str | None) -> torch.dtype:
    if name == "auto":
        on_gpu = str(device).startswith("cuda") and torch.cuda.is_available()
        return torch.bfloat16 if on_gpu and torch.cuda.is_bf16_supported() else torch.float32
    return getattr(torch, name)
