"""roboscape_wm, the world models as a LeRobot env: gymnasium's checks, batched steps, precision, determinism, its
starts (from the dataset, branched, a file, given frames), its state, and the inputs it refuses."""

import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from lerobot_roboscape.dataset.reader import open_dataset, read_episode, read_frames
from lerobot_roboscape.envs.batched import SingleEnv
from lerobot_roboscape.envs.world_model_env import RoboscapeWorldModelEnv
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from roboscape_core.errors import InvalidInputError
from tests.conftest import IMAGE_SIZE


def test_gymnasium_env_checker(env_config):
    check_env(SingleEnv(RoboscapeWorldModelEnv(env_config(temperature=1.0), num_envs=1)), skip_render_check=False)


def test_batched_reset_and_step(env_config):
    env = RoboscapeWorldModelEnv(env_config(), num_envs=3)
    obs, info = env.reset(seed=0)
    assert set(obs["pixels"]) == {"third_view", "wrist"}
    assert obs["pixels"]["wrist"].shape == (3, IMAGE_SIZE, IMAGE_SIZE, 3) and obs["pixels"]["wrist"].dtype == np.uint8
    assert obs in env.observation_space
    assert len(info["task"]) == 3 and info["goal"]["third_view"].shape == (3, IMAGE_SIZE, IMAGE_SIZE, 3)
    success = np.zeros(3, dtype=bool)
    for step in range(6):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert reward.shape == (3,) and np.isfinite(reward).all()
        assert not terminated.any() and truncated.all() == (step == 5)  # Algorithm 1: the fixed horizon
        success |= info["done_probability"] >= env.config.theta
        assert np.array_equal(info["is_success"], success)  # done crossed theta at any step
    for key in ("reward_sparse", "reward_dense", "distance_to_goal", "done_probability", "clipped_actions"):
        assert info[key].shape == (3,)
    assert env.render()[0].shape == (2 * IMAGE_SIZE, 2 * IMAGE_SIZE, 3)
    assert env.call("_max_episode_steps") == (6, 6, 6) and len(env.call("task_description")) == 3


def anchored_copy(path, out):
    """The saved world model at `path` as an anchored one (its anchor embedding drawn), saved in `out`."""
    model = STWorldModel.from_pretrained(path)
    model.config.anchor = True
    torch.manual_seed(0)
    anchored = STWorldModel(model.config)
    missing = anchored.load_state_dict(model.state_dict(), strict=False).missing_keys
    assert missing == ["anchor_emb"]
    anchored.save_pretrained(out)
    return str(out)


def test_anchored_world_models_run_the_env_past_their_window(env_config, tmp_path):
    """Goals from an anchored text model, episodes from an anchored action model, both reading the start's first
    frame after it has left their window."""
    base = env_config()
    config = env_config(
        action_world_model=anchored_copy(base.action_world_model, tmp_path / "action"),
        text_world_model=anchored_copy(base.text_world_model, tmp_path / "text"),
        episode_length=48,
        max_goal_steps=48,
    )
    env = RoboscapeWorldModelEnv(config, num_envs=2)
    env.reset(seed=0)
    first = torch.stack([s.first_tokens for s in env._starts]).to(env._rollout.anchor.device)
    window = env.action_model.config.window
    for _ in range(48):
        _, reward, _, _, _ = env.step(env.action_space.sample())
        assert np.isfinite(reward).all()
    assert env._rollout.frames_seen > window and torch.equal(env._rollout.anchor[:2], first)


def test_bfloat16_precision_runs_the_models_under_autocast(env_config, monkeypatch):
    """precision=bfloat16: the world model's passes compute in bf16, the env's outputs stay float32 and finite, and
    the goals it makes are told apart from float32 ones."""
    from lerobot_roboscape.world_model.modeling_world_model import STWorldModel

    dtypes = []
    compute_logits = STWorldModel.compute_logits

    def spy(self, *args, **kwargs):
        logits, *rest = compute_logits(self, *args, **kwargs)
        dtypes.append(logits.dtype)
        return logits, *rest

    monkeypatch.setattr(STWorldModel, "compute_logits", spy)
    env = RoboscapeWorldModelEnv(env_config(precision="bfloat16"), num_envs=2)
    env.reset(seed=0)
    for _ in range(4):  # one model frame (k = 4)
        obs, reward, *_, info = env.step(env.action_space.sample())
        assert reward.dtype == np.float32 and np.isfinite(reward).all() and np.isfinite(info["done_probability"]).all()
    assert dtypes and set(dtypes) == {torch.bfloat16}
    assert obs in env.observation_space
    assert env._goal_settings()["precision"] == "bfloat16"
    with pytest.raises(InvalidInputError, match="precision must be one of .*'float16'"):
        env_config(precision="float16")


