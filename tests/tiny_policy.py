"""Save a tiny LeRobot ACT (or diffusion) policy with random weights, for the policy tests (run
as a script in a process of its own, so that torch never enters the test's process, which hosts
the server):

    python tests/tiny_policy.py DIR [--type act|diffusion] [--camera NAME] [--state N]
        [--action-mean M] [--action-std S] [--chunk N]

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
    parser.add_argument("--type", choices=("act", "diffusion"), default="act")
    args = parser.parse_args()

    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    image = f"observation.images.{args.camera}"
    inputs = {
        "observation.state": PolicyFeature(FeatureType.STATE, (args.state,)),
        image: PolicyFeature(FeatureType.VISUAL, (3, 32, 32)),
    }
    outputs = {"action": PolicyFeature(FeatureType.ACTION, (6,))}
    if args.type == "act":
        from lerobot.policies.act.configuration_act import ACTConfig

        config: object = ACTConfig(
            input_features=inputs,
            output_features=outputs,
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
    else:  # the smallest U-Net LeRobot's diffusion policy takes, few denoising steps
        from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

        config = DiffusionConfig(
            input_features=inputs,
            output_features=outputs,
            n_obs_steps=2,
            horizon=16,
            n_action_steps=args.chunk,
            crop_shape=None,
            pretrained_backbone_weights=None,
            use_group_norm=True,
            down_dims=(32, 64),
            diffusion_step_embed_dim=32,
            spatial_softmax_num_keypoints=8,
            num_inference_steps=4,
            device="cpu",
        )
    torch.manual_seed(0)
    policy = get_policy_class(args.type)(config)
    mean = math.nan if math.isnan(args.action_mean) else args.action_mean
    # Mean and std for ACT, min and max for diffusion (its states and actions are MIN_MAX).
    spread = 3 * args.action_std
    stats = {
        "observation.state": {
            "mean": torch.zeros(args.state),
            "std": torch.full((args.state,), 30.0),
            "min": torch.full((args.state,), -90.0),
            "max": torch.full((args.state,), 90.0),
        },
        image: {"mean": torch.full((3, 1, 1), 0.5), "std": torch.full((3, 1, 1), 0.25)},
        "action": {
            "mean": torch.full((6,), mean),
            "std": torch.full((6,), args.action_std),
            "min": torch.full((6,), mean - spread),
            "max": torch.full((6,), mean + spread),
        },
    }
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    policy.save_pretrained(args.dir)
    pre.save_pretrained(args.dir)
    post.save_pretrained(args.dir)


if __name__ == "__main__":
    main()
