"""OpenVLA's checkpoints and its actions' unnormalisation: the published 7B layout loaded exactly, adapters saved and
refused, and the dataset quantiles applied as predict_action applies them."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import make_pre_post_processors
from lerobot.processor import PolicyProcessorPipeline
from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action
from lerobot_policy_openvla import OpenVLAConfig, OpenVLAPolicy
from lerobot_policy_openvla.checkpoint import (
    RANDOM_7B,
    OpenVLACheckpoint,
    OpenVLACheckpointError,
    build_vla,
    checkpoint_state_dict,
    read_checkpoint,
    tiny_checkpoint,
    tiny_config,
    write_checkpoint,
)
from safetensors import safe_open

from roboscape_core.errors import InvalidInputError
from tests.conftest import IMAGE_SIZE
from tests.policies.openvla_tiny import CAMERA, FIXTURES, make_batch


def test_checkpoint_in_the_published_layout_loads_exactly(tmp_path):
    checkpoint = tiny_checkpoint(seed=3)
    directory = write_checkpoint(checkpoint, tmp_path / "openvla-tiny")
    index = json.loads((directory / "model.safetensors.index.json").read_text())
    assert len(set(index["weight_map"].values())) > 1  # sharded like the Hub repo
    assert any(key.endswith("ls1.scale_factor") for key in index["weight_map"])  # OpenVLA's LayerScale name
    assert {
        "vision_backbone.featurizer.reg_token",
        "projector.fc3.weight",
        "language_model.lm_head.weight",
        "language_model.model.embed_tokens.weight",
    } <= set(index["weight_map"])
    loaded = read_checkpoint(str(directory))
    assert loaded.config == checkpoint.config
    vla = build_vla(loaded, "cpu", torch.float32)
    state = vla.state_dict()
    assert state["vision_backbone.featurizer.blocks.0.ls1.gamma"].equal(
        checkpoint.state_dict["vision_backbone.featurizer.blocks.0.ls1.scale_factor"]
    )
    assert len(state) == len(checkpoint.state_dict)
    reference = build_vla(checkpoint, "cpu", torch.float32).state_dict()
    assert all(state[key].equal(reference[key]) for key in reference)
    assert loaded.tokenizer("In: What").input_ids == checkpoint.tokenizer("In: What").input_ids


def test_checkpoint_with_wrong_keys_is_refused_by_name(tmp_path):
    checkpoint = tiny_checkpoint()
    checkpoint.state_dict["projector.fc4.weight"] = torch.zeros(1)
    del checkpoint.state_dict["projector.fc1.bias"]
    with pytest.raises(OpenVLACheckpointError, match=r"projector\.fc1\.bias.*projector\.fc4\.weight"):
        build_vla(checkpoint, "cpu", torch.float32)
    checkpoint.config["model_type"] = "llava"
    with pytest.raises(OpenVLACheckpointError, match="model_type='llava'"):
        _ = checkpoint.architecture


def test_unknown_base_checkpoint_is_a_clear_error(monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(OpenVLACheckpointError, match="no-such-org/openvla-missing"):
        read_checkpoint("no-such-org/openvla-missing")


def test_adapter_only_checkpoint_round_trip(policy, tmp_path):
    batch = make_batch()
    with torch.no_grad():
        for name, parameter in policy.named_parameters():
            if "lora_B" in name:
                parameter.normal_(0, 0.05)  # a trained-looking adapter (LoRA starts with B = 0)
    policy.save_pretrained(tmp_path)
    with safe_open(tmp_path / "model.safetensors", framework="pt") as file:
        keys = list(file.keys())
        assert file.metadata()["base_model"] == "tiny"
    assert keys and all("lora_" in key or key.startswith("value_head.") for key in keys)
    assert json.loads((tmp_path / "config.json").read_text())["base_model"] == "tiny"
    loaded = OpenVLAPolicy.from_pretrained(tmp_path)
    torch.testing.assert_close(loaded.select_action(batch), policy.select_action(batch))
    raw = torch.randint(0, 256, (3, 7))
    expected = policy.evaluate_actions(batch, raw).log_prob
    torch.testing.assert_close(loaded.evaluate_actions(batch, raw).log_prob, expected)


def test_adapter_for_another_lora_config_is_refused(policy, tmp_path):
    policy.save_pretrained(tmp_path)
    config = json.loads((tmp_path / "config.json").read_text())
    (tmp_path / "config.json").write_text(json.dumps({**config, "lora_target_modules": ["q_proj"]}))
    with pytest.raises(ValueError, match="does not fit this policy's adapter"):
        OpenVLAPolicy.from_pretrained(tmp_path)


def openvla_config(**overrides) -> OpenVLAConfig:
    """A config for the processors alone (no weights built)."""
    features = {CAMERA: PolicyFeature(FeatureType.VISUAL, (3, IMAGE_SIZE, IMAGE_SIZE))}
    action = {"action": PolicyFeature(FeatureType.ACTION, (7,))}
    kwargs = dict(device="cpu", base_model="tiny", input_features=features, output_features=action)
    return OpenVLAConfig(**{**kwargs, **overrides})


def published_norm_stats() -> dict:
    return json.loads((FIXTURES / "openvla_7b_norm_stats.json").read_text())["norm_stats"]


def base_with_norm_stats(directory: Path, norm_stats: dict) -> str:
    """A base checkpoint folder whose config.json carries `norm_stats` (all the processors read)."""
    directory.mkdir()
    (directory / "config.json").write_text(json.dumps({**tiny_config(), "norm_stats": norm_stats}))
    return str(directory)


def test_unnormalisation_uses_the_dataset_quantiles_and_passes_the_gripper(tmp_path):
    # Was: every dimension, the gripper included, mapped to [q01, q99] (LeRobot's QUANTILES). OpenVLA's fine-tuning
    # statistics mask the gripper, which is neither normalised nor un-normalised.
    q01, q99 = torch.linspace(-0.5, 0.1, 7), torch.linspace(0.2, 0.9, 7)
    stats = {"action": {"q01": q01, "q99": q99, "min": q01 - 1, "max": q99 + 1, "mean": q01, "std": q99}}
    preprocessor, postprocessor = make_pre_post_processors(openvla_config(), dataset_stats=stats)
    x = torch.tensor([[-1.0, 1.0, -1.0, 1.0, 0.0, 0.5, -0.3]], dtype=torch.float64)
    expected = torch.cat([((x + 1) / 2 * (q99 - q01) + q01)[:, :6], x[:, 6:]], dim=1)
    torch.testing.assert_close(postprocessor(x), expected)
    assert postprocessor(x)[0, 6] == -0.3  # the gripper, untouched
    # The preprocessor inverts it for SFT targets, clipped to [-1, 1] as OpenVLA's data pipeline does.
    action = torch.cat([expected[:, :6], torch.tensor([[0.7]], dtype=torch.float64)], dim=1).float()
    batch = preprocessor({CAMERA: torch.rand(3, IMAGE_SIZE, IMAGE_SIZE), "task": "x", "action": action[0]})
    torch.testing.assert_close(batch["action"], torch.cat([x[:, :6], torch.tensor([[0.7]])], 1).float())
    far = preprocessor({CAMERA: torch.rand(3, IMAGE_SIZE, IMAGE_SIZE), "task": "x", "action": torch.full((7,), 9.0)})
    assert far["action"][0, :6].eq(1).all() and far["action"][0, 6] == 9  # OpenVLA's tokenizer clips the gripper
    # The statistics travel with the saved pipeline.
    postprocessor.save_pretrained(tmp_path)
    saved = json.loads((tmp_path / "policy_postprocessor.json").read_text())["steps"][0]
    assert saved["registry_name"] == "openvla_unnormalize_action" and saved["config"]["mask"] == [True] * 6 + [False]
    converters = dict(to_transition=policy_action_to_transition, to_output=transition_to_policy_action)
    reloaded = PolicyProcessorPipeline.from_pretrained(tmp_path, "policy_postprocessor.json", **converters)
    assert torch.equal(reloaded(x), postprocessor(x))


def predict_action_reference(token_ids: np.ndarray, action_stats: dict) -> np.ndarray:
    """OpenVLAForActionPrediction.predict_action (prismatic/extern/hf/modeling_prismatic.py) after `generate`,
    in numpy as the published code writes it, for openvla-7b's config (vocab 32064 padded by 64, 256 bins)."""
    bins = np.linspace(-1, 1, 256)
    bin_centers = (bins[:-1] + bins[1:]) / 2.0
    vocab_size = 32064 - 64  # text_config.vocab_size - pad_to_multiple_of
    discretized_actions = vocab_size - token_ids
    discretized_actions = np.clip(discretized_actions - 1, a_min=0, a_max=bin_centers.shape[0] - 1)
    normalized_actions = bin_centers[discretized_actions]
    mask = action_stats.get("mask", np.ones_like(action_stats["q01"], dtype=bool))
    action_high, action_low = np.array(action_stats["q99"]), np.array(action_stats["q01"])
    return np.where(mask, 0.5 * (normalized_actions + 1) * (action_high - action_low) + action_low, normalized_actions)