def test_determinism_under_a_seed(env_config):
    env = RoboscapeWorldModelEnv(env_config(temperature=1.0), num_envs=2)
    actions = np.random.default_rng(0).uniform(-1, 1, (5, 2, 7)).astype(np.float32)

    def rollout(seed):
        obs, _ = env.reset(seed=seed)
        frames, rewards = [obs["pixels"]["wrist"]], []
        for a in actions:
            obs, reward, *_ = env.step(a)
            frames.append(obs["pixels"]["wrist"])
            rewards.append(reward)
        return np.stack(frames), np.stack(rewards)

    first, again = rollout(7), rollout(7)
    np.testing.assert_array_equal(first[0], again[0])
    np.testing.assert_array_equal(first[1], again[1])


def test_bad_actions(env_config):
    env = RoboscapeWorldModelEnv(env_config(), num_envs=2)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(2, 7\).*got \(2, 6\)"):
        env.step(np.zeros((2, 6), np.float32))
    bad = np.zeros((2, 7), np.float32)
    bad[1, 3] = np.nan
    with pytest.raises(ValueError, match=r"envs \[1\] contain NaN or inf"):
        env.step(bad)
    wide = np.zeros((2, 7), np.float32)
    wide[0, :3] = 5.0
    *_, info = env.step(wide)
    assert info["clipped_actions"].tolist() == [3, 0]


def test_missing_world_model_is_named(env_config, tmp_path):
    with pytest.raises(FileNotFoundError, match="no action world model at .*roboscape-train-wm"):
        RoboscapeWorldModelEnv(env_config(action_world_model=str(tmp_path / "nowhere")))


def test_starts_per_scene_keeps_the_first_episodes_of_each_scene(env_config, demo_dataset):
    env = RoboscapeWorldModelEnv(env_config(starts_per_scene=1), num_envs=1)
    every = RoboscapeWorldModelEnv(env_config(), num_envs=1)
    scenes = [(s.facts["task_family"], s.facts["scene"]) for s in env.starts]
    assert len(scenes) == len(set(scenes)) == len({(s.facts["task_family"], s.facts["scene"]) for s in every.starts})
    assert len(every.starts) > len(env.starts)


def test_branched_starts_begin_at_real_frames_along_an_episode_and_share_its_goal(env_config, demo_dataset):
    env = RoboscapeWorldModelEnv(env_config(starts_per_scene=1, branches_per_episode=3), num_envs=4)
    by_episode = {}
    for start in env.starts:
        by_episode.setdefault(start.episode_index, []).append(start)
    demos, _ = demo_dataset
    for index, starts in by_episode.items():
        length = demos.meta.episodes[index]["length"]
        assert [s.frame for s in starts] == [0, round((length - 1) / 3), round(2 * (length - 1) / 3)]
        real = env.encode(read_frames(demos, index, [s.frame for s in starts]))
        assert torch.equal(torch.stack([s.first_tokens for s in starts]), real)  # real states, as recorded
        goals, _ = env.goal_bank.goals_for(starts)
        assert (goals == goals[0]).all()  # the episode's goal, made from its first frame
    _, info = env.reset(seed=0)
    assert set(info["start_frame"]) <= {s.frame for s in env.starts}


def test_starts_saved_to_a_file_run_the_env_without_its_dataset(env_config, tmp_path):
    """export_starts writes the env's starts (branched ones too); an env given the file and no dataset has the same
    starts and action range, and plays the same episodes. A file made with another selection, or not a starts
    file, is refused by name."""
    from lerobot_roboscape.envs.starts import export_starts

    selection = dict(starts_per_scene=1, branches_per_episode=2, precision="float32")
    path = export_starts(env_config(**selection), tmp_path / "starts.safetensors")
    from_data = RoboscapeWorldModelEnv(env_config(**selection), num_envs=2)
    from_file = RoboscapeWorldModelEnv(
        env_config(**selection, starts_file=str(path), dataset_repo_id=None, dataset_root=None), num_envs=2
    )
    assert len(from_file.starts) == len(from_data.starts) and from_file.cameras == from_data.cameras
    for a, b in zip(from_file.starts, from_data.starts, strict=True):
        assert (a.episode_index, a.task, a.facts, a.horizon, a.frame) == (
            b.episode_index,
            b.task,
            b.facts,
            b.horizon,
            b.frame,
        )
        assert torch.equal(a.first_tokens, b.first_tokens) and torch.equal(a.goal_prompt, b.goal_prompt)
    np.testing.assert_array_equal(from_file.action_range[0], from_data.action_range[0])
    assert from_file._goal_settings() == from_data._goal_settings()  # one goal file serves both
    episodes = []
    for env in (from_data, from_file):
        observation, _ = env.reset(seed=3)
        steps = [env.step(np.full((2, 7), 0.2, np.float32)) for _ in range(8)]
        episodes.append((observation, [(o, r) for o, r, *_ in steps]))
    for camera, frames in episodes[0][0]["pixels"].items():
        np.testing.assert_array_equal(episodes[1][0]["pixels"][camera], frames)
    for (o_data, r_data), (o_file, r_file) in zip(episodes[0][1], episodes[1][1], strict=True):
        np.testing.assert_allclose(r_file, r_data, atol=1e-6)
        np.testing.assert_array_equal(o_file["pixels"]["third_view"], o_data["pixels"]["third_view"])

    with pytest.raises(InvalidInputError, match="made with other starts .*'branches_per_episode': \\(2, 1\\)"):
        RoboscapeWorldModelEnv(env_config(starts_per_scene=1, starts_file=str(path)), num_envs=1)
    (tmp_path / "not_starts.safetensors").write_bytes(b"nonsense")
    with pytest.raises(InvalidInputError, match="not_starts.safetensors is not a file that export_starts writes"):
        RoboscapeWorldModelEnv(env_config(starts_file=str(tmp_path / "not_starts.safetensors")), num_envs=1)


