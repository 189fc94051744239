import dataclasses
import json

import draccus
import numpy as np
import pytest
import torch

from lerobot_roboscape.training.checkpoints import FINAL, last_checkpoint
from lerobot_roboscape.training.loop import TRAIN_LOG
from lerobot_roboscape.world_model.clips import ClipMixture, ClipSampler, ResidentClips, gather, select_episodes
from lerobot_roboscape.world_model.measures.fidelity import FidelityConfig, evaluate_fidelity
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from lerobot_roboscape.world_model.robot_state import UNIT_STATE_STATS
from lerobot_roboscape.world_model.train import TrainWorldModelConfig, train_world_model
from tests.harness import assert_same_weights, command, kill_when, run

STEPS = 60


def train_args(demo_dataset, trained_tokenizer, token_cache, output_dir, control="action", steps=STEPS):
    _, root = demo_dataset
    return [
        "--dataset.repo_id=test/demos",
        f"--dataset.root={root}",
        f"--tokenizer={trained_tokenizer}",
        f"--token_cache={token_cache.root}",
        f"--output_dir={output_dir}",
        f"--wm.control={control}",
        "--wm.d_model=64",
        "--wm.n_head=2",
        "--wm.n_layer=2",
        "--wm.window=4",
        "--wm.prompt_frames=1",
        f"--train.steps={steps}",
        "--train.batch_size=4",
        "--train.save_freq=20",
        "--train.log_freq=5",
        "--train.warmup_steps=5",
        "--train.mixed_precision=no",
    ]


@pytest.fixture(scope="module")
def action_wm(demo_dataset, trained_tokenizer, token_cache, tmp_path_factory):
    out = tmp_path_factory.mktemp("wm_action")
    train_world_model(
        draccus.parse(TrainWorldModelConfig, args=train_args(demo_dataset, trained_tokenizer, token_cache, out))
    )
    return out


def test_clips_follow_the_action_convention(token_cache):
    episodes = select_episodes(token_cache)
    batch = ClipSampler(token_cache, episodes, window=4, batch_size=8, seed=0)(step=5)
    assert batch["tokens"].shape == (8, 4, 32) and batch["actions"].shape == (8, 4, 1, 7)
    again = ClipSampler(token_cache, episodes, window=4, batch_size=8, seed=0)(step=5)
    assert torch.equal(batch["tokens"], again["tokens"])  # a pure function of the step: resumable
    row = episodes[0]
    clip = _clip(ClipSampler(token_cache, episodes, 4, 1), start=0)
    assert clip["no_action"].tolist() == [True, False, False, False]
    assert (clip["actions"][1, 0] == token_cache.actions[row["start"]]).all()  # frame 1 carries action 0


def test_clips_of_action_chunks(token_cache):
    """With frame_skip k, clip frames are k control steps apart and each carries the k actions leading to it."""
    row = max(select_episodes(token_cache), key=lambda r: r["length"])
    start, k = row["start"], 3
    sampler = ClipSampler(token_cache, [row], window=3, batch_size=1, frame_skip=k)
    clip = _clip(sampler, start=1)
    assert np.array_equal(clip["tokens"], token_cache.tokens[start + np.array([1, 4, 7])].reshape(3, -1))
    assert np.array_equal(clip["anchor"], token_cache.tokens[start].reshape(-1))  # the episode's first frame
    assert clip["no_action"].tolist() == [False, False, False]
    assert (clip["actions"][0, :2] == 0).all()  # steps -2 and -1: before the episode
    assert np.array_equal(clip["actions"][0, 2], token_cache.actions[start])
    assert np.array_equal(clip["actions"][2], token_cache.actions[start + 4 : start + 7])  # steps 4..6 lead to 7
    end = _clip(sampler, start=row["length"] - 2)  # past the end: the last frame held, no actions
    assert (end["tokens"][1] == end["tokens"][2]).all() and (end["actions"][2] == 0).all()


