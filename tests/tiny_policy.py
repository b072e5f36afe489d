"""Save a tiny LeRobot ACT policy with random weights, for the policy tests (run as a script in
a process of its own, so that torch never enters the test's process, which hosts the server):

    python tests/tiny_policy.py DIR [--camera NAME] [--state N] [--action-mean M] [--action-std S]

Nothing is downloaded (no pretrained backbone). The action statistics set what the policy
outputs: LeRobot unnormalizes the network's output (about -3..3) as `mean + std * output`, so a
NaN mean makes every action NaN and a std of 1e4 makes jumps far beyond any step limit.
"""

from __future__ import annotations

import argparse
import math


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("dir")
    parser.add_argument("--camera", default="front")
    parser.add_argument("--state", type=int, default=6)
    parser.add_argument("--action-mean", type=float, default=0.0)
    parser.add_argument("--action-std", type=float, default=1.0)
    parser.add_argument("--chunk", type=int, default=10)
    args = parser.parse_args()

    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    image = f"observation.images.{args.camera}"
    config = ACTConfig(
        input_features={
            "observation.state": PolicyFeature(FeatureType.STATE, (args.state,)),
            image: PolicyFeature(FeatureType.VISUAL, (3, 32, 32)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (6,))},
        chunk_size=args.chunk,
        n_action_steps=args.chunk,
        dim_model=16,
        n_heads=2,
        dim_feedforward=32,
        n_encoder_layers=1,
        n_decoder_layers=1,
        n_vae_encoder_layers=1,
        latent_dim=4,
        pretrained_backbone_weights=None,
        device="cpu",
    )
    torch.manual_seed(0)
    policy = ACTPolicy(config)
    mean = math.nan if math.isnan(args.action_mean) else args.action_mean
    stats = {
        "observation.state": {
            "mean": torch.zeros(args.state),
            "std": torch.full((args.state,), 30.0),
        },
        image: {"mean": torch.full((3, 1, 1), 0.5), "std": torch.full((3, 1, 1), 0.25)},
        "action": {"mean": torch.full((6,), mean), "std": torch.full((6,), args.action_std)},
    }
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    policy.save_pretrained(args.dir)
    pre.save_pretrained(args.dir)
    post.save_pretrained(args.dir)


if __name__ == "__main__":
    main()
