"""Does an ensemble of cheap members (the model's top drawn afresh and retrained alone) part where the data did not
reach, as whole models trained apart do? On a synthetic token world (world_model/synthetic.py, "motion": only the
action moves the square), measured where PPO in the world model would take a policy off the data.

One action model is trained; beside it two ensembles of two more members each:
- cheap: the model with its last block and heads drawn afresh from seeds 1, 2 and trained alone for a quarter of its
  steps (`roboscape-train-wm --init_from --retrain_blocks=1`, the ensemble lever's default);
- whole: models trained from seeds 1, 2 as the first, for as many steps.
Each ensemble's disagreement (envs/ensemble.py: mutual information per token, in nats, on each next frame before it
is generated, the episode read teacher-forced from the real frames) is read on episodes
- in the data: new episodes drawn as the training ones;
- with actions off the data: the same starts, the translation 3x larger than any training action (the world moves
  the square one cell either way; the models never saw such an action);
- on frames off the data: backgrounds of tokens no training frame had.

    python scripts/experiments/ensemble_members.py --out docs/results/world_model/ensemble_members
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from lerobot_roboscape.envs.ensemble import Ensemble
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from lerobot_roboscape.world_model.rollout import Rollout
from lerobot_roboscape.world_model.synthetic import ACTION_DIM, SyntheticWorld, train_on_world, world_model

WINDOW = 4
CONDITIONS = ("in the data", "actions off the data", "frames off the data")


def build(world: SyntheticWorld, seed: int) -> STWorldModel:
    return world_model(world, WINDOW, seed, d_model=64, n_head=2)


def cheap_member(model: STWorldModel, world: SyntheticWorld, seed: int, steps: int) -> tuple[STWorldModel, dict]:
    """`model` with its last block and heads drawn afresh from `seed` and trained alone (as train_wm.start_from)."""
    member = build(world, 0)
    member.load_state_dict(model.state_dict())
    torch.manual_seed(seed)
    member.redraw_top(1)
    return member, trained(member, world, seed, steps)


def whole_member(world: SyntheticWorld, seed: int, steps: int) -> tuple[STWorldModel, dict]:
    member = build(world, seed)
    return member, trained(member, world, seed, steps)


def trained(member: STWorldModel, world: SyntheticWorld, seed: int, steps: int) -> dict:
    tic = time.perf_counter()
    curve = train_on_world(member, world, steps, seed=seed)
    return {"steps": steps, "seconds": time.perf_counter() - tic, "retrieval": curve[-1]["retrieval"]}


def episodes(world: SyntheticWorld, condition: str, n: int, steps: int, seed: int) -> tuple[np.ndarray, ...]:
    """Tokens (n, steps + 1, S), actions (n, steps, 7) and states (n, steps + 1, 2) of episodes under `condition`."""
    rng = np.random.default_rng(seed)
    background, position = world.random_starts(rng, n, steps)
    if condition == "frames off the data":  # tokens between the training backgrounds' and the square's
        background = rng.integers(world.background_tokens, world.square_token, background.shape)
    actions = world.random_controls(rng, n, steps)
    if condition == "actions off the data":
        actions[..., :2] *= 3.0
    played = world.episodes(rng, n, steps, controls=actions, starts=(background, position))
    return played["tokens"], actions, played["states"]


@torch.no_grad()
def disagreement(
    model: STWorldModel, members: list[STWorldModel], tokens: np.ndarray, actions: np.ndarray, states: np.ndarray
) -> float:
    """Mean over episodes and frames of the ensemble's disagreement on each next frame, the frames read as they were."""
    tokens_t, actions_t, states_t = torch.from_numpy(tokens).long(), torch.from_numpy(actions), torch.from_numpy(states)
    B, A = len(tokens), ACTION_DIM
    ensemble = Ensemble(members)
    ensemble.start(tokens_t[:, :1], states_t[:, :1])
    own = Rollout.start(model, tokens_t[:, :1], model.episode_control(torch.zeros(B, 0, A)), states=states_t[:, :1])
    values = []
    for t in range(actions.shape[1]):
        chunk = actions_t[:, t : t + 1, None]  # (B, 1, k=1, A)
        values.append(ensemble.disagreement(own, chunk))
        own.observe(tokens_t[:, t + 1 : t + 2], model.encode_control(chunk), states_t[:, t + 1])
        ensemble.observe(tokens_t[:, t + 1], chunk, states_t[:, t + 1])
    return float(torch.stack(values).mean())


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--steps", type=int, default=100_000, help="training steps of the model, at most")
    parser.add_argument(
        "--minutes",
        type=float,
        default=5.0,
        help="the model's training clock; whole members train for the steps it made, cheap ones for a quarter of them",
    )
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--horizon", type=int, default=8, help="frames read per episode")
    args = parser.parse_args()
    torch.set_num_threads(2)
    world = SyntheticWorld(kind="motion", grid=8, vocab_size=16, background_tokens=4)
    model = build(world, 0)
    tic = time.perf_counter()
    curve = train_on_world(model, world, args.steps, seed=0, minutes=args.minutes)
    steps = curve[-1]["step"]
    runs = {"model": {"steps": steps, "seconds": time.perf_counter() - tic, "retrieval": curve[-1]["retrieval"]}}
    ensembles = {"cheap": [], "whole": []}
    for seed in (1, 2):
        member, runs[f"cheap {seed}"] = cheap_member(model, world, seed, steps // 4)
        ensembles["cheap"].append(member.eval())
        member, runs[f"whole {seed}"] = whole_member(world, seed, steps)
        ensembles["whole"].append(member.eval())
    model.eval()
    table = {
        name: {
            condition: disagreement(model, members, *episodes(world, condition, args.episodes, args.horizon, 99))
            for condition in CONDITIONS
        }
        for name, members in ensembles.items()
    }
    results = {"runs": runs, "disagreement": table, "minutes": args.minutes, "episodes": args.episodes}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    print(render(results, args.out))


def render(results: dict, out: Path) -> str:
    """report.md from results.json: the table, what it measured and how to regenerate it."""
    runs, table = results["runs"], results["disagreement"]
    lines = [
        "# Cheap ensemble members against whole models, on a synthetic world",
        "",
        f"The action model trained for {results['minutes']:g} minutes ({runs['model']['steps']} steps; retrieval "
        f"{runs['model']['retrieval']:.2f} among 4 action sequences, chance 0.25) on the motion world. Each ensemble "
        "is the model and two members; its disagreement is the mutual information per token on each next frame, in "
        f"nats, over {results['episodes']} episodes of 8 frames read teacher-forced (x: against in the data). Steps "
        "and seconds are each member's training on 2 CPU cores, nothing else running.",
        "",
        "| ensemble | steps per member | seconds per member | members' retrieval | "
        + " | ".join(f"disagreement, {c}" for c in CONDITIONS)
        + " |",
        "|---|---:|---:|---:|" + "---:|" * len(CONDITIONS),
    ]
    for name, row in table.items():
        members = [runs[f"{name} {seed}"] for seed in (1, 2)]
        cells = [f"{row[c]:.4f} ({row[c] / row[CONDITIONS[0]]:.1f}x)" for c in CONDITIONS]
        lines.append(
            f"| {name} | {members[0]['steps']} | {np.mean([m['seconds'] for m in members]):.0f} | "
            + ", ".join(f"{m['retrieval']:.2f}" for m in members)
            + " | "
            + " | ".join(cells)
            + " |"
        )
    lines += ["", f"`python scripts/experiments/ensemble_members.py --out {out} --minutes {results['minutes']:g}`"]
    text = "\n".join(lines) + "\n"
    (out / "report.md").write_text(text)
    return text


if __name__ == "__main__":
    main()
