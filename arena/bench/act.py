"""The ACT of `arena bench policy`, saved by `python -m arena.bench.act DIR` (and the diffusion
policy of `arena bench workers`, `--type diffusion`): LeRobot's default architecture with random
weights and no pretrained backbone (nothing is downloaded). It imports torch, so it runs in a
process of its own, never in the benchmark's or the server's."""

from __future__ import annotations

import argparse
from pathlib import Path

#: The one camera's image as the policy takes it (the worker scales the camera's JPEG).
IMAGE = (3, 240, 320)
#: Actions a chunk (ACT's default).
CHUNK = 100


def save_act(folder: Path, small: bool = False) -> None:
    """Save the benchmark's ACT (random weights) with its processors in `folder` (this
    imports torch: run it in a process of its own, `python -m arena.bench.act DIR`); `small`:
    a few-layer ACT on a 32x32 image (milliseconds an inference: what `arena bench pause`
    measures Arena's own part with)."""
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    image = "observation.images.front"
    size = dict(dim_model=32, n_heads=2, dim_feedforward=64, n_encoder_layers=1) if small else {}
    config = ACTConfig(
        input_features={
            "observation.state": PolicyFeature(FeatureType.STATE, (6,)),
            image: PolicyFeature(FeatureType.VISUAL, (3, 32, 32) if small else IMAGE),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (6,))},
        chunk_size=CHUNK,
        n_action_steps=CHUNK,
        pretrained_backbone_weights=None,
        device="cpu",
        **size,
    )
    torch.manual_seed(0)
    policy = ACTPolicy(config)
    # Actions near the robot's rest pose, a few degrees either way.
    stats = {
        "observation.state": {"mean": torch.zeros(6), "std": torch.full((6,), 30.0)},
        image: {"mean": torch.full((3, 1, 1), 0.5), "std": torch.full((3, 1, 1), 0.25)},
        "action": {"mean": torch.zeros(6), "std": torch.full((6,), 1.0)},
    }
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    policy.save_pretrained(folder)
    pre.save_pretrained(folder)
    post.save_pretrained(folder)


def save_diffusion(folder: Path) -> None:
    """Save a diffusion policy of LeRobot's default architecture (random weights) taking the
    same camera and state, denoising in 10 steps (its default 100 take most of a minute a chunk
    on a small CPU), in `folder` (imports torch)."""
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors

    image = "observation.images.front"
    config = DiffusionConfig(
        input_features={
            "observation.state": PolicyFeature(FeatureType.STATE, (6,)),
            image: PolicyFeature(FeatureType.VISUAL, IMAGE),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (6,))},
        pretrained_backbone_weights=None,  # (LeRobot 0.6's default would download them)
        use_group_norm=True,
        num_inference_steps=10,
        device="cpu",
    )
    torch.manual_seed(0)
    policy = DiffusionPolicy(config)
    bounds = {"min": torch.full((6,), -3.0), "max": torch.full((6,), 3.0)}
    stats = {
        "observation.state": {"min": torch.full((6,), -90.0), "max": torch.full((6,), 90.0)},
        image: {"mean": torch.full((3, 1, 1), 0.5), "std": torch.full((3, 1, 1), 0.25)},
        "action": bounds,
    }
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    policy.save_pretrained(folder)
    pre.save_pretrained(folder)
    post.save_pretrained(folder)


def main() -> None:
    """`python -m arena.bench.act DIR [--type diffusion|small]`: save the benchmark's policy
    in DIR."""
    parser = argparse.ArgumentParser()
    parser.add_argument("dir")
    parser.add_argument("--type", choices=("act", "diffusion", "small"), default="act")
    args = parser.parse_args()
    try:
        import lerobot  # noqa: F401  (a clear line where it is missing, not a traceback)
    except ImportError:
        from arena.extras import install_line

        raise SystemExit(f"Saving a policy needs LeRobot: {install_line('lerobot')}") from None
    if args.type == "diffusion":
        save_diffusion(Path(args.dir))
    else:
        save_act(Path(args.dir), small=args.type == "small")


if __name__ == "__main__":
    main()