def test_clip_mixture_draws_each_source_at_its_share(token_cache):
    episodes = select_episodes(token_cache)
    pick, push = (ClipSampler(token_cache, [row], 4, 1) for row in (episodes[0], episodes[3]))
    assert {row["task"] for row in (episodes[0], episodes[3])} == {pick.episodes[0]["task"], push.episodes[0]["task"]}
    assert set(ClipMixture([pick, push], [0.0, 1.0], 16)(3)["task"]) == {push.episodes[0]["task"]}
    batch = ClipMixture([pick, push], [0.25, 0.75], 200)(3)
    assert 30 <= batch["task"].count(pick.episodes[0]["task"]) <= 70  # 50 expected
    assert torch.equal(batch["tokens"], ClipMixture([pick, push], [0.25, 0.75], 200)(3)["tokens"])  # resumable
    with pytest.raises(ValueError, match="summing to 1"):
        ClipMixture([pick, push], [0.5, 0.6], 4)


def test_action_model_trains_on_exploratory_episodes_too(
    demo_dataset, exploration_dataset, trained_tokenizer, token_cache, tmp_path
):
    """The exploratory dataset joins the action model's clips at its share, and its actions join the normalisation
    statistics; the text model refuses it."""
    from lerobot.datasets.compute_stats import aggregate_feature_stats

    explore, explore_root = exploration_dataset
    extra = [
        "--exploration.repo_id=test/explore",
        f"--exploration.root={explore_root}",
        "--exploration_share=0.5",
        f"--cache_dir={tmp_path / 'caches'}",
    ]
    args = train_args(demo_dataset, trained_tokenizer, token_cache, tmp_path / "wm", steps=4) + extra
    model = train_world_model(draccus.parse(TrainWorldModelConfig, args=args))
    demo_stats = demo_dataset[0].meta.stats["action"]
    both = aggregate_feature_stats([demo_stats, explore.meta.stats["action"]])
    np.testing.assert_allclose(model.config.action_std, both["std"], rtol=1e-6)
    assert (np.asarray(model.config.action_std)[3:6] > 1.5 * np.asarray(demo_stats["std"])[3:6]).all()
    run = json.loads((tmp_path / "wm" / "train_config.json").read_text())
    assert run["exploration_token_cache"].startswith(str(tmp_path / "caches")) and run["exploration_share"] == 0.5
    cfg = draccus.parse(TrainWorldModelConfig, args=args)
    with pytest.raises(ValueError, match="train the action world model only, not the text one"):
        dataclasses.replace(cfg, wm=dataclasses.replace(cfg.wm, control="text"))


class _FixedStart:
    """A random generator that always draws the sampler's first episode, from control step `start`."""

    def __init__(self, start):
        self.start = start

    def choice(self, n, size, p):
        return np.zeros(size, dtype=np.int64)

    def integers(self, low, high):
        return np.full_like(high, self.start)


def _clip(sampler: ClipSampler, start: int) -> dict:
    """The sampler's first episode's clip from control step `start`, unbatched."""
    batch = gather(sampler.cache, sampler.draw(_FixedStart(start), 1))
    return {k: v[0] for k, v in batch.items()}


def test_resident_clips_are_the_samplers_batches(token_cache):
    """Sliced from the caches held on the device, the batches are the host sampler's, mixture included."""
    episodes = select_episodes(token_cache)
    sampler = ClipSampler(token_cache, episodes, window=4, batch_size=8, seed=3, frame_skip=2)
    mixture = ClipMixture([sampler, ClipSampler(token_cache, episodes[:2], 4, 8, 1, 2)], [0.6, 0.4], 16, seed=5)
    for source in (sampler, mixture):
        resident = ResidentClips(source, "cpu")
        for step in (0, 7):
            host, sliced = source(step), resident(step)
            assert host["task"] == sliced["task"]
            for key in ("tokens", "anchor", "actions", "no_action", "state", "done", "reward"):
                assert host[key].dtype == sliced[key].dtype and torch.equal(host[key], sliced[key]), key
    one_cache = token_cache.tokens.size * 4 + token_cache.actions.nbytes + token_cache.states.nbytes
    one_cache += 2 * len(token_cache.done) * 4
    assert resident.nbytes == 2 * one_cache  # the mixture's two samplers read one cache: it is held twice


