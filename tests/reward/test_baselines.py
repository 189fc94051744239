import draccus
import numpy as np
import pytest
import torch

from lerobot_roboscape.dataset.writer import read_episode_info
from lerobot_roboscape.envs.reward_report import replay_rewards, teacher_forced_done
from lerobot_roboscape.envs.world_model_env import RoboscapeWorldModelEnv
from lerobot_roboscape.reward.baselines import RewardModel, RewardModelConfig
from lerobot_roboscape.reward.train import TrainRewardConfig, train_reward_model
from lerobot_roboscape.training.checkpoints import FINAL
from lerobot_roboscape.world_model.clips import model_frames
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from tests.conftest import IMAGE_SIZE


@pytest.fixture(scope="module")
def reward_models(demo_dataset, trained_tokenizer, token_cache, world_models, tmp_path_factory):
    _, root = demo_dataset
    dirs, losses = {}, {}
    for kind in ("embedding", "proxy", "success"):
        out = tmp_path_factory.mktemp(f"reward_{kind}")
        cfg = draccus.parse(
            TrainRewardConfig,
            args=[
                f"--reward.kind={kind}",
                "--dataset.repo_id=test/demos",
                f"--dataset.root={root}",
                f"--tokenizer={trained_tokenizer}",
                f"--action_world_model={world_models['action']}",
                f"--token_cache={token_cache.root}",
                f"--output_dir={out}",
                "--train.steps=500",
                "--train.save_freq=500",
                f"--train.batch_size={4 if kind == 'embedding' else 16}",  # clips of 4 frames, or frames
                "--train.warmup_steps=5",
                "--train.log_freq=1",
                "--train.lr=3e-3",
            ],
        )
        train_reward_model(cfg)
        dirs[kind] = out / FINAL
        losses[kind] = _logged_losses(out)
    return dirs, losses


def _logged_losses(out):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(next((out / "logs").rglob("events.out.tfevents*"))))
    events.Reload()
    return [e.value for e in events.Scalars("loss")]


def test_reward_models_fit_the_rule_based_labels(reward_models, token_cache):
    _, losses = reward_models
    label_variance = float(np.var(token_cache.rewards))  # the error of always predicting the mean reward
    for kind in ("embedding", "proxy"):
        values = losses[kind]
        assert np.mean(values[-25:]) < 0.7 * label_variance, (kind, np.mean(values[-25:]), label_variance)


def test_success_classifier_learns_the_rare_done_frames(reward_models, token_cache):
    dirs, losses = reward_models
    # A constant guess scores ln 2 on the balanced loss, whatever the share of done frames.
    assert np.mean(losses["success"][-25:]) < 0.6 * np.log(2), np.mean(losses["success"][-25:])
    model = RewardModel.from_pretrained(dirs["success"]).eval()
    assert model.config.kind == "success"
    images = torch.rand(3, 2, 3, IMAGE_SIZE, IMAGE_SIZE)
    p = model.success_probability(images)
    assert p.shape == (3,) and ((p >= 0) & (p <= 1)).all()


def test_balanced_loss_weighs_the_rare_class_as_much_as_the_common_one():
    from lerobot_roboscape.training.losses import balanced_bce

    labels = torch.tensor([1.0] + [0.0] * 19)
    never_done = torch.full((20,), -4.0)  # what an RMSE-trained head drifts to when done frames are rare
    plain = torch.nn.functional.binary_cross_entropy_with_logits(never_done, labels)
    assert balanced_bce(never_done, labels) > 5 * plain
    assert torch.isclose(
        balanced_bce(never_done[1:], labels[1:]), plain * 0 + torch.nn.functional.softplus(torch.tensor(-4.0))
    )  # one class only: its own mean


def test_reward_model_round_trip_and_bad_input(tmp_path):
    model = RewardModel(RewardModelConfig(kind="proxy", image_size=32, n_cameras=2)).eval()
    model.save_pretrained(tmp_path)
    loaded = RewardModel.from_pretrained(tmp_path).eval()
    images = torch.rand(3, 2, 3, 32, 32)
    assert torch.equal(model(images), loaded(images))
    with pytest.raises(ValueError, match=r"expects \(B, 2, 3, 32, 32\)"):
        model(torch.rand(3, 1, 3, 32, 32))
    with pytest.raises(ValueError, match="kind must be one of"):
        RewardModelConfig(kind="learned")