def test_unnormalisation_equals_predict_action(policy, tmp_path):
    """The published model zero-shot (--policy.unnorm_key=bridge_orig): token ids -> the policy's decoding ->
    the postprocessor equals OpenVLA's predict_action, bit for bit, gripper included."""
    norm_stats = published_norm_stats()
    bridge = norm_stats["bridge_orig"]["action"]
    config = openvla_config(base_model=base_with_norm_stats(tmp_path / "base", norm_stats), unnorm_key="bridge_orig")
    _, postprocessor = make_pre_post_processors(config)
    token_ids = np.array(
        [[31744, 31999, 31872, 31800, 31900, 31950, 31947], [31745, 31998, 31871, 31760, 31990, 31850, 31750]]
    )
    actions = postprocessor(policy.action_tokenizer.decode(torch.from_numpy(token_ids)))
    expected = predict_action_reference(token_ids, bridge)
    assert actions.dtype == torch.float64 and np.array_equal(actions.numpy(), expected)
    # The case: a gripper token decoded to -0.588 stays -0.588 (mask[6] is False); QUANTILES made it 0.206.
    assert round(float(actions[0, 6]), 3) == -0.588
    assert (
        round(0.5 * (float(actions[0, 6]) + 1) * (bridge["q99"][6] - bridge["q01"][6]) + bridge["q01"][6], 3) == 0.206
    )
    # End to end: the greedy tokens the policy picks, through select_action and the postprocessor.
    batch = make_batch()
    slots, _, _ = policy.generate_action_slots(batch, greedy=True)
    token_ids = policy.action_tokenizer.slots_to_action_ids(slots).numpy()
    assert np.array_equal(
        postprocessor(policy.select_action(batch)).numpy(), predict_action_reference(token_ids, bridge)
    )


