"""OpenVLA as a LeRobot policy: its action tokens, its prompt and padding, its actor-critic log-probabilities, SFT with
LoRA, bf16, the errors it names, and lerobot-train then lerobot-eval in roboscape_wm."""

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from huggingface_hub import ModelCard
from lerobot.policies.factory import get_policy_class
from lerobot_policy_openvla import OpenVLAPolicy
from lerobot_policy_openvla.action_tokenizer import OpenVLAActionTokenizer
from lerobot_policy_openvla.checkpoint import (
    default_dtype,
    read_checkpoint,
)
from lerobot_policy_openvla.modeling_openvla import openvla_prompt
from lerobot_policy_openvla.prismatic import PrismaticVisionBackbone
from torch import nn

from lerobot_roboscape.evaluation.agreement import AgreementConfig, evaluate_agreement
from lerobot_roboscape.hub.push import push_policy
from tests.conftest import IMAGE_SIZE, lerobot_train, roboscape_wm_args
from tests.policies.openvla_tiny import CAMERA, TASKS, make_batch, make_policy


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
