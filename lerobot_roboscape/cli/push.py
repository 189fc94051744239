"""`roboscape-push`: a dataset, the world models or a policy to the Hugging Face Hub, with its card.

    roboscape-push --artifact=dataset --repo_id=me/roboscape_demos --dataset_root=outputs/datasets/roboscape
    roboscape-push --artifact=world_models --repo_id=me/roboscape_world_models \\
        --tokenizer=outputs/tokenizer/pretrained_model \\
        --action_world_model=outputs/world_model_action/pretrained_model \\
        --text_world_model=outputs/world_model_text/pretrained_model --fidelity_dir=outputs/fidelity
    roboscape-push --artifact=policy --repo_id=me/roboscape_mlp_ppo_wm \\
        --policy=outputs/ppo/checkpoints/last/pretrained_model --eval_dir=outputs/eval

`--local_dir=DIR` writes the repo's folder under DIR instead of uploading (log in with `hf auth login` to upload).
"""

import logging

import draccus

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.hub.push import PushConfig, push


@one_line_errors("roboscape-push")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    print(f"Pushed to {push(draccus.parse(PushConfig, args=argv))}")


if __name__ == "__main__":
    main()