def test_action_range_of_the_dataset(env_config, demo_dataset, mlp_checkpoint):
    """The world-model env reports its dataset's action range and clips to it when asked; the MLP policy's actions
    stay inside it, and it lies inside the simulator's [-1, 1]."""
    from lerobot_roboscape.rl.policy_loading import PolicyIO, load_policy

    env = RoboscapeWorldModelEnv(env_config(clip_actions=True), num_envs=2)
    low, high = env.action_range
    data = open_dataset("test/demos", demo_dataset[1])
    actions = np.asarray(data.hf_dataset["action"])
    np.testing.assert_allclose(low, actions.min(0), atol=1e-6)
    np.testing.assert_allclose(high, actions.max(0), atol=1e-6)
    assert (low >= -1).all() and (high <= 1).all()

    policy, pre, post = load_policy(mlp_checkpoint, "cpu")
    io = PolicyIO(pre, post)
    obs, _ = env.reset(seed=0)
    for _ in range(3):
        action = io.env_action(policy.sample_action(io.batch(obs["pixels"], env.tasks())).action)[:, 0]  # 1st of chunk
        assert ((action >= low - 1e-5) & (action <= high + 1e-5)).all()
        obs, *_ = env.step(action)

    def next_frame(action):
        env.reset(seed=0)
        return env.step(np.broadcast_to(action, (2, 7)))[0]["pixels"]["wrist"]

    np.testing.assert_array_equal(next_frame(np.ones(7, np.float32)), next_frame(high))  # clipped to the range


def test_soak_at_batch_64_is_finite_with_flat_memory(env_config):
    """300 steps of 64 episodes (resets included): finite outputs, and the resident memory stops growing once the
    first episodes have filled the caches (scripts/benchmarks/soak_world_model_env.py prints the curve)."""
    import psutil

    env = RoboscapeWorldModelEnv(env_config(episode_length=50, temperature=1.0, similarity="lpips"), num_envs=64)
    rng, process, rss = np.random.default_rng(0), psutil.Process(), {}
    env.reset(seed=0)
    for step in range(1, 301):
        obs, reward, terminated, truncated, info = env.step(rng.uniform(-1, 1, (64, 7)).astype(np.float32))
        assert np.isfinite(reward).all() and np.isfinite(info["done_probability"]).all()
        assert np.isfinite(info["distance_to_goal"]).all()
        if (terminated | truncated).all():
            env.reset()
        if step in (1, 100, 200, 300):
            rss[step] = process.memory_info().rss / 2**20
    assert rss[300] - rss[100] < 0.05 * rss[100], f"RSS (MiB) at steps 1, 100, 200, 300: {rss}"


