"""The done-refresh lever (Dyna-style, issue 49): PPO in the world model whose done head is refitted, before each
slice of the PPO clock, on simulator rollouts of the current policy.

A policy that games the world model drives it to frames its done head calls success although the task is not
done. Refitting the head on what the current policy does in the simulator (labelled by the simulator's success)
takes that exploit away as soon as the policy finds it. It uses the simulator, so its row says how many simulator
steps it spent beside PPO's clock; the demonstrations go into every refit so the head keeps what it learned.
"""

import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from lerobot_roboscape.dataset.reader import open_dataset
from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig
from lerobot_roboscape.envs.maniskill_env import RoboscapeManiSkillEnv
from lerobot_roboscape.evaluation.success_rate import record_episodes
from lerobot_roboscape.io.atomic import write_text_atomically
from lerobot_roboscape.io.records import from_record
from lerobot_roboscape.pipeline.resume import is_done, mark_done, start, train_once
from lerobot_roboscape.rl.configuration_ppo import PPOConfig
from lerobot_roboscape.rl.policy_loading import PolicyIO, load_policy
from lerobot_roboscape.rl.ppo import train_ppo
from lerobot_roboscape.rl.ppo_state import checkpoint_seconds
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.tokenizer.token_cache import episodes_token_cache, load_or_build_token_cache
from lerobot_roboscape.training.checkpoints import FINAL, last_checkpoint, publish_final
from lerobot_roboscape.training.loop import resolve_device, save_atomically
from lerobot_roboscape.world_model.done_tuning import SourceFit, refit_done_head
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel

REFRESH_DIR = "done_refresh"  # in the PPO run's folder: round_<r>/ (the refitted model and its figures)
REFRESH_SEED = 300_000  # the rollouts' initial states, apart from Table 1's and the curve's
FOCUS_SEED = 310_000  # those of the rollouts in the focus scenes
BATCH = 8  # simulator episodes played at once


@dataclass
class DoneRefresh:
    """Args:
    sim: the simulator env the policy's rollouts run in (the training scenes).
    tokenizer: the tokenizer the world model reads.
    demonstrations_repo_id, demonstrations_root: the demonstrations whose episodes are refitted on beside the
        rollouts (their token cache is found in `cache_dir`, as the world model's training left it).
    cache_dir: the run's token caches.
    rounds: equal slices of PPO's clock; the head is refitted before each slice, from the last refit's head (the
        first from the base model's, on rollouts of the policy PPO starts from).
    episodes: simulator episodes of the current policy per refit.
    focus_scenes, focus_episodes: that many more episodes per refit in these scenes alone: where the policy
        succeeds (the scenes its SFT learned), so that the head sees the policy's successes beside its failures.
    demonstrations: demonstration episodes (spread over the dataset) per refit.
    steps: full-batch steps of the head's fit.
    """

    sim: RoboscapeManiSkillEnvConfig
    tokenizer: str
    demonstrations_repo_id: str
    demonstrations_root: str
    cache_dir: str
    rounds: int = 3
    episodes: int = 16
    focus_scenes: list[str] = field(default_factory=list)
    focus_episodes: int = 0
    demonstrations: int = 16
    steps: int = 300
    device: str = "auto"


def ppo_with_done_refresh(cfg: PPOConfig, fresh: bool = False, *, refresh: DoneRefresh) -> Path:
    """PPO in the world model of `cfg.env` over `refresh.rounds` equal slices of its run (of `cfg.time_budget_s`
    where it has one, else of `cfg.iterations`), its done head refitted before each slice; one run folder (so its
    checkpoints form one curve), resumed from its last checkpoint and round when interrupted. Returns the final
    checkpoint."""
    folder = Path(cfg.output_dir)
    train_once(folder, {"ppo": cfg, "refresh": refresh}, fresh, lambda resume: _rounds(cfg, refresh, resume))
    return publish_final(folder)


def slice_ends(cfg: PPOConfig, rounds: int) -> list[dict]:
    """Where each slice of the run ends, as PPO's settings: its clock's seconds, or its iterations (whole ones, the
    last slice ending at the run's)."""
    if cfg.time_budget_s is not None:
        return [{"time_budget_s": cfg.time_budget_s * (r + 1) / rounds} for r in range(rounds)]
    return [{"iterations": math.ceil(cfg.iterations * (r + 1) / rounds)} for r in range(rounds)]


def _rounds(cfg: PPOConfig, refresh: DoneRefresh, resume: bool) -> None:
    folder, env = Path(cfg.output_dir), cfg.env
    for r, end in enumerate(slice_ends(cfg, refresh.rounds)):
        # The first refit plays the policy PPO starts from: the head is tuned on demonstrations only, and can call
        # that policy's failures success from the first iteration. Each refit starts from the last one's head.
        policy = last_checkpoint(folder) / FINAL if r else cfg.policy_path  # a path or a Hub repo id
        model = refreshed_world_model(refresh, env.action_world_model, policy, r, folder)
        env = replace(env, action_world_model=str(model))
        if _slice_ran(folder, end):  # before an interruption
            continue
        train_ppo(replace(cfg, env=env, **end, resume=resume or last_checkpoint(folder) is not None))


