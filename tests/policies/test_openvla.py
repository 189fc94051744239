import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from huggingface_hub import ModelCard
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import get_policy_class, make_pre_post_processors
from lerobot.processor import PolicyProcessorPipeline
from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action
from lerobot_policy_openvla import OpenVLAConfig, OpenVLAPolicy
from lerobot_policy_openvla.action_tokenizer import OpenVLAActionTokenizer
from lerobot_policy_openvla.checkpoint import (
    RANDOM_7B,
    OpenVLACheckpoint,
    OpenVLACheckpointError,
    build_vla,
    checkpoint_state_dict,
    default_dtype,
    read_checkpoint,
    tiny_checkpoint,
    tiny_config,
    write_checkpoint,
)
from lerobot_policy_openvla.modeling_openvla import openvla_prompt
from lerobot_policy_openvla.prismatic import PrismaticVisionBackbone
from safetensors import safe_open
from torch import nn

from lerobot_roboscape.evaluation.agreement import AgreementConfig, evaluate_agreement
from lerobot_roboscape.hub.push import push_policy
from roboscape_core.errors import InvalidInputError
from tests.conftest import IMAGE_SIZE, lerobot_train, roboscape_wm_args

CAMERA = "observation.images.third_view"
FIXTURES = Path(__file__).parents[1] / "fixtures"
TASKS = ["push the can forward", "pick up the red apple and place it in the bowl", "pull the mug back"]


def make_policy(**overrides) -> OpenVLAPolicy:
    features = {
        CAMERA: PolicyFeature(FeatureType.VISUAL, (3, IMAGE_SIZE, IMAGE_SIZE)),
        "observation.images.wrist": PolicyFeature(FeatureType.VISUAL, (3, IMAGE_SIZE, IMAGE_SIZE)),
        "observation.state": PolicyFeature(FeatureType.STATE, (16,)),
    }
    kwargs = dict(
        device="cpu",
        base_model="tiny",
        input_features=features,
        gradient_checkpointing=False,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (7,))},
    )
    torch.manual_seed(0)
    return OpenVLAPolicy(OpenVLAConfig(**{**kwargs, **overrides}))


@pytest.fixture(scope="module")
def policy():
    return make_policy()


def make_batch(tasks=TASKS):
    generator = torch.Generator().manual_seed(1)
    return {
        CAMERA: torch.rand(len(tasks), 3, IMAGE_SIZE, IMAGE_SIZE, generator=generator),
        "task": list(tasks),
        "action": torch.rand(len(tasks), 7, generator=generator) * 2 - 1,
    }


def test_action_tokenizer_bins_and_ids():
    tokenizer = OpenVLAActionTokenizer()
    assert np.array_equal(tokenizer.bins.numpy(), np.linspace(-1, 1, 256))  # OpenVLA's float64 edges, bit for bit
    ids = tokenizer.encode(torch.tensor([-1.0, 1.0, 0.0, -5.0, 5.0]))
    assert ids.tolist() == [31999, 31744, 31872, 31999, 31744]  # 32000 - bin, bins 1..256, clipped
    actions = torch.linspace(-0.999, 0.999, 1001)
    assert (tokenizer.decode(tokenizer.encode(actions)) - actions).abs().max() <= 1 / 255 + 1e-6  # half a bin
    all_ids = torch.arange(31744, 32000)
    centres = tokenizer.decode(all_ids)
    assert torch.equal(tokenizer.encode(centres)[1:], all_ids[1:])  # each centre maps back to its own token
    assert centres[0] == centres[1]  # the top bin shares the last centre, as in OpenVLA
    assert torch.equal(
        tokenizer.action_ids_to_slots(tokenizer.slots_to_action_ids(torch.arange(256))), torch.arange(256)
    )


def test_prompt_format_and_padding_layout(policy):
    assert openvla_prompt("Push the Can") == "In: What action should the robot take to push the can?\nOut:"
    input_ids, mask = policy.prompt_ids({"task": TASKS, CAMERA: torch.zeros(3, 3, IMAGE_SIZE, IMAGE_SIZE)})
    tokenizer = policy.tokenizer
    assert (input_ids[:, 0] == tokenizer.bos_token_id).all() and (input_ids[:, -1] == policy.space_token_id).all()
    for row, row_mask, task in zip(input_ids, mask, TASKS, strict=True):
        text = tokenizer.decode(row[row_mask.bool()], skip_special_tokens=True)
        assert text.strip() == openvla_prompt(task)
        assert (row[~row_mask.bool()] == tokenizer.pad_token_id).all()