def test_reset_from_given_frames_starts_there_with_a_goal_made_from_them(env_config, demo_dataset):
    """Another env's first observation (the simulator's) becomes the start: the frame shown is those pixels through
    the tokenizer, the goal is the text model's from them under the given instruction, and the horizon is as given."""
    _, root = demo_dataset
    env = RoboscapeWorldModelEnv(env_config(), num_envs=2)
    episode = read_episode(open_dataset("test/demos", root), 4)  # a push episode
    frames, states = episode.images, episode.state[[0, -1]]
    first = {cam: np.stack([images[0], images[-1]]) for cam, images in frames.items()}
    with pytest.raises(InvalidInputError, match=r"options\['states'\] of shape \(2, 16\)"):
        env.reset(options={"frames": first, "task": ["push the cube"] * 2})
    obs, info = env.reset(
        options={"frames": first, "states": states, "task": ["push the cube", "push the cube"], "horizon": [5, 9]}
    )
    expected = env._pixels(env.decode(env.encode(first)))
    for cam in env.cameras:
        assert np.array_equal(obs["pixels"][cam], expected[cam])
    assert not np.array_equal(obs["pixels"]["third_view"][0], obs["pixels"]["third_view"][1])
    goals = env.goal_bank.generate(env._starts)
    for cam in env.cameras:  # the goal of each start is the one made from its own frame
        assert np.array_equal(info["goal"][cam], env._pixels(env.decode(torch.stack([g.tokens for g in goals])))[cam])
    assert (info["episode_index"] == -1).all() and info["task"] == ["push the cube"] * 2
    ended = [env.step(np.zeros((2, 7), np.float32))[3] for _ in range(9)]
    assert [t[0] for t in ended].index(True) == 4 and [t[1] for t in ended].index(True) == 8  # horizons 5 and 9
    last = {cam: np.stack([images[-1], images[-1]]) for cam, images in frames.items()}  # a goal given instead
    _, info = env.reset(options={"frames": first, "states": states, "task": ["push the cube"] * 2, "goal_frames": last})
    for cam in env.cameras:
        assert np.array_equal(info["goal"][cam], env._pixels(env.decode(env.encode(last)))[cam])
    assert info["goal_from_text_model"].all()


def test_include_state_returns_the_start_state_then_the_models_own(env_config, demo_dataset):
    """With include_state, `agent_pos` is the start frame's recorded state at reset, then the action model's
    predicted state, which moves with the actions and is the state it generates each frame under."""
    _, root = demo_dataset
    env = RoboscapeWorldModelEnv(env_config(include_state=True), num_envs=2)
    obs, info = env.reset(options={"episode_index": 0})
    assert obs in env.observation_space and obs["agent_pos"].shape == (2, 16)
    recorded = read_episode(open_dataset("test/demos", root), 0).state[0]
    np.testing.assert_allclose(obs["agent_pos"], np.stack([recorded, recorded]), rtol=1e-6)
    actions = np.stack([np.zeros(7), np.full(7, 0.8)]).astype(np.float32)
    for _ in range(env.frame_skip):
        obs, *_ = env.step(actions)
    first = env.encode(read_frames(open_dataset("test/demos", root), 0, [0]))
    with env.autocast():  # the same first frame, state and actions, generated outside the env
        expected = env.action_model.generate(
            first[None].expand(2, -1, -1),
            1,
            actions=torch.from_numpy(actions)[:, None].expand(-1, env.frame_skip, -1),
            states=torch.from_numpy(np.stack([recorded, recorded]))[:, None],
        ).state[:, 0]
    # Both paths sum in another order on several threads (`-n 0`): 5e-5 apart there, far below the actions' effect.
    np.testing.assert_allclose(obs["agent_pos"], expected.float().numpy(), rtol=1e-5, atol=1e-4)


def test_reset_from_frames_refuses_a_wrong_camera_or_shape(env_config):
    env = RoboscapeWorldModelEnv(env_config(), num_envs=1)
    good = np.zeros((1, IMAGE_SIZE, IMAGE_SIZE, 3), np.uint8)
    with pytest.raises(InvalidInputError, match="cameras"):
        env.reset(options={"frames": {"third_view": good}, "task": ["push"]})
    with pytest.raises(InvalidInputError, match=r"frames\['wrist'\] has shape"):
        env.reset(options={"frames": {"third_view": good, "wrist": good[:, :8]}, "task": ["push"]})
    with pytest.raises(InvalidInputError, match="goal_source"):
        RoboscapeWorldModelEnv(env_config(goal_source="dataset_last_frame"), num_envs=1).reset(
            options={"frames": {"third_view": good, "wrist": good}, "task": ["push"]}
        )


def test_a_batch_whose_cache_cannot_fit_is_refused_at_construction(env_config):
    """The key/value cache of num_envs episodes is checked against the device's free memory before any generation,
    and the refusal names the batch, the window, the bytes needed and those free."""
    from lerobot_roboscape.envs.world_model_env import free_memory_bytes
    from lerobot_roboscape.world_model.modeling_world_model import STWorldModel

    model = STWorldModel.from_pretrained(env_config().action_world_model)
    per_episode = model.cache_bytes(1)
    too_many = free_memory_bytes("cpu") // per_episode + 1
    refusal = rf"{too_many} episodes at once need .* GiB of key/value cache \(window .* GiB are free on cpu"
    with pytest.raises(InvalidInputError, match=refusal):
        RoboscapeWorldModelEnv(env_config(precision="float32"), num_envs=too_many)
