"""The policy after PPO in the world model, rolled out there and its actions replayed open loop in the simulator
from the same scene and initial state: what each world said of the same actions (the claim's replay step)."""

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from lerobot_roboscape.demos.rollout import EpisodeJob, replay_actions, worker_env
from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.experiments import world_model_runs
from lerobot_roboscape.io.atomic import write_text_atomically
from lerobot_roboscape.io.records import from_record
from lerobot_roboscape.pipeline import resume
from lerobot_roboscape.pipeline.config import PipelineConfig
from lerobot_roboscape.rl.ppo_state import trained_world_model
from lerobot_roboscape.robot import CONTROL_FREQ
from lerobot_roboscape.training.records import write_video

REPLAY_JSON, REPLAY_PNG = "replay.json", "replay.png"
REPLAY_STRIPS = 4  # replays drawn in replay.png


@dataclass(frozen=True)
class Replay:
    """One start: the return and success the world model gave the policy's rollout, whether its actions replayed
    in the simulator succeeded, and the side-by-side video (under the replay's folder)."""

    episode_index: int
    family: str
    scene: str
    world_model_return: float
    world_model_success: bool
    simulator_success: bool
    video: str

    @classmethod
    def from_json(cls, data: "dict | Replay") -> "Replay":
        return data if isinstance(data, Replay) else from_record(cls, data)


def agreed(replays: list[Replay]) -> int:
    """The replayed rollouts whose outcome the world model and the simulator agree on."""
    return sum(r.world_model_success == r.simulator_success for r in replays)


def replay_in_simulator(
    p: PipelineConfig,
    folder: Path,
    env_cfg: RoboscapeWorldModelEnvConfig | None,
    checkpoint: Path,
    rollouts_file: Path | None = None,
    *,
    episodes: int,
    per_outcome: int,
) -> list[Replay]:
    """The policy after PPO in the world model, rolled out in `roboscape_wm` (with the action model its checkpoint
    last trained in) from `episodes` starts (spread over the starts, so over families and scenes), or its rollouts
    made where the world models are (`rollouts_file`); of them, up to `per_outcome` the world model called
    successes and as many it called failures have their actions replayed open loop in the simulator from the same
    scene and initial state (the share of its successes the simulator confirms needs successes to replay, and the
    world model calls few).
    Writes side-by-side videos (world model | its goal | simulator) and returns, per replay, what each world said:
    the world model's return and success, the simulator's success. Written into `folder`."""
    if rollouts_file is None:
        if trained := trained_world_model(checkpoint):  # the done refresh's run ends in a refitted model
            env_cfg = dataclasses.replace(env_cfg, action_world_model=trained)
        settings = {"env": env_cfg, "checkpoint": str(checkpoint), "episodes": episodes}
    else:
        settings = {
            "rollouts": str(rollouts_file),
            "bytes": rollouts_file.stat().st_size,
            "checkpoint": str(checkpoint),
        }
    settings["per_outcome"] = per_outcome

    def replay():
        if rollouts_file is None:
            rollouts = world_model_runs.roll_out(env_cfg, checkpoint, episodes, p.device)
        else:
            rollouts = world_model_runs.load_rollouts(rollouts_file)
        _replay(folder, rollouts, picked(rollouts.success, per_outcome), p.data.image_size)

    resume.run_once(folder, settings, p.fresh, replay)
    return [Replay.from_json(row) for row in json.loads((folder / REPLAY_JSON).read_text())]


def picked(success: np.ndarray, per_outcome: int) -> list[int]:
    """The rollouts to replay: up to `per_outcome` of those the world model called successes, then as many of
    those it called failures, each spread over the rollouts (so over families and scenes)."""
    chosen = []
    for called in (True, False):
        group = np.flatnonzero(success == called)
        spread = np.linspace(0, len(group) - 1, min(per_outcome, len(group))).round().astype(int)
        chosen += group[spread].tolist()
    return chosen


def _replay(folder: Path, rollouts: world_model_runs.Rollouts, chosen: list[int], image_size: int) -> None:
    """Replays the chosen rollouts; the picture's strips are the first chosen, so successes when there are any."""
    folder.mkdir(parents=True)
    rows, strips = [], []
    for i in chosen:
        start = rollouts.starts[i]
        family, scene, seed = start.task_family, start.scene, start.seed
        job = EpisodeJob(family, scene, seed, "optimal", image_size)
        replayed = replay_actions(worker_env(job), job, rollouts.actions[:, i], {})
        simulator = np.concatenate([replayed.images[camera] for camera in rollouts.cameras], axis=1)  # (T, 2H, W, 3)
        clip = [np.concatenate([rollouts.frames[t, i], simulator[t]], axis=1) for t in range(len(simulator))]
        wm_success, sim_success = bool(rollouts.success[i]), bool(replayed.success.any())
        outcome = f"wm-{'success' if wm_success else 'failure'}_sim-{'success' if sim_success else 'failure'}"
        row = Replay(
            start.episode_index,
            family,
            scene,
            round(float(rollouts.returns[i]), 3),
            wm_success,
            sim_success,
            f"{i:02d}_{family}_{outcome}.mp4",
        )
        write_video(folder / row.video, clip, CONTROL_FREQ)
        rows.append(row)
        strips.append(_strip(clip))
    iio.imwrite(folder / REPLAY_PNG, np.concatenate(strips[:REPLAY_STRIPS], axis=0))
    write_text_atomically(folder / REPLAY_JSON, json.dumps([dataclasses.asdict(row) for row in rows], indent=2))


def _strip(clip: list[np.ndarray], columns: int = 5) -> np.ndarray:
    """`columns` frames of a clip, evenly spaced, side by side."""
    picks = np.linspace(0, len(clip) - 1, columns).round().astype(int)
    return np.concatenate([clip[t] for t in picks], axis=1)