def test_episode_filters(token_cache):
    every = select_episodes(token_cache)
    assert len(every) == 6
    kept = select_episodes(token_cache, only_optimal=True, only_successful=True)
    assert all(row["optimal"] and row["success"] for row in kept) and len(kept) < 6
    with pytest.raises(ValueError, match=r"episodes \[99\] are not in the token cache"):
        select_episodes(token_cache, episodes=[99])


def test_killed_run_resumes_to_the_same_model(action_wm, demo_dataset, trained_tokenizer, token_cache, tmp_path):
    args = train_args(demo_dataset, trained_tokenizer, token_cache, tmp_path)
    kill_when(command("train_wm", *args), lambda: last_checkpoint(tmp_path) is not None)
    interrupted_at = json.loads((last_checkpoint(tmp_path) / "training_step.json").read_text())["step"]
    assert interrupted_at < STEPS and not (tmp_path / FINAL).exists()

    with pytest.raises(FileExistsError, match="--resume=true"):
        train_world_model(draccus.parse(TrainWorldModelConfig, args=args))
    resumed = run(command("train_wm", *args, "--train.resume=true"))
    assert f"{interrupted_at}/{STEPS}" in resumed.stderr  # the progress bar starts at the checkpoint's step
    final = json.loads((last_checkpoint(tmp_path) / "training_step.json").read_text())["step"]
    assert final == STEPS
    assert_same_weights(action_wm / FINAL / "model.safetensors", tmp_path / FINAL / "model.safetensors")


def test_trained_model_learns_and_loads(action_wm):
    model = STWorldModel.from_pretrained(action_wm / FINAL)
    assert model.config.vocab_size == 64 and model.config.tokens_per_frame == 32  # taken from the token cache
    logs = list((action_wm / "logs").rglob("events.out.tfevents*"))
    assert logs, "TensorBoard logs are written"


def test_training_log_reads_throughput_and_flops(action_wm):
    """Every logging step's line carries the losses and, from the second on, clips/s and the TFLOP/s they make with
    the model's FLOPs per clip (MFU needs a known peak: none on a CPU)."""
    lines = [json.loads(line) for line in (action_wm / TRAIN_LOG).read_text().splitlines()]
    assert [line["step"] for line in lines] == [1, *range(5, STEPS + 1, 5)]
    flops = STWorldModel.from_pretrained(action_wm / FINAL).training_flops_per_clip()
    for line in lines[1:]:
        assert line["samples_per_s"] > 0 and "mfu" not in line
        assert line["tflops"] == pytest.approx(line["samples_per_s"] * flops / 1e12, rel=1e-3)
    assert all(0 <= line["token_acc"] <= 1 and line["loss"] > 0 for line in lines)


def test_resident_clips_train_the_same_model(demo_dataset, trained_tokenizer, token_cache, tmp_path):
    """Clips sliced from the caches held on the device train the model the host sampler's clips train."""
    for resident in ("false", "true"):
        args = train_args(demo_dataset, trained_tokenizer, token_cache, tmp_path / resident, steps=3)
        extra = [f"--train.resident={resident}", "--done_tuning_steps=0"]  # the clips are what differs
        train_world_model(draccus.parse(TrainWorldModelConfig, args=[*args, *extra]))
    assert_same_weights(
        tmp_path / "false" / FINAL / "model.safetensors", tmp_path / "true" / FINAL / "model.safetensors"
    )


