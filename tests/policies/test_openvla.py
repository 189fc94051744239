import json
import subprocess
import sys

import pytest
import torch
from huggingface_hub import ModelCard
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import get_policy_class, make_pre_post_processors
from lerobot_policy_openvla import OpenVLAConfig, OpenVLAPolicy
from lerobot_policy_openvla.action_tokenizer import OpenVLAActionTokenizer
from lerobot_policy_openvla.checkpoint import (
    OpenVLACheckpointError,
    build_vla,
    read_checkpoint,
    tiny_checkpoint,
    write_checkpoint,
)
from lerobot_policy_openvla.modeling_openvla import openvla_prompt
from safetensors import safe_open

from lerobot_roboscape.actor_critic import ActorCritic
from lerobot_roboscape.hub.push import push_policy
from tests.conftest import IMAGE_SIZE, lerobot_train

CAMERA = "observation.images.third_view"
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
    assert isinstance(policy, ActorCritic)
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


def test_unnormalisation_uses_the_dataset_quantiles(policy):
    q01, q99 = torch.linspace(-0.5, 0.1, 7), torch.linspace(0.2, 0.9, 7)
    stats = {"action": {"q01": q01, "q99": q99, "min": q01 - 1, "max": q99 + 1, "mean": q01, "std": q99}}
    _, postprocessor = make_pre_post_processors(policy.config, dataset_stats=stats)
    torch.testing.assert_close(postprocessor(torch.full((1, 7), -1.0)), q01[None])
    torch.testing.assert_close(postprocessor(torch.ones(1, 7)), q99[None])


def test_lerobot_train_then_lerobot_eval(demo_dataset, tmp_path):
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
    assert (checkpoint / "policy_postprocessor.json").exists()
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
