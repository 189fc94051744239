"""MaskGIT decoding of a trained action world model, measured on rollouts (issue 70): retrieval, action gain and the
arm's measures on saved controllability starts (`wm_levers.py` writes ind.safetensors and ood.safetensors), for
each number of MaskGIT steps and each temperature asked for. Decoding changes no weight, so one model serves every
row; the likelihood's retrieval, which no decoding touches, is read once. Prints a markdown table and writes
OUT/decoding.json.

    python scripts/experiments/wm_decoding.py outputs/screen/levers20/all_seed0/pretrained_model \
        --starts outputs/screen/levers20/ind.safetensors --steps 2 4 8 --temperatures 0 1 \
        --tokenizer outputs/screen/tokenizer/pretrained_model --out docs/results/world_model/levers70
"""

import argparse
import itertools
import json
from pathlib import Path

import torch

from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.world_model.measures.controllability import control_summary, load_control_starts
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel

COLUMNS = ("retrieval_whole_frame", "action_gain_db", "retrieval_state", "tcp_error_share_of_moved", "arm_psnr")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", type=Path, help="an action world model's pretrained_model folder")
    parser.add_argument("--tokenizer", type=Path, required=True)
    parser.add_argument("--starts", type=Path, nargs="+", required=True, help="saved controllability starts")
    parser.add_argument("--steps", type=int, nargs="+", default=[2, 4, 8], help="MaskGIT steps per frame")
    parser.add_argument("--temperatures", type=float, nargs="+", default=[0.0, 1.0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    model = STWorldModel.from_pretrained(args.model).eval()
    tokenizer = VisualTokenizer.from_pretrained(args.tokenizer).eval()
    sets = {path.stem: load_control_starts(path, model.config.frame_skip) for path in args.starts}
    rows = []
    for steps, temperature in itertools.product(args.steps, args.temperatures):
        model.config.maskgit_steps = steps
        for name, starts in sets.items():
            torch.manual_seed(args.seed)  # the same draws for every row at a temperature above 0
            summary = control_summary(model, tokenizer, starts, temperature)
            rows.append({"set": name, "maskgit_steps": steps, "temperature": temperature, **summary})
            values = " | ".join(f"{summary[c]:.3f}" if summary.get(c) is not None else "" for c in COLUMNS)
            print(f"| {name} | {steps} | {temperature:g} | {values} |", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "decoding.json").write_text(json.dumps({"model": str(args.model), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
