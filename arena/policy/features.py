"""What a policy asks of a robot, checked against what the robot has, and its observations built
from what Arena measures, in LeRobot's names and units (specs/lerobot.md, the mapping export
uses: `arena.recording.dataset`)."""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence

from arena.policy.wire import Feature, Loaded
from arena.protocol.errors import ArenaError, ErrorCode
from arena.recording.dataset import feature_names, from_dataset, to_dataset
from arena.robot.model import RobotModel
from arena.robot.snapshot import RobotSnapshot

STATE = "observation.state"
ENVIRONMENT = "observation.environment_state"
IMAGE_PREFIX = "observation.images."
ACTION = "action"


def _invalid(message: str) -> ArenaError:
    return ArenaError(ErrorCode.POLICY_INVALID, message)


def check_features(
    loaded: Loaded, model: RobotModel, cameras: Collection[str], environment: int = 0
) -> None:
    """Refuse (POLICY_INVALID, naming the feature) a policy whose inputs the robot cannot supply
    or whose action is not one value per joint. `environment`: the length of the
    `observation.environment_state` its attacher gives (0: none)."""
    joints = len(model.joints)
    names = ", ".join(feature_names(model))
    for feature in loaded.inputs:
        if feature.name == STATE:
            if feature.shape != (joints,):
                raise _invalid(
                    f"Input feature {STATE} has shape {list(feature.shape)}; a "
                    f"{model.robot_type} measures {joints} joints ({names})."
                )
        elif feature.name.startswith(IMAGE_PREFIX):
            _check_image(feature, cameras)
        elif feature.name == ENVIRONMENT:
            if feature.shape != (environment,):
                raise _invalid(
                    f"Input feature {ENVIRONMENT} has shape {list(feature.shape)}; "
                    f"{environment} values were given (`environment_state`: the task's state, "
                    "which Arena does not measure, given when the policy is attached)."
                )
        else:
            raise _invalid(
                f"Input feature {feature.name} ({feature.kind}) is not something Arena measures "
                f"(it gives {STATE}, {IMAGE_PREFIX}<camera> and, given at attach, {ENVIRONMENT})."
            )
    actions = [feature for feature in loaded.outputs if feature.name == ACTION]
    if not actions or actions[0].shape != (joints,):
        shape = list(actions[0].shape) if actions else None
        raise _invalid(
            f"Output feature {ACTION} has shape {shape}; a {model.robot_type} takes {joints} "
            f"joint targets ({names})."
        )


def _check_image(feature: Feature, cameras: Collection[str]) -> None:
    camera = feature.name.removeprefix(IMAGE_PREFIX)
    if camera not in cameras:
        have = ", ".join(sorted(cameras)) or "none"
        raise _invalid(
            f"Input feature {feature.name} needs a camera {camera!r}, which this robot does not "
            f"have (its cameras: {have}). Attach one with POST /api/robots/{{id}}/cameras."
        )
    if len(feature.shape) != 3 or feature.shape[0] != 3 or min(feature.shape) < 1:
        raise _invalid(
            f"Input feature {feature.name} has shape {list(feature.shape)}; "
            "Arena gives colour images, (3, height, width)."
        )


def lerobot_state(model: RobotModel, values: Sequence[float]) -> tuple[float, ...]:
    """`observation.state`: measured values (Arena's units, servo order) in LeRobot's."""
    return tuple(
        to_dataset(joint, value) for joint, value in zip(model.joints, values, strict=True)
    )


def measured(model: RobotModel, snapshot: RobotSnapshot) -> tuple[float, ...]:
    """Each joint's measured value (else its target) in Arena's units, in servo order."""
    values = []
    for joint in model.joints:
        seen = snapshot.joint(joint.name)
        values.append(seen.real_value if seen.real_value is not None else seen.virtual_value)
    return tuple(values)


def action_targets(model: RobotModel, action: Sequence[float]) -> tuple[float, ...]:
    """One action of the policy (LeRobot's units, servo order) in Arena's units (an action of
    the wrong length as it is, for the rules to refuse)."""
    if len(action) != len(model.joints):
        return tuple(action)
    return tuple(
        from_dataset(joint, value) for joint, value in zip(model.joints, action, strict=True)
    )


def camera_images(
    frames: Mapping[str, bytes | None], loaded: Loaded
) -> tuple[dict[str, bytes], list[str]]:
    """The JPEG of each camera the policy takes, and the cameras that have no frame yet."""
    images: dict[str, bytes] = {}
    missing: list[str] = []
    for feature in loaded.inputs:
        if feature.name.startswith(IMAGE_PREFIX):
            camera = feature.name.removeprefix(IMAGE_PREFIX)
            jpeg = frames.get(camera)
            if jpeg is None:
                missing.append(camera)
            else:
                images[camera] = jpeg
    return images, missing