def test_text_world_model_trains_on_successful_optimal_episodes(demo_dataset, trained_tokenizer, token_cache, tmp_path):
    model = train_world_model(
        draccus.parse(
            TrainWorldModelConfig, args=train_args(demo_dataset, trained_tokenizer, token_cache, tmp_path, "text", 4)
        )
    )
    loaded = STWorldModel.from_pretrained(tmp_path / FINAL)
    assert loaded.config.control == "text" and (tmp_path / FINAL / "text_encoder").is_dir()
    task = "push the red cube forward"
    prompt = torch.from_numpy(token_cache.tokens[:1].astype("int64")).reshape(1, 1, -1)
    state = torch.from_numpy(token_cache.states[:1]).reshape(1, 1, -1)
    a = model.eval().generate(prompt, 2, instructions=[task], states=state)
    b = loaded.eval().generate(prompt, 2, instructions=[task], states=state)
    assert torch.equal(a.tokens, b.tokens) and torch.equal(a.state, b.state)
    assert loaded.config.state_mean is not None and len(loaded.config.state_mean) == token_cache.state_dim


def test_fidelity_report(action_wm, demo_dataset, trained_tokenizer, tmp_path):
    _, root = demo_dataset
    cfg = draccus.parse(
        FidelityConfig,
        args=[
            "--dataset.repo_id=test/demos",
            f"--dataset.root={root}",
            "--dataset.episodes=[1,3]",
            f"--tokenizer={trained_tokenizer}",
            f"--world_model={action_wm / FINAL}",
            f"--output_dir={tmp_path}",
            "--horizon=8",
            "--allow_random_lpips=true",
        ],
    )
    report = evaluate_fidelity(cfg)
    frames = 8 // STWorldModel.from_pretrained(action_wm / FINAL).config.frame_skip  # a frame per k control steps
    assert frames == 2 and report["episodes"][0]["frame_skip"] == 4
    for name in ("fidelity.json", "fidelity.md", "fidelity.png", "side_by_side.mp4"):
        assert (tmp_path / name).stat().st_size > 0
    assert [e["episode_index"] for e in report["episodes"]] == [1, 3]
    for key, values in report["per_step"].items():
        assert len(values) == frames and all(v is not None and v == v for v in values), key
    assert report["lpips_trunk"].startswith("random")
    # The reconstruction baseline is the tokenizer's own round trip; PSNR is in a sane range for both.
    assert 5 < report["mean"]["reconstruction_psnr"] < 60 and 5 < report["mean"]["prediction_psnr"] < 60
    # The demo dataset has the object's masks: the object's region is measured per step too.
    assert len(report["per_step"]["prediction_object_psnr"]) == frames
    assert "object PSNR pred" in (tmp_path / "fidelity.md").read_text()


def test_fidelity_needs_the_action_model(demo_dataset, trained_tokenizer, tmp_path):
    _, root = demo_dataset
    text = STWorldModel(
        dataclasses.replace(
            draccus.parse(TrainWorldModelConfig, args=["--wm.control=text", "--wm.n_layer=1"]).wm, **UNIT_STATE_STATS
        )
    )
    text.save_pretrained(tmp_path / "text")
    cfg = FidelityConfig(tokenizer=str(trained_tokenizer), world_model=str(tmp_path / "text"), output_dir=tmp_path)
    cfg.dataset.root = str(root)
    with pytest.raises(ValueError, match="is a text world model"):
        evaluate_fidelity(cfg)


