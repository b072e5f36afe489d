"""The pure parts of running a policy: LeRobot's async-inference queue, the policy rules, the
features a robot can supply, and the worker's pipe (its frames, and what it refuses to load)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import msgspec
import pytest

from arena.policy import process
from arena.policy.actions import ActionQueue, check_step
from arena.policy.features import action_targets, check_features
from arena.policy.wire import (
    HEADER,
    MAX_FRAME,
    Chunk,
    Feature,
    FrameError,
    Load,
    Loaded,
    Observe,
    decode_from_worker,
    decode_to_worker,
    encode,
    frame_length,
)
from arena.policy.worker import PolicyDirectoryError, adapt_config, check_directory, check_steps
from arena.protocol.errors import ArenaError, ErrorCode
from arena.recording.dataset import Span, dataset_name, policies_in
from arena.recording.mcap_file import RecordedMessage
from arena.robot.model import load_robot_model

MODEL = load_robot_model("so-arm100")
JOINTS = [joint.name for joint in MODEL.joints]


def test_the_queue_asks_for_a_chunk_at_the_threshold_and_drops_what_is_past() -> None:
    queue = ActionQueue(actions_per_chunk=4, chunk_size_threshold=0.5)
    assert queue.ready_for_observation() and queue.observation_step == 0
    assert queue.add_chunk(0, [(0.0,), (1.0,), (2.0,), (3.0,)]) == 4
    assert not queue.ready_for_observation()
    assert queue.next_action() == (0, (0.0,))
    assert not queue.ready_for_observation()  # 3 of 4 left
    assert queue.next_action() == (1, (1.0,))
    assert queue.ready_for_observation()  # 2 of 4: at the threshold
    # A chunk for an observation at step 1: its actions for steps 1 (past) and 2, 3 merge.
    assert queue.add_chunk(1, [(10.0,), (20.0,), (30.0,), (40.0,)]) == 3
    assert queue.next_action() == (2, (pytest.approx(0.3 * 2 + 0.7 * 20),))
    assert queue.next_action() == (3, (pytest.approx(0.3 * 3 + 0.7 * 30),))
    assert queue.next_action() == (4, (40.0,))
    assert queue.next_action() is None and queue.latest_action == 4


@pytest.mark.parametrize(
    ("name", "merged"),
    [("weighted_average", 7.0), ("latest_only", 10.0), ("average", 5.0), ("conservative", 3.0)],
)
def test_lerobots_aggregate_functions(name: str, merged: float) -> None:
    queue = ActionQueue(2, aggregate_fn_name=name)
    queue.add_chunk(0, [(0.0,), (0.0,)])
    queue.add_chunk(0, [(10.0,), (10.0,)])
    assert queue.next_action() == (0, (pytest.approx(merged),))


def test_a_new_chunk_replaces_the_queue_and_chunks_are_cut_to_actions_per_chunk() -> None:
    queue = ActionQueue(actions_per_chunk=3)
    queue.add_chunk(0, [(1.0,)] * 10)
    assert len(queue) == 3
    queue.add_chunk(0, [(2.0,)])  # LeRobot keeps only the new chunk's steps
    assert len(queue) == 1


@pytest.mark.parametrize(
    "settings",
    [
        {"actions_per_chunk": 0},
        {"chunk_size_threshold": 1.5},
        {"aggregate_fn_name": "max"},
        {"blend_steps": -1},
    ],
)
def test_queue_settings_out_of_range_are_refused(settings: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        ActionQueue(**{"actions_per_chunk": 2, **settings})  # type: ignore[arg-type]


def test_the_step_limit_clamps_toward_the_action_and_counts() -> None:
    check = check_step(["a", "b", "c"], [15.0, -30.0, 1.0], [0.0, 0.0, 0.0], 10.0)
    assert check.invalid is None
    assert check.targets == {"a": 10.0, "b": -10.0, "c": 1.0}
    assert check.clamped == ("a", "b")
    assert check_step(["a"], [90.0], [0.0], None).targets == {"a": 90.0}


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_an_action_that_is_not_finite_is_refused_whole(bad: float) -> None:
    check = check_step(["a", "b"], [1.0, bad], [0.0, 0.0], 10.0)
    assert check.targets == {} and check.invalid is not None and "b" in check.invalid


def test_an_action_of_the_wrong_length_is_refused() -> None:
    assert check_step(["a", "b"], [1.0], [0.0, 0.0], 10.0).invalid is not None
    assert action_targets(MODEL, [1.0]) == (1.0,)  # left as it is, for the rule to refuse


def test_state_and_actions_in_lerobots_units() -> None:
    jaw = MODEL.joints[-1]
    assert "gripper" in jaw.aliases
    targets = action_targets(MODEL, [5.0, 0, 0, 0, 0, 100.0])
    assert targets[0] == 5.0 and targets[-1] == pytest.approx(jaw.upper)
    assert action_targets(MODEL, [0, 0, 0, 0, 0, 0.0])[-1] == pytest.approx(jaw.lower)


def loaded(*inputs: Feature, action: tuple[int, ...] = (6,)) -> Loaded:
    return Loaded("act", "0" * 12, inputs, (Feature("action", "ACTION", action),), 10, 0.0)


STATE = Feature("observation.state", "STATE", (6,))
FRONT = Feature("observation.images.front", "VISUAL", (3, 96, 128))


def test_features_the_robot_supplies_pass() -> None:
    check_features(loaded(STATE, FRONT), MODEL, ["front", "top"])


@pytest.mark.parametrize(
    ("policy", "cameras", "named"),
    [
        (loaded(STATE, FRONT), ["top"], "observation.images.front"),
        (loaded(Feature("observation.state", "STATE", (7,))), [], "observation.state"),
        (loaded(Feature("observation.environment_state", "ENV", (3,))), [], "environment_state"),
        (loaded(Feature("observation.images.front", "VISUAL", (1, 9, 9))), ["front"], "(3,"),
        (loaded(STATE, action=(7,)), [], "action"),
    ],
)
def test_features_the_robot_cannot_supply_are_refused_by_name(
    policy: Loaded, cameras: list[str], named: str
) -> None:
    with pytest.raises(ArenaError) as refused:
        check_features(policy, MODEL, cameras)
    assert refused.value.code is ErrorCode.POLICY_INVALID and named in refused.value.message


def test_an_environment_state_given_at_attach_feeds_the_policy() -> None:
    target = Feature("observation.environment_state", "ENV", (3,))
    check_features(loaded(STATE, target), MODEL, [], environment=3)
    with pytest.raises(ArenaError) as refused:
        check_features(loaded(STATE, target), MODEL, [], environment=2)
    assert refused.value.code is ErrorCode.POLICY_INVALID
    assert "[3]; 2 values were given" in refused.value.message
    observation = Observe(0, (1.0,), {}, "reach", (0.1, -0.2, 0.3))
    assert decode_to_worker(encode(observation)[HEADER.size :]) == observation


def test_frames_round_trip_and_refuse_anything_else() -> None:
    observation = Observe(3, (1.0, 2.0), {"front": b"\xff\xd8jpeg"}, "wave")
    frame = encode(observation)
    assert frame_length(frame[: HEADER.size]) == len(frame) - HEADER.size
    assert decode_to_worker(frame[HEADER.size :]) == observation
    chunk = Chunk(3, ((1.0, 2.0),), 0.01)
    assert decode_from_worker(encode(chunk)[HEADER.size :]) == chunk
    with pytest.raises(FrameError):
        decode_from_worker(encode(Load("x"))[HEADER.size :])  # a request is no answer
    with pytest.raises(FrameError):
        decode_to_worker(msgspec.msgpack.encode({"type": "pickle", "data": b"cos\nsystem"}))
    with pytest.raises(FrameError):
        frame_length(HEADER.pack(MAX_FRAME + 1))


def write_policy(folder: Path, step: dict[str, object]) -> Path:
    folder.mkdir()
    for name in ("config.json", "model.safetensors"):
        (folder / name).write_text("{}")
    (folder / "policy_preprocessor.json").write_text(json.dumps({"steps": [step]}))
    (folder / "policy_postprocessor.json").write_text(json.dumps({"steps": []}))
    return folder


def test_a_processor_step_that_names_a_class_is_never_loaded(tmp_path: Path) -> None:
    check_directory(write_policy(tmp_path / "ok", {"registry_name": "normalizer_processor"}))
    for index, step in enumerate(
        [{"class": "os.system"}, {"registry_name": "x", "class": "os.system"}, "os.system"]
    ):
        folder = write_policy(tmp_path / f"bad{index}", step)  # type: ignore[arg-type]
        with pytest.raises(PolicyDirectoryError, match="registered steps"):
            check_directory(folder)


async def test_workers_are_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(process, "MAX_WORKERS", 0)
    with pytest.raises(ArenaError) as refused:
        await process.PolicyProcess.start()
    assert refused.value.code is ErrorCode.OVERLOADED and "at most 0" in refused.value.message


def test_a_dataset_of_a_policys_episodes_is_named_as_an_evaluation() -> None:
    def command(at: int, source: str, accepted: bool = True) -> RecordedMessage:
        data = {"source": source, "accepted": accepted}
        return RecordedMessage("/robots/arm/command", "arm", "command", at, data)

    policy = "policy:act:0123456789ab"
    messages = [
        command(5, "policy:act:ffffffffffff"),  # before the episode: not in the dataset
        command(10, "ui"),
        command(20, policy),
        command(30, "policy:act:eeeeeeeeeeee", accepted=False),  # refused: drove nothing
        command(40, "alice"),
    ]
    spans = [Span(0, "wave", 10, 40)]
    assert policies_in(messages, spans) == [policy]
    assert policies_in(messages, [Span(0, "wave", 35, 45)]) == []
    assert dataset_name(None, "arm", [policy]) == "arena/eval_arm"
    assert dataset_name(None, "arm", []) == "arena/arm"
    assert dataset_name("lab/eval_cube", "arm", [policy]) == "lab/eval_cube"
    assert dataset_name("lab/cube", "arm", []) == "lab/cube"
    with pytest.raises(ArenaError) as refused:
        dataset_name("lab/cube", "arm", [policy])
    assert refused.value.code is ErrorCode.INVALID_VALUE
    assert policy in refused.value.message and "lab/eval_cube" not in refused.value.message
    assert ".../eval_cube" in refused.value.message
    with pytest.raises(ArenaError) as refused:
        dataset_name("lab/eval_cube", "arm", [])
    assert "no policy drove" in refused.value.message


def test_a_later_lerobots_config_fields_are_dropped_only_where_they_change_nothing() -> None:
    known = {"type", "chunk_size", "device"}
    saved = {"type": "act", "chunk_size": 10, "pretrained_revision": "main"}
    later = {"gradient_checkpointing": True, "use_relative_actions": False}
    assert adapt_config({**saved, **later}, known, "0.4.4") == {"type": "act", "chunk_size": 10}
    for field, value in [
        ("use_relative_actions", True),
        ("action_feature_names", ["a"]),
        ("never_heard_of", None),
        ("relative_steps", []),
    ]:
        with pytest.raises(PolicyDirectoryError) as refused:
            adapt_config({**saved, field: value}, known, "0.4.4")
        message = str(refused.value)
        assert f"{field!r} = {json.dumps(value)}" in message and "LeRobot 0.4.4" in message


def test_processor_steps_a_worker_s_lerobot_lacks_are_refused_by_name(tmp_path: Path) -> None:
    folder = write_policy(tmp_path / "pi0", {"registry_name": "relative_actions_processor"})
    check_steps(folder, {"normalizer_processor", "relative_actions_processor"}, "0.6.1")
    with pytest.raises(PolicyDirectoryError, match="does not have: relative_actions_processor"):
        check_steps(folder, {"normalizer_processor"}, "0.4.4")


def test_a_policys_own_python_is_for_the_servers_admin_and_must_be_a_program(
    tmp_path: Path,
) -> None:
    import importlib.util
    import sys

    from arena.protocol.rest import PolicyMasterBody
    from arena.server.drivers import make_master

    if importlib.util.find_spec("lerobot") is None:
        pytest.skip("lerobot is not installed")
    model = load_robot_model("so-arm100")
    folder = tmp_path / "act"
    folder.mkdir()
    (folder / "config.json").write_text("{}")  # looked for, not read, before the worker starts

    def made(python: str, anywhere: bool) -> object:
        body = PolicyMasterBody(path="act", python=python)  # a name in the tenant's folder
        return make_master(body, model=model, anywhere=anywhere, policy_dir=tmp_path)

    with pytest.raises(ArenaError) as tenant:
        made(sys.executable, anywhere=False)
    assert tenant.value.code is ErrorCode.FORBIDDEN and '"python"' in tenant.value.message
    with pytest.raises(ArenaError) as not_a_program:
        made(str(tmp_path / "no-python"), anywhere=True)
    assert not_a_program.value.code is ErrorCode.INVALID_VALUE
    assert "no-python" in not_a_program.value.message
    master = made(sys.executable, anywhere=True)
    assert master.settings.python == sys.executable  # type: ignore[attr-defined]


def test_a_new_chunk_is_blended_in_from_the_old_plan_over_blend_steps() -> None:
    # Issue 57: a chunk whose first actions disagree with the one running stepped the arm at
    # the seam. Blended over 3 steps: step k of the new chunk lies k/4 of the way from the old
    # plan (the queue's action for that step, else the last action taken) to the new one.
    queue = ActionQueue(10, aggregate_fn_name="latest_only", blend_steps=3)
    queue.add_chunk(0, [(float(k),) for k in range(4)])  # the old plan: 0, 1, 2, 3
    assert queue.next_action() == (0, (0.0,))
    assert queue.next_action() == (1, (1.0,))
    queue.add_chunk(2, [(40.0,)] * 6)  # disagrees by 38 degrees and more
    blended = [queue.next_action() for _ in range(6)]
    assert blended == [
        (2, (2.0 + 0.25 * 38.0,)),  # from the old plan's 2
        (3, (3.0 + 0.5 * 37.0,)),  # from the old plan's 3
        (4, (1.0 + 0.75 * 39.0,)),  # past the old plan: from the last action taken (step 1)
        (5, (40.0,)),
        (6, (40.0,)),
        (7, (40.0,)),
    ]
    queue.drop()  # a pause: nothing to blend from after it (the arm may have been moved)
    queue.add_chunk(8, [(0.0,)] * 2)
    assert queue.next_action() == (8, (0.0,))


def test_blend_steps_zero_keeps_lerobots_seams() -> None:
    queue = ActionQueue(10, aggregate_fn_name="latest_only")
    queue.add_chunk(0, [(0.0,)] * 3)
    queue.next_action()
    queue.add_chunk(1, [(40.0,)] * 3)
    assert queue.next_action() == (1, (40.0,))