def test_padding_inside_a_batch_changes_nothing(policy):
    batch = make_batch()
    together = policy.evaluate_actions(batch, torch.arange(21).view(3, 7))
    for i in range(3):
        alone = {CAMERA: batch[CAMERA][i : i + 1], "task": [TASKS[i]]}
        single = policy.evaluate_actions(alone, torch.arange(21).view(3, 7)[i : i + 1])
        torch.testing.assert_close(single.log_prob, together.log_prob[i : i + 1], atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(single.value, together.value[i : i + 1], atol=1e-5, rtol=1e-4)


def test_actor_critic_log_probs_are_consistent(policy):
    batch = make_batch()
    torch.manual_seed(0)
    sample = policy.sample_action(batch)
    assert sample.raw_action.shape == (3, 7) and sample.action.shape == (3, 7)
    assert ((sample.raw_action >= 0) & (sample.raw_action < 256)).all()
    evaluation = policy.evaluate_actions(batch, sample.raw_action)
    torch.testing.assert_close(evaluation.log_prob, sample.log_prob, atol=1e-4, rtol=1e-4)  # cached vs full pass
    torch.testing.assert_close(evaluation.value, sample.value, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(policy.predict_value(batch), sample.value, atol=1e-5, rtol=1e-4)
    assert (evaluation.entropy > 0).all() and (evaluation.entropy <= 7 * torch.log(torch.tensor(256.0)) + 1e-3).all()
    # Greedy decoding picks the most likely token at each step.
    greedy = policy.select_action(batch)
    slots = policy.action_tokenizer.action_ids_to_slots(policy.action_tokenizer.encode(greedy))
    slots[slots == 0] = 1  # the shared top-bin centre maps to slot 1
    logits, _ = policy.predict_suffix(batch, policy.action_tokenizer.slots_to_action_ids(slots))
    chosen = policy.action_logits(logits).argmax(-1)
    chosen[chosen == 0] = 1
    assert torch.equal(chosen, slots)


def test_sft_with_lora_learns_the_demonstrated_action_tokens():
    policy = make_policy(gradient_checkpointing=True)
    policy.train()
    batch = make_batch()
    frozen = {n: p.clone() for n, p in policy.vla.named_parameters() if not p.requires_grad}
    optimizer = torch.optim.AdamW(policy.get_optim_params(), lr=1e-2)
    first, _ = policy.forward(batch)
    for _ in range(30):
        loss, info = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert loss.item() < 0.6 * first.item() and info["action_accuracy"] >= 0.9
    assert all(torch.equal(p, frozen[n]) for n, p in policy.vla.named_parameters() if not p.requires_grad)
    assert {"action_accuracy", "action_l1"} <= set(info)


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


@pytest.mark.parametrize(
    ("change", "error", "message"),
    [
        (lambda b: b.pop(CAMERA), KeyError, "expects camera 'observation.images.third_view'"),
        (lambda b: b.update({CAMERA: torch.rand(3, 3, 16, 16)}), ValueError, r"\(3, 16, 16\)"),
        (lambda b: b.pop("task"), KeyError, "instruction"),
    ],
)
def test_bad_input_names_what_is_wrong(policy, change, error, message):
    batch = make_batch()
    change(batch)
    with pytest.raises(error, match=message):
        policy.select_action(batch)


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


def test_bf16_preprocessing_is_fp32_then_cast():
    architecture = read_checkpoint("tiny").architecture
    backbones = {}
    for dtype in (torch.float32, torch.bfloat16):
        torch.manual_seed(0)
        with default_dtype(dtype):
            backbones[dtype] = PrismaticVisionBackbone(architecture)
    images = torch.rand(2, 3, IMAGE_SIZE, IMAGE_SIZE, generator=torch.Generator().manual_seed(0))
    assert architecture.image_size != IMAGE_SIZE  # the antialiased bicubic resize runs (it raised in bf16 on CPU)
    reference = backbones[torch.float32].preprocess(images)
    for fp32, bf16 in zip(reference, backbones[torch.bfloat16].preprocess(images), strict=True):
        assert bf16.dtype == torch.bfloat16 and torch.equal(bf16, fp32.to(torch.bfloat16))
    actions = make_policy(dtype="bfloat16").select_action(make_batch())  # the whole tiny policy in bf16 on CPU
    assert actions.shape == (3, 7) and torch.isfinite(actions).all()


@pytest.mark.gpu
def test_bf16_preprocessing_on_gpu_is_fp32_then_cast():
    """On a GPU the bf16 path used to normalise in bf16 and differ from OpenVLA's fp32-then-cast by up to 0.016."""
    architecture = read_checkpoint("tiny").architecture
    backbones = {}
    for dtype in (torch.float32, torch.bfloat16):
        torch.manual_seed(0)
        with torch.device("cuda"), default_dtype(dtype):
            backbones[dtype] = PrismaticVisionBackbone(architecture)
    images = torch.rand(2, 3, IMAGE_SIZE, IMAGE_SIZE, generator=torch.Generator().manual_seed(0)).cuda()
    reference = backbones[torch.float32].preprocess(images)
    for fp32, bf16 in zip(reference, backbones[torch.bfloat16].preprocess(images), strict=True):
        assert bf16.dtype == torch.bfloat16 and torch.equal(bf16, fp32.to(torch.bfloat16))


def test_lora_is_gaussian_initialised_and_leaves_the_lm_head():
    policy = make_policy()
    assert policy.lora_config().init_lora_weights == "gaussian"
    lora_A = torch.cat([p.flatten() for n, p in policy.vla.named_parameters() if "lora_A" in n])
    assert abs(lora_A.std().item() - 1 / policy.config.lora_r) < 0.05 / policy.config.lora_r  # N(0, 1/r^2)
    assert all(p.eq(0).all() for n, p in policy.vla.named_parameters() if "lora_B" in n)
    modules = dict(policy.vla.named_modules())
    adapted = {n.removesuffix(".base_layer") for n in modules if n.endswith(".base_layer")}
    linear = {n.removesuffix(".base_layer") for n, m in modules.items() if type(m) is nn.Linear and "lora_" not in n}
    used = {n for n in linear if "attn_pool" not in n}  # SigLIP's pooling head is never read
    assert adapted == used - {"language_model.lm_head"}  # peft's all-linear: every linear layer but the head
    # RL4VLA's PPO adapter also trains the LM head: its explicit target list (which ends in "lm_head") gives it.
    with_head = make_policy(lora_target_modules=["q_proj", "v_proj", "lm_head"])
    assert any(n.startswith("language_model.lm_head.lora_A") for n, _ in with_head.vla.named_parameters())


def test_lerobot_train_then_lerobot_eval(demo_dataset, trained_tokenizer, world_models, env_config, tmp_path):
    assert get_policy_class("openvla") is OpenVLAPolicy
    _, root = demo_dataset
    checkpoint = lerobot_train(
        root,
        tmp_path / "train",
        2,
        "--policy.type=openvla",
        "--policy.base_model=tiny",
        "--policy.gradient_checkpointing=false",
    )
    postprocessor = json.loads((checkpoint / "policy_postprocessor.json").read_text())
    unnormalize = next(step for step in postprocessor["steps"] if step["registry_name"] == "openvla_unnormalize_action")
    assert unnormalize["config"]["mask"] == [True] * 6 + [False]  # the dataset's q01/q99, the gripper masked
    assert (checkpoint / "model.safetensors").stat().st_size < 5e6  # the adapter and value head, not the base
    # lerobot-eval reads the policy from the folder its Hub repo would hold.
    repo = push_policy("me/openvla_sft", checkpoint, local_dir=tmp_path / "hub")
    card = ModelCard.load(f"{repo}/README.md")
    assert "openvla" in card.data.tags and card.data.base_model is None  # "tiny" is a preset, not a Hub repo
    assert "adapter and value head only" in card.text and "`tiny`" in card.text
    cmd = [
        sys.executable,
        "-m",
        "lerobot.scripts.lerobot_eval",
        f"--policy.path={repo}",
        "--policy.device=cpu",
        "--env.type=roboscape_maniskill",
        f"--env.image_size={IMAGE_SIZE}",
        "--env.families=[push]",
        "--env.episode_length=2",
        "--eval.n_episodes=1",
        "--eval.batch_size=1",
        f"--output_dir={tmp_path / 'eval'}",
    ]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    assert json.loads((tmp_path / "eval" / "eval_info.json").read_text())["overall"]["n_episodes"] == 1
    # And in the world model: OpenVLA looks at every step, the model steps once per 4 of its actions.
    cmd = [c for c in cmd if not c.startswith(("--env.", "--output_dir"))]
    cmd += [*roboscape_wm_args(root, trained_tokenizer, world_models), f"--output_dir={tmp_path / 'eval_wm'}"]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    assert json.loads((tmp_path / "eval_wm" / "eval_info.json").read_text())["overall"]["n_episodes"] == 1
    # And paired with the simulator from the same start (roboscape-eval-agreement), read from the same folder.
    agreement = AgreementConfig(
        policy_paths=[repo],
        env=env_config(episode_length=None),
        families=["push"],
        episodes=1,
        batch_size=1,
        episode_length=4,
        videos=0,
        workers=1,
        output_dir=tmp_path / "agreement",
        device="cpu",
    )
    ladder = evaluate_agreement(agreement)
    (record,) = [json.loads(line) for line in (tmp_path / "agreement" / "policy_0" / "episodes.jsonl").open()]
    assert record["family"] == "push" and {"sim_success", "wm_success", "sim_return", "wm_return"} <= set(record)
    assert ladder["pooled"]["episodes"] == 1