def test_env_takes_done_from_the_success_classifier(reward_models, env_config):
    dirs, _ = reward_models
    small = dict(episode_length=3, max_goal_steps=2, theta=0.5)
    cfg = env_config(done_source="classifier", success_classifier=str(dirs["success"]), **small)
    env = RoboscapeWorldModelEnv(cfg, num_envs=2)
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.zeros((2, 7), np.float32))
    classifier = RewardModel.from_pretrained(dirs["success"]).eval()
    np.testing.assert_allclose(
        info["done_probability"], classifier.success_probability(env._frames).numpy(), rtol=1e-5, atol=1e-6
    )
    with pytest.raises(ValueError, match="needs success_classifier"):
        env_config(done_source="classifier", **small)
    with pytest.raises(ValueError, match="not a success classifier"):
        RoboscapeWorldModelEnv(env_config(done_source="classifier", success_classifier=str(dirs["proxy"]), **small))


def test_done_report_chooses_source_and_threshold_on_validation(
    reward_models, demo_dataset, trained_tokenizer, world_models, tmp_path
):
    from lerobot_roboscape.reward.done_report import DoneReportConfig, evaluate_done

    _, root = demo_dataset
    dirs, _ = reward_models
    cfg = draccus.parse(
        DoneReportConfig,
        args=[
            "--dataset.repo_id=test/demos",
            f"--dataset.root={root}",
            "--dataset.episodes=[1,2,3,4]",
            "--validation.repo_id=test/demos",
            f"--validation.root={root}",
            f"--tokenizer={trained_tokenizer}",
            f"--world_model={world_models['action']}",
            f"--success_classifier={dirs['success']}",
            f"--output_dir={tmp_path}",
        ],
    )
    report = evaluate_done(cfg)
    for name in ("done_report.json", "done_report.md", "done_curves.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert set(report["sources"]) == {"world_model", "classifier"}
    validation_auc = {s: v["validation"]["frame_roc_auc"] for s, v in report["sources"].items()}
    assert report["chosen"]["source"] == max(validation_auc, key=validation_auc.get)
    facts = {row["episode_index"]: row for row in read_episode_info(root)}
    failed = sum(not facts[i]["success"] for i in (1, 2, 3, 4))
    for source in report["sources"].values():
        assert source["theta_from"] == "validation"
        for mode in ("teacher_forced", "open_loop"):
            c = source[mode]["confusion"]
            assert c["failed_called_done"] + c["failed_not_done"] == failed
            assert sum(v for k, v in c.items() if k != "failed_called_done_rate") == 4
    for episode in report["episodes"]:
        lengths = {len(v) for v in episode["scores"].values()}
        assert len(lengths) == 1, "open-loop and teacher-forced scores cover every frame"


@pytest.mark.parametrize("kind", ["embedding", "proxy"])
def test_env_uses_the_baseline_reward(kind, reward_models, env_config):
    dirs, _ = reward_models
    small = dict(episode_length=8, max_goal_steps=2, theta=1.0)
    env = RoboscapeWorldModelEnv(env_config(reward_type=kind, reward_model=str(dirs[kind]), **small), num_envs=2)
    env.reset(seed=0)
    for _ in range(env.frame_skip):  # the chunk's last action makes the frame and is paid its reward
        _, reward, *_ = env.step(np.zeros((2, 7), np.float32))
    model = RewardModel.from_pretrained(dirs[kind]).eval()
    with torch.no_grad():
        expected = model(env._rollout.features if kind == "embedding" else env._frames)
    np.testing.assert_allclose(reward, expected.numpy(), rtol=1e-5, atol=1e-6)
    other = "proxy" if kind == "embedding" else "embedding"
    with pytest.raises(ValueError, match=f"is a {kind} reward model"):
        RoboscapeWorldModelEnv(env_config(reward_type=other, reward_model=str(dirs[kind]), **small))
    with pytest.raises(ValueError, match="needs reward_model"):
        env_config(reward_type=kind, **small)


def test_reward_report(reward_models, demo_dataset, trained_tokenizer, world_models, token_cache, tmp_path):
    from lerobot_roboscape.envs.reward_report import RewardReportConfig, write_reward_report

    _, root = demo_dataset
    dirs, _ = reward_models
    cfg = draccus.parse(
        RewardReportConfig,
        args=[
            "--dataset.repo_id=test/demos",
            f"--dataset.root={root}",
            f"--env.tokenizer={trained_tokenizer}",
            f"--env.action_world_model={world_models['action']}",
            f"--env.text_world_model={world_models['text']}",
            f"--env.image_size={IMAGE_SIZE}",
            "--env.allow_random_lpips=true",
            "--env.max_goal_steps=3",
            f"--embedding_reward={dirs['embedding']}",
            f"--proxy_reward={dirs['proxy']}",
            f"--output_dir={tmp_path}",
        ],
    )
    report = write_reward_report(cfg)
    for name in ("reward_report.json", "reward_report.md", "reward_curves.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert set(report["summary"]) == {"world_model", "world_model_dense", "rule_based", "embedding", "proxy"}
    # Two families: each start's goal is also made under the other family's instruction, and judged against it.
    for episode in report["episodes"]:
        assert isinstance(episode["goal"]["final_nearer_own_goal_than_other_instructions"], bool)
    assert 0 <= report["goals"]["final_nearer_own_goal_than_other_instructions"] <= 1
    # Returns are summed over each family's fixed horizon (its longest successful episode), the last frame holding.
    facts = {row["episode_index"]: row for row in read_episode_info(root)}
    rows = {row["episode_index"]: row for row in token_cache.episodes}
    horizon = {}
    for index, row in rows.items():
        if facts[index]["success"]:
            family = facts[index]["task_family"]
            horizon[family] = max(horizon.get(family, 0), row["length"])
    for episode in report["episodes"]:
        index = episode["episode_index"]
        steps = horizon[facts[index]["task_family"]]
        for kind, values in episode["rewards"].items():
            assert len(values) == steps and np.isfinite(values).all(), kind
        # The rule-based curve is the dataset's own reward of the model frame seen after each step (a frame every
        # k steps), the last one held; the world model pays at each chunk's last step only.
        row, k = rows[index], STWorldModel.from_pretrained(world_models["action"]).config.frame_skip
        frames = model_frames(row["length"], k)
        seen = frames[np.minimum(np.arange(1, steps + 1) // k, len(frames) - 1)]
        recorded = token_cache.rewards[row["start"] + seen]
        np.testing.assert_allclose(episode["rewards"]["rule_based"], recorded)
        assert (np.asarray(episode["rewards"]["world_model"])[np.arange(steps) % k != k - 1] == 0).all()


def test_reward_report_open_loop_pays_the_frames_generated_from_the_recorded_actions(env_config, demo_dataset):
    from lerobot_roboscape.dataset.reader import open_dataset, read_episode
    from lerobot_roboscape.envs.reward_report import RewardReportConfig, episode_rewards
    from roboscape_core.errors import InvalidInputError

    _, root = demo_dataset
    env = RoboscapeWorldModelEnv(env_config(episode_length=None), num_envs=1)
    episode = read_episode(open_dataset("test/demos", root), 0)
    open_loop, real = episode_rewards(env, episode, {}, open_loop=True), episode_rewards(env, episode, {})
    k, indices = env.frame_skip, model_frames(len(episode.action), env.frame_skip)
    first = env.encode({cam: episode.images[cam][:1] for cam in env.cameras})
    actions = torch.from_numpy(episode.action[: (len(indices) - 1) * k])
    first_state = torch.from_numpy(episode.state[:1])
    with env.autocast():  # as the report generates: in the env's precision
        generated = env.action_model.generate(
            first[None], len(indices) - 1, actions=actions[None], states=first_state[None]
        )
    frames = torch.cat([first, generated.tokens[0]])
    done, _ = teacher_forced_done(env, frames, actions, torch.cat([first_state, generated.state[0].float()]))
    expected, _ = replay_rewards(env, episode.index, frames, done)
    np.testing.assert_allclose(open_loop["world_model"], expected, rtol=1e-5)
    np.testing.assert_allclose(open_loop["rule_based"], real["rule_based"])  # the recording's own
    with pytest.raises(InvalidInputError, match="frames must be one of"):
        RewardReportConfig(frames="imagined")
