"""`arena learn reach -o DIR`: collect, export, train and evaluate in the physics twin
(specs/learning.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from arena.cli.common import Commands

#: The arms the reach task knows (their twins, their tips).
ROBOT_TYPES = ("so-arm100", "so-101")


def add(commands: Commands) -> None:
    """Declare `learn`."""
    learn = commands.add_parser(
        "learn",
        help="the whole loop in the twin: expert episodes, a LeRobot dataset, a policy trained "
        "on this CPU, its success rate on targets it never saw",
    )
    learn.add_argument("task", choices=["reach"], help="the task (reach: the gripper to a point)")
    learn.add_argument("-o", "--out", required=True, help="the folder for everything it makes")
    learn.add_argument("--episodes", type=int, default=50, help="expert episodes (50)")
    learn.add_argument(
        "--steps",
        type=int,
        help="training steps (3000; with --dagger: 1500, later rounds twice that)",
    )
    learn.add_argument("--targets", type=int, default=20, help="held-out targets (20)")
    learn.add_argument("--seed", type=int, default=0, help="seed of targets and training (0)")
    learn.add_argument(
        "--robot-type",
        choices=list(ROBOT_TYPES),
        default="so-arm100",
        help="the arm in the twin (so-arm100)",
    )
    learn.add_argument(
        "--dagger",
        type=int,
        metavar="ROUNDS",
        help="improve the policy in ROUNDS rounds: deploy it, let the expert correct it "
        "through an intervention where it strays, retrain on the corrections",
    )
    learn.add_argument(
        "--demos", type=int, default=10, help="with --dagger: expert demonstrations (10)"
    )
    learn.add_argument(
        "--rollouts", type=int, default=50, help="with --dagger: corrected episodes a round (50)"
    )
    learn.set_defaults(handler=learn_command)


def learn_command(args: argparse.Namespace) -> int:
    """Run the loop and print the success rates and where the policy is."""
    from arena.extras import require
    from arena.protocol.errors import ArenaError, ErrorCode

    require("gym", "arena learn")
    require("physics", "arena learn")
    require("lerobot", "arena learn")
    from arena.gym.dagger import STEPS
    from arena.gym.learn import LearnSettings, learn_reach

    if args.steps is None:
        args.steps = 3000 if args.dagger is None else STEPS
    if args.episodes < 1 or args.steps < 1 or args.targets < 1:
        raise ArenaError(
            ErrorCode.INVALID_VALUE, "--episodes, --steps and --targets must be 1 or more."
        )
    out = Path(args.out)
    if out.exists() and any(out.iterdir()):
        raise ArenaError(ErrorCode.INVALID_VALUE, f"{out} (-o) exists and is not empty.")
    if args.dagger is not None:
        return _dagger(args, out)
    settings = LearnSettings(
        out, args.episodes, args.steps, args.targets, seed=args.seed, robot_type=args.robot_type
    )
    report = learn_reach(settings, say=lambda line: print(line, flush=True))
    minutes = sum(report.seconds.values()) / 60
    print(
        f"success on {args.targets} held-out targets of the {args.robot_type} "
        "(tip within 2 cm for 0.5 s):"
    )
    print(f"  expert  {report.expert:6.0%}")
    print(f"  random  {report.random:6.0%}")
    print(f"  policy  {report.policy:6.0%}   (ACT, {report.episodes} episodes, {args.steps} steps)")
    times = ", ".join(f"{name} {seconds:.0f} s" for name, seconds in report.seconds.items())
    print(f"took {minutes:.1f} min ({times})")
    print(
        f"policy saved in {report.policy_dir} (copy it into the server's policies/NAME/, "
        'then POST /api/robots/ID/master {"type": "policy", "path": "NAME", '
        '"environment_state": [x, y, z]})'
    )
    return 0


def _dagger(args: argparse.Namespace, out: Path) -> int:
    """`--dagger ROUNDS`: the loop, and the held-out success after each round."""
    from arena.gym.dagger import DaggerSettings, learn_dagger
    from arena.protocol.errors import ArenaError, ErrorCode

    if args.dagger < 1 or args.demos < 1 or args.rollouts < 1:
        raise ArenaError(
            ErrorCode.INVALID_VALUE, "--dagger, --demos and --rollouts must be 1 or more."
        )
    settings = DaggerSettings(
        out,
        rounds=args.dagger,
        demos=args.demos,
        rollouts=args.rollouts,
        steps=args.steps,
        targets=args.targets,
        seed=args.seed,
        robot_type=args.robot_type,
    )
    report = learn_dagger(settings, say=lambda line: print(line, flush=True))
    print(
        f"success on {args.targets} held-out targets of the {args.robot_type} "
        "(tip within 2 cm for 0.5 s), policy alone:"
    )
    for stage in report.rounds:
        print(f"  round {stage.round}  {stage.success:6.0%}   (trained on {stage.frames} frames)")
    load = ", ".join(f"{value:.1f}" for value in report.load_average)
    print(
        f"took {report.seconds / 60:.1f} min ({report.cpu_seconds / 60:.1f} min of CPU; "
        f"load average {load})"
    )
    print(f"policy saved in {report.rounds[-1].policy_dir}")
    return 0
