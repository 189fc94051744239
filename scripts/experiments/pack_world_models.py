"""What a lent GPU machine needs to train the world models, from a run's folder, in one folder that travels.

From `roboscape-demo`'s output_dir (the bench scale: its datasets, tokenizer and token caches), writes to --out:
- demos.xz, explore.xz: the token caches of the demonstrations and of the exploratory episodes, with their datasets'
  action statistics (tokenizer/token_cache.py: export_token_cache), built here first if the run has not yet;
- ind.safetensors.xz, ood.safetensors.xz: the controllability sets of the training scenes (new initial states) and
  of the held-out scenes, read for the world model's frame skip and horizon (world_model/measures/controllability.py:
  save_control_starts), their real frames included, so that retrieval is measured there as here;
- tokenizer/: the tokenizer (the controllability sets' frames are decoded from the rollouts' codes with it);
- sizes.json: the bytes of each, and the seconds the packing took.

    python scripts/experiments/pack_world_models.py --run outputs/bench --out .gpu/data
"""

import argparse
import json
import lzma
import shutil
import time
from pathlib import Path

from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.dataset.reader import open_dataset
from lerobot_roboscape.pipeline.layout import (
    CONTROL_DIR,
    CONTROL_IND_DIR,
    DEMOS_DIR,
    DEMOS_REPO_ID,
    EXPLORE_DIR,
    EXPLORE_REPO_ID,
    TOKEN_CACHE_DIR,
    TOKENIZER_DIR,
)
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.tokenizer.token_cache import export_token_cache
from lerobot_roboscape.training.checkpoints import FINAL
from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig
from lerobot_roboscape.world_model.measures.controllability import read_control_set, save_control_starts, spread
from lerobot_roboscape.world_model.train import prepare_token_cache


def xz(path: Path) -> Path:
    """`path` compressed beside itself (path.xz); the original removed."""
    target = path.with_name(path.name + ".xz")
    with open(path, "rb") as src, lzma.open(target, "wb", preset=6) as dst:
        shutil.copyfileobj(src, dst)
    path.unlink()
    return target


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="a roboscape-demo output_dir")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--preset", default="gpu", help="the world-model preset whose frame skip the sets are read for")
    parser.add_argument("--horizon", type=int, default=16, help="control steps of the controllability rollouts")
    parser.add_argument("--ind-starts", type=int, default=32, help="IND starts kept, spread over the scenes")
    parser.add_argument("--ood-starts", type=int, default=32, help="OOD starts kept, spread over the scenes")
    args = parser.parse_args()
    began = time.time()
    run, out = args.run.resolve(), args.out
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    tokenizer_dir = run / TOKENIZER_DIR / FINAL
    if not tokenizer_dir.is_dir():
        raise SystemExit(f"{tokenizer_dir} does not exist: run roboscape-demo --scale=bench on {run} first")
    shutil.copytree(tokenizer_dir, out / "tokenizer")
    sizes = {}
    caches = (("demos", DEMOS_REPO_ID, DEMOS_DIR), ("explore", EXPLORE_REPO_ID, EXPLORE_DIR))
    for name, repo_id, folder in caches:
        cache, stats = prepare_token_cache(
            DatasetConfig(repo_id=repo_id, root=str(run / folder)), str(tokenizer_dir), run / TOKEN_CACHE_DIR
        )
        sizes[f"{name}.xz"] = export_token_cache(cache, out / f"{name}.xz", stats)
        sizes[f"{name} raw tokens"] = int(cache.tokens.nbytes)
        packed = sizes[f"{name}.xz"] / 2**20
        print(f"{name}: {len(cache.episodes)} episodes, {len(cache.tokens)} frames -> {packed:.1f} MiB")
    frame_skip = WorldModelConfig.get_choice_class(args.preset)().frame_skip
    tokenizer = VisualTokenizer.from_pretrained(tokenizer_dir).eval()
    for name, folder, keep in (("ind", CONTROL_IND_DIR, args.ind_starts), ("ood", CONTROL_DIR, args.ood_starts)):
        dataset = open_dataset(f"local/{Path(folder).name}", run / folder)
        starts = read_control_set(dataset, tokenizer, frame_skip, args.horizon, "cpu")
        picked = spread(starts, keep)
        save_control_starts(picked, out / f"{name}.safetensors", frame_skip)
        path = xz(out / f"{name}.safetensors")
        sizes[path.name] = path.stat().st_size
        packed = sizes[path.name] / 2**20
        print(f"{name} controllability set: {len(picked)} of {len(starts)} starts -> {packed:.1f} MiB")
    sizes["tokenizer"] = sum(p.stat().st_size for p in (out / "tokenizer").rglob("*") if p.is_file())
    total = sum(v for k, v in sizes.items() if "raw" not in k)
    summary = {"bytes": sizes, "total_bytes": total, "seconds": round(time.time() - began, 1)}
    (out / "sizes.json").write_text(json.dumps(summary, indent=2))
    print(f"packed {total / 2**20:.1f} MiB into {out} in {summary['seconds']:.0f} s")


if __name__ == "__main__":
    main()