def test_done_head_tuned_on_its_own_open_loop_frames(demo_dataset, trained_tokenizer, token_cache, tmp_path):
    """After training, the done head alone is refitted on the model's open-loop frames and the real ones: it
    separates the open-loop frames of done from the others, and nothing but the head changes."""
    args = train_args(demo_dataset, trained_tokenizer, token_cache, tmp_path, steps=4)
    model = train_world_model(
        draccus.parse(TrainWorldModelConfig, args=[*args, "--done_tuning_steps=300", "--done_tuning_episodes=6"])
    )
    summary = json.loads((tmp_path / "done_tuning.json").read_text())
    assert summary["episodes"] == 6 and summary["frames"]["open_loop"] == summary["frames"]["real"] > 0
    assert summary["loss"]["last"] < summary["loss"]["first"]
    assert summary["mean_done_of_positive_open_loop_frames"] > summary["mean_done_of_negative_open_loop_frames"]
    saved = STWorldModel.from_pretrained(tmp_path / FINAL).state_dict()
    trained = STWorldModel.from_pretrained(last_checkpoint(tmp_path) / FINAL).state_dict()
    changed = {name for name, weight in saved.items() if not torch.equal(weight, trained[name])}
    assert changed and all(name.startswith("done_head.") for name in changed)
    assert all(torch.equal(model.state_dict()[name], weight) for name, weight in saved.items())


def test_a_member_started_from_a_model_retrains_its_top_alone(
    action_wm, demo_dataset, trained_tokenizer, token_cache, tmp_path
):
    """`init_from` with `retrain_blocks`: the trunk keeps the trained model's weights bit for bit; the last blocks and
    the heads are drawn afresh from the seed and trained, and the member's loss falls as they learn. A model and data
    that differ, or retrain_blocks without a model, are refused by name."""
    from lerobot_roboscape.envs.ensemble import mutual_information
    from roboscape_core.errors import InvalidInputError

    base = action_wm / FINAL
    args = train_args(demo_dataset, trained_tokenizer, token_cache, tmp_path, steps=20)
    start = [f"--init_from={base}", "--retrain_blocks=1", "--train.seed=1", "--done_tuning_steps=0"]
    train_world_model(draccus.parse(TrainWorldModelConfig, args=[*args, *start]))
    trained, member = STWorldModel.from_pretrained(base), STWorldModel.from_pretrained(tmp_path / FINAL)
    top = {
        name
        for name, _ in member.named_parameters()
        if name.startswith(("blocks.1.", "ln_f.", "head.", "done_head.", "robot_state.head."))
    }
    assert top and any(name.startswith("blocks.0.") for name, _ in member.named_parameters())
    theirs = dict(trained.named_parameters())
    for name, weight in member.named_parameters():
        assert torch.equal(weight, theirs[name]) != (name in top), name  # frozen: equal; retrained: not
    losses = [json.loads(line)["loss"] for line in (tmp_path / TRAIN_LOG).read_text().splitlines()]
    assert losses[-1] < losses[0]
    # The two disagree on a frame of the data: a member an ensemble can read.
    k = member.config.frame_skip
    batch = ClipSampler(token_cache, select_episodes(token_cache), 4, 2, seed=0, frame_skip=k)(step=0)
    with torch.no_grad():
        logits = [
            m.eval().compute_logits(
                batch["tokens"], m.encode_control(batch["actions"], batch["no_action"]), states=batch["state"]
            )[0][:, -1]
            for m in (trained, member)
        ]
    assert (mutual_information(logits) > 1e-4).all()

    with pytest.raises(InvalidInputError, match="differ in .*'control': \\('action', 'text'\\)"):
        text = [a for a in args if not a.startswith("--wm.control")] + ["--wm.control=text"]
        train_world_model(draccus.parse(TrainWorldModelConfig, args=[*text, *start, f"--output_dir={tmp_path / 't'}"]))
    with pytest.raises(InvalidInputError, match="has 2 blocks; cannot take the last 3"):
        again = [*args, *start[:1], "--retrain_blocks=3", f"--output_dir={tmp_path / 'b'}"]
        train_world_model(draccus.parse(TrainWorldModelConfig, args=again))
    with pytest.raises(InvalidInputError, match="give init_from"):
        TrainWorldModelConfig(retrain_blocks=1)