def _slice_ran(folder: Path, end: dict) -> bool:
    checkpoint = last_checkpoint(folder)
    if checkpoint is None:
        return False
    if "time_budget_s" in end:
        return checkpoint_seconds(checkpoint) >= end["time_budget_s"]
    return int(checkpoint.name) >= end["iterations"]


@dataclass(frozen=True)
class RefreshRound:
    """The figures of one refit: its round, the policy that played the rollouts, their simulator steps and success
    (over all of them, and over those in the focus scenes alone when some were), and the fit's
    (`done_tuning.refit_done_head`: the loss first and last, each source's frames and positives)."""

    round: int
    policy: str
    simulator_steps: int
    rollout_success: float
    loss: dict[str, float]
    rollouts: SourceFit
    demonstrations: SourceFit
    focus_success: float | None = None

    @classmethod
    def from_json(cls, data: dict) -> "RefreshRound":
        return from_record(cls, data)


def refresh_rounds(folder: Path) -> list[RefreshRound]:
    """The figures of each refit of a run."""
    paths = sorted(Path(folder).glob(f"{REFRESH_DIR}/round_*/refresh.json"))
    return [RefreshRound.from_json(json.loads(p.read_text())) for p in paths]


def refreshed_world_model(refresh: DoneRefresh, base: str, policy: str | Path, round_: int, run: Path) -> Path:
    """Round `round_`'s action model: the base model with its done head refitted on `refresh.episodes` simulator
    rollouts of `policy` and on demonstrations. Done once per round: a resumed run reads it back."""
    folder = run / REFRESH_DIR / f"round_{round_}"
    settings = {"base": base, "refresh": asdict(refresh), "round": round_}
    if not is_done(folder, settings, fresh=False):
        start(folder).mkdir(parents=True)
        _refit(refresh, base, policy, round_, folder)
        mark_done(folder, settings)
    return folder / FINAL


def _refit(refresh: DoneRefresh, base: str, policy_path: str | Path, round_: int, folder: Path) -> None:
    device = resolve_device(refresh.device)
    policy, preprocessor, postprocessor = load_policy(policy_path, device)
    policy.eval()
    io = PolicyIO(preprocessor, postprocessor)
    rollouts = _simulator_rollouts(refresh.sim, refresh.episodes, policy, io, REFRESH_SEED + 7919 * round_)
    focus = []
    if refresh.focus_episodes:
        sim = replace(refresh.sim, scenes=list(refresh.focus_scenes))
        focus = _simulator_rollouts(sim, refresh.focus_episodes, policy, io, FOCUS_SEED + 7919 * round_)
    rollouts += focus
    tokenizer = VisualTokenizer.from_pretrained(refresh.tokenizer).to(device).eval()
    model = STWorldModel.from_pretrained(base).to(device)
    demos = open_dataset(refresh.demonstrations_repo_id, refresh.demonstrations_root)
    demo_cache = load_or_build_token_cache(demos, tokenizer, refresh.cache_dir, device=device)
    picks = np.linspace(0, len(demo_cache.episodes) - 1, min(refresh.demonstrations, len(demo_cache.episodes)))
    demo_episodes = [demo_cache.episodes[int(i)] for i in picks.round()]
    policy_cache = episodes_token_cache(tokenizer, rollouts, demo_cache.cameras)
    sources = [(policy_cache, policy_cache.episodes), (demo_cache, demo_episodes)]
    figures = refit_done_head(model, sources, refresh.steps)
    save_atomically(model, folder / FINAL)
    summary = RefreshRound(
        round_,
        str(policy_path),
        int(sum(len(e.action) - 1 for e in rollouts)),
        _success(rollouts),
        figures.loss,
        *figures.sources,  # the rollouts', then the demonstrations'
        _success(focus) if focus else None,
    )
    write_text_atomically(folder / "refresh.json", json.dumps(asdict(summary), indent=2))


def _success(episodes: list) -> float:
    return float(np.mean([e.done[-1] > 0.5 for e in episodes]))


@torch.no_grad()
def _simulator_rollouts(sim: RoboscapeManiSkillEnvConfig, episodes: int, policy, io: PolicyIO, seed: int) -> list:
    # with the robot's state, which the world models read beside the frames
    env = RoboscapeManiSkillEnv(replace(sim, include_state=True), num_envs=min(BATCH, episodes))
    try:
        batches = math.ceil(episodes / env.num_envs)
        played = [e for k in range(batches) for e in record_episodes(env, policy, io, seed + k)]
    finally:
        env.close()
    return played[:episodes]
