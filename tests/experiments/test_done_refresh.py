"""The done-refresh lever: PPO in the world model over slices of its clock, the action model's done head refitted
before each on simulator rollouts of the policy as it is then."""

from dataclasses import replace

import draccus
import torch

from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig
from lerobot_roboscape.experiments.done_refresh import (
    REFRESH_DIR,
    DoneRefresh,
    ppo_with_done_refresh,
    refresh_rounds,
    slice_ends,
)
from lerobot_roboscape.pipeline.methods import initial_scene
from lerobot_roboscape.rl.configuration_ppo import PPOConfig
from lerobot_roboscape.rl.ppo_state import trained_world_model
from lerobot_roboscape.training.checkpoints import CHECKPOINTS, FINAL, last_checkpoint
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from tests.conftest import IMAGE_SIZE
from tests.rl.test_ppo_world_model import ppo_args  # noqa: F401 (a fixture)

SIM_STEPS = 4
ITERATIONS = 4  # PPO's, in 2 slices of 2


def test_the_done_head_is_refitted_on_the_policys_rollouts_between_slices_of_ppo(
    ppo_args,  # noqa: F811
    demo_dataset,
    trained_tokenizer,
    token_cache,
    world_models,
    tmp_path,
):
    _, root = demo_dataset
    run = tmp_path / "run"
    cfg = draccus.parse(PPOConfig, args=[*ppo_args, f"--output_dir={run}", f"--iterations={ITERATIONS}"])
    refresh = DoneRefresh(
        sim=RoboscapeManiSkillEnvConfig(
            families=["pick_place", "push"], split="ind", image_size=IMAGE_SIZE, episode_length=SIM_STEPS, workers=1
        ),
        tokenizer=str(trained_tokenizer),
        demonstrations_repo_id="test/demos",
        demonstrations_root=str(root),
        cache_dir=str(token_cache.root.parent),
        rounds=2,
        episodes=2,
        focus_scenes=[initial_scene()],
        focus_episodes=1,
        demonstrations=4,
        steps=50,
        device="cpu",
    )
    final = ppo_with_done_refresh(cfg, refresh=refresh)

    # Two refits, one before each slice: the first on 2 simulator episodes of the policy PPO started from (and 1
    # in the focus scene), the second on 2 (and 1) of the policy as the first slice left it.
    first, second = refresh_rounds(run)
    assert (first.round, second.round) == (0, 1)
    assert first.policy == cfg.policy_path and second.policy == str(run / CHECKPOINTS / "00000002" / FINAL)
    for figures in (first, second):
        assert figures.simulator_steps == 3 * SIM_STEPS
        assert figures.focus_success is not None
        assert figures.rollouts.frames > 0 and figures.demonstrations.positives > 0
        assert figures.loss["last"] < figures.loss["first"]
    # A refitted model is the base one but for its done head.
    base = STWorldModel.from_pretrained(world_models["action"]).state_dict()
    for r in (0, 1):
        new = STWorldModel.from_pretrained(run / REFRESH_DIR / f"round_{r}" / FINAL).state_dict()
        changed = {name for name, weight in new.items() if not torch.equal(weight, base[name])}
        assert changed and all(name.startswith("done_head.") for name in changed)
    # The second slice trained in the world model with the second refit's head, to the run's end; the run's model
    # is its newest checkpoint's, published with the flags beside it.
    assert final == run / FINAL
    newest = last_checkpoint(run) / FINAL
    assert (final / "model.safetensors").read_bytes() == (newest / "model.safetensors").read_bytes()
    # The replay plays the policy in the model it last trained in, as its checkpoint's flags name it.
    assert trained_world_model(final) == str(run / REFRESH_DIR / "round_1" / FINAL)
    assert last_checkpoint(run).name == f"{ITERATIONS:08d}"


def test_a_run_is_sliced_by_its_clock_or_else_by_its_iterations():
    cfg = PPOConfig(policy_path="p", env=RoboscapeManiSkillEnvConfig(), iterations=25, time_budget_s=None)
    assert slice_ends(cfg, 3) == [{"iterations": 9}, {"iterations": 17}, {"iterations": 25}]
    timed = slice_ends(replace(cfg, time_budget_s=600.0), 3)
    assert timed == [{"time_budget_s": 200.0}, {"time_budget_s": 400.0}, {"time_budget_s": 600.0}]