def test_unnorm_key_is_chosen_as_predict_action_chooses_it(tmp_path):
    norm_stats = published_norm_stats()
    base = base_with_norm_stats(tmp_path / "all", norm_stats)
    with pytest.raises(InvalidInputError, match=r"25 datasets.*--policy.unnorm_key.*'bridge_orig'.*'viola'"):
        make_pre_post_processors(openvla_config(base_model=base))
    with pytest.raises(InvalidInputError, match=r"unnorm_key='bridge'.*'bridge_orig'"):
        make_pre_post_processors(openvla_config(base_model=base, unnorm_key="bridge"))
    single = base_with_norm_stats(tmp_path / "one", {"fractal20220817_data": norm_stats["fractal20220817_data"]})
    _, postprocessor = make_pre_post_processors(openvla_config(base_model=single))
    fractal = norm_stats["fractal20220817_data"]["action"]
    assert postprocessor.steps[0].q01 == fractal["q01"] and postprocessor.steps[0].mask == fractal["mask"]
    # unnorm_key wins over the dataset's statistics; without either, a base without norm_stats passes actions.
    _, postprocessor = make_pre_post_processors(
        openvla_config(base_model=base, unnorm_key="fractal20220817_data"),
        dataset_stats={"action": {"q01": torch.zeros(7), "q99": torch.ones(7)}},
    )
    assert postprocessor.steps[0].q99 == fractal["q99"]
    _, postprocessor = make_pre_post_processors(openvla_config())
    assert torch.equal(postprocessor(torch.full((1, 7), 0.5)), torch.full((1, 7), 0.5))


def test_published_checkpoint_keys_and_shapes_load_exactly():
    """Independent of the plugin's own key mapping: the published checkpoint's 982 tensors (names from its
    model.safetensors.index.json, shapes from its config), checked against its total_size, then loaded through
    `build_vla` into the random-7b preset on the meta device and compared name by name."""
    fixture = json.loads((FIXTURES / "openvla_7b_checkpoint.json").read_text())
    published = fixture["tensors"]
    assert len(published) == 982
    assert sum(math.prod(shape) * 2 for shape, dtype in published.values()) == fixture["total_size"] == 15_082_474_368
    assert {dtype for _, dtype in published.values()} == {"BF16"}

    preset = read_checkpoint(RANDOM_7B)
    state_dict = {
        name: torch.empty(shape, dtype=torch.bfloat16, device="meta") for name, (shape, _) in published.items()
    }
    checkpoint = OpenVLACheckpoint("openvla-7b (meta)", preset.config, state_dict, preset.tokenizer)
    vla = build_vla(checkpoint, "meta", torch.bfloat16)  # refuses a missing, unexpected or misshapen key
    ours = {name: [list(t.shape), str(t.dtype)] for name, t in checkpoint_state_dict(vla).items()}
    assert sorted(ours) == sorted(published)
    assert all(ours[name] == [shape, "torch.bfloat16"] for name, (shape, _) in published.items())
    renamed = {name.replace(".scale_factor", ".gamma"): t for name, t in state_dict.items()}
    with pytest.raises(OpenVLACheckpointError, match=r"missing=\['vision_backbone\.featurizer\.blocks\.0\.ls1\.scale"):
        build_vla(OpenVLACheckpoint("renamed", preset.config, renamed, preset.tokenizer), "meta", torch.bfloat16)
