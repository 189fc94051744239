"""The ManiSkill task envs behind `roboscape_maniskill`'s parallel episodes (its slots), stepped in this process
(`Slots`) or spread over worker processes (`SlotWorkers`), with one interface.

On a machine without a GPU the simulator renders in software on the CPU, one core per process: a batch of
episodes uses more than one core only when its envs live in more than one process. The workers each hold a
contiguous share of the slots and step them while the others do the same; the policy runs once for the whole
batch in the caller's process. Every reset rebuilds the scene of each slot, so an episode depends only on its
family, scene and seed, never on the worker or the episodes before it: any number of workers gives the same
episodes, bit for bit.
"""

import contextlib
import multiprocessing as mp
import traceback
from dataclasses import dataclass

import numpy as np

from lerobot_roboscape.demos.rollout import observation_images, observation_state
from lerobot_roboscape.robot import STATE_DIM
from lerobot_roboscape.tasks.make import make_task_env


@dataclass(frozen=True)
class SlotSpec:
    """What every slot's env is built with (its family aside).

    Args:
        scene_id: the scene the envs are built in (each reset picks its own).
        image_size: camera image side.
        max_episode_steps: the envs' own time limit; episodes are cut by the caller's horizons, below it.
        light_wrist_camera: render the wrist camera's body with the light mesh (tasks/wrist_camera_mesh.py).
    """

    scene_id: str
    image_size: int
    max_episode_steps: int
    light_wrist_camera: bool = True


class Slots:
    """One ManiSkill env per slot (its task family given by `families`), in this process. After each call, `images`
    ({camera: (k, H, W, 3) uint8}) and `state` ((k, STATE_DIM) float32) hold every slot's latest observation."""

    def __init__(self, families: list[str], spec: SlotSpec):
        self.envs = [
            make_task_env(
                family,
                spec.scene_id,
                image_size=spec.image_size,
                max_episode_steps=spec.max_episode_steps,
                reward_mode="normalized_dense",
                light_wrist_camera=spec.light_wrist_camera,
            )
            for family in families
        ]
        self.images: dict[str, np.ndarray] = {}
        self.state = np.zeros((len(families), STATE_DIM), np.float32)

    def _observe(self, i: int, obs: dict) -> None:
        for camera, image in observation_images(obs).items():
            if camera not in self.images:
                self.images[camera] = np.zeros((len(self.envs), *image.shape), np.uint8)
            self.images[camera][i] = image
        self.state[i] = observation_state(obs)

    def reset(self, seeds: list[int], scene_ids: list[str]) -> tuple[dict, np.ndarray, list[str]]:
        """Reset slot i into scene `scene_ids[i]` with seed `seeds[i]`: (images, state, instructions)."""
        for i, (env, seed, scene_id) in enumerate(zip(self.envs, seeds, scene_ids, strict=True)):
            obs, _ = env.reset(seed=int(seed), options={"scene_id": str(scene_id)})
            self._observe(i, obs)
        return self.images, self.state, [env.unwrapped.instruction for env in self.envs]

    def step(self, actions: np.ndarray, live: np.ndarray) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray]:
        """Step the live slots (the others keep their last observation): (images, state, normalised dense reward,
        success), the last two 0 for slots not stepped."""
        dense = np.zeros(len(self.envs), np.float32)
        success = np.zeros(len(self.envs), bool)
        for i in np.flatnonzero(live):
            obs, reward, _, _, info = self.envs[i].step(actions[i])
            self._observe(i, obs)
            dense[i], success[i] = float(reward[0]), bool(info["success"][0])
        return self.images, self.state, dense, success

    def close(self) -> None:
        for env in self.envs:
            env.close()


def _serve(connection, families: list[str], spec: SlotSpec) -> None:
    """A worker's loop: build its slots, then answer (method, args) calls until "close" or a closed pipe."""
    try:
        slots = Slots(families, spec)
        connection.send(("ok", None))
        while True:
            method, args = connection.recv()
            if method == "close":
                slots.close()
                return
            connection.send(("ok", getattr(slots, method)(*args)))
    except EOFError:
        return
    except Exception:
        connection.send(("error", traceback.format_exc()))


class SlotWorkers:
    """`Slots` spread over `workers` processes in contiguous shares, called with the same methods: each call goes to
    every worker before any answer is read, so the workers step their shares at the same time."""

    def __init__(self, families: list[str], spec: SlotSpec, workers: int):
        context = mp.get_context("spawn")  # SAPIEN's renderer does not survive fork
        self.shares = np.array_split(np.arange(len(families)), min(workers, len(families)))
        self.connections, self.processes = [], []
        for share in self.shares:
            ours, theirs = context.Pipe()
            process = context.Process(target=_serve, args=(theirs, [families[i] for i in share], spec), daemon=True)
            process.start()
            self.connections.append(ours)
            self.processes.append(process)
        self._answers()  # the envs are built

    def _answers(self) -> list:
        answers = []
        for k, connection in enumerate(self.connections):
            try:
                status, value = connection.recv()
            except EOFError:
                self.close()
                raise RuntimeError(f"simulator worker {k} (slots {self.shares[k].tolist()}) died") from None
            if status == "error":
                self.close()
                raise RuntimeError(f"simulator worker {k} (slots {self.shares[k].tolist()}) failed:\n{value}")
            answers.append(value)
        return answers

    def _call(self, method: str, *per_slot) -> list:
        for share, connection in zip(self.shares, self.connections, strict=True):
            connection.send((method, [np.asarray(arg)[share] for arg in per_slot]))
        return self._answers()

    def reset(self, seeds, scene_ids) -> tuple[dict, np.ndarray, list[str]]:
        answers = self._call("reset", seeds, scene_ids)
        return _joined_images(answers), np.concatenate([a[1] for a in answers]), [t for a in answers for t in a[2]]

    def step(self, actions, live) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray]:
        answers = self._call("step", actions, live)
        return _joined_images(answers), *(np.concatenate([a[k] for a in answers]) for k in (1, 2, 3))

    def close(self) -> None:
        for connection in self.connections:
            with contextlib.suppress(BrokenPipeError, OSError):
                connection.send(("close", ()))
        for process in self.processes:
            process.join(timeout=30)
            if process.is_alive():
                process.kill()
        self.connections, self.processes = [], []


def _joined_images(answers: list) -> dict[str, np.ndarray]:
    """The workers' image batches ({camera: (k_w, H, W, 3)}, first in each answer) as one, in slot order."""
    return {cam: np.concatenate([a[0][cam] for a in answers]) for cam in answers[0][0]}


def make_slots(families: list[str], spec: SlotSpec, workers: int) -> Slots | SlotWorkers:
    """The slots in this process (workers <= 1) or spread over `workers` processes."""
    return SlotWorkers(families, spec, workers) if workers > 1 else Slots(families, spec)
