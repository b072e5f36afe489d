"""The policy worker: a process of its own that loads a LeRobot policy and answers observations
with action chunks (`python -m arena.policy.worker`, started by `PolicyProcess`).

torch and LeRobot are imported here and only here, so they never share the interpreter of the
server's control loop. The worker speaks `wire.py` frames on its stdin and stdout; anything
LeRobot or torch print goes to stderr (fd 1 is pointed there before they are imported). It ends
when its stdin closes, so a server that dies leaves no worker behind.

Loading runs nothing the directory names: `config.json` and the processors' JSON are data, the
weights are safetensors, and a processor step that names a class to import (rather than one of
LeRobot's registered steps) is refused.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, BinaryIO

from arena.policy.wire import (
    HEADER,
    Chunk,
    Failed,
    Feature,
    FrameError,
    FromWorker,
    Load,
    Loaded,
    Observe,
    decode_to_worker,
    encode,
    frame_length,
)

#: The processor files LeRobot 0.4 saves beside a policy.
PROCESSOR_FILES = ("policy_preprocessor.json", "policy_postprocessor.json")
STATE = "observation.state"
ENVIRONMENT = "observation.environment_state"
IMAGE_PREFIX = "observation.images."


#: Fields a LeRobot newer than 0.4 added to policies' configs, and the values with which a
#: policy does what an older LeRobot does without the field (ANY: the field never changes what
#: a loaded policy does). Such a field is dropped for an older LeRobot; any other field it does
#: not know is refused by name, never ignored (specs/policy.md).
ANY = object()
LATER_FIELDS: dict[str, object] = {
    "pretrained_revision": ANY,  # the hub revision the weights came from: unused once local
    "gradient_checkpointing": ANY,  # memory in training, not what inference computes
    "use_relative_actions": False,  # actions relative to the state: a change when on
    "relative_exclude_joints": ANY,  # read only with use_relative_actions on
    "action_feature_names": None,
}


class PolicyDirectoryError(Exception):
    """The directory is not a LeRobot policy this worker can load; the message says why."""


def adapt_config(config: dict[str, Any], known: set[str], version: str) -> dict[str, Any]:
    """`config` (a policy's `config.json`) as a LeRobot whose config knows the fields `known`
    reads it: later LeRobots' fields that hold their neutral value dropped (`LATER_FIELDS`);
    `PolicyDirectoryError` naming every other field it does not know."""
    adapted: dict[str, Any] = {}
    refused: list[str] = []
    for name, value in config.items():
        if name == "type" or name in known:
            adapted[name] = value
            continue
        if name not in LATER_FIELDS or LATER_FIELDS[name] not in (ANY, value):
            refused.append(f"{name!r} = {json.dumps(value)}")
    if refused:
        raise PolicyDirectoryError(
            f"config.json has fields LeRobot {version}, which this worker runs, does not know: "
            f"{', '.join(refused)}. A newer LeRobot saved it: run the worker with that LeRobot "
            "(arena serve --policy-python PATH, specs/policy.md)"
        )
    return adapted


def check_steps(path: Path, registered: set[str], version: str) -> None:
    """Refuse processor steps LeRobot `version` (its registry: `registered`) does not have."""
    for name in PROCESSOR_FILES:
        steps = json.loads((path / name).read_text(encoding="utf-8"))["steps"]
        unknown = [str(step["registry_name"]) for step in steps]
        unknown = [step for step in unknown if step not in registered]
        if unknown:
            raise PolicyDirectoryError(
                f"{name} has steps LeRobot {version}, which this worker runs, does not have: "
                f"{', '.join(unknown)}. A newer LeRobot saved it: run the worker with that "
                "LeRobot (arena serve --policy-python PATH, specs/policy.md)"
            )


def checkpoint_of(weights: Path) -> str:
    """The first 12 hex digits of the SHA-256 of `weights` (a policy's `model.safetensors`)."""
    digest = hashlib.sha256()
    with weights.open("rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:12]


def check_directory(path: Path) -> None:
    """Refuse a directory that is not a saved LeRobot 0.4 policy, or whose processors would
    import a class by name; the message names the file and the problem (the server puts the
    directory in front of it)."""
    if not path.is_dir():
        raise PolicyDirectoryError("not a directory")
    for name in ("config.json", "model.safetensors", *PROCESSOR_FILES):
        if not (path / name).is_file():
            raise PolicyDirectoryError(f"no {name} in it (a LeRobot 0.4 policy has one)")
    for name in PROCESSOR_FILES:
        try:
            pipeline = json.loads((path / name).read_text(encoding="utf-8"))
            steps = pipeline["steps"]
        except (ValueError, KeyError, TypeError) as exc:
            raise PolicyDirectoryError(f"{name} is not a LeRobot processor file ({exc})") from None
        for index, step in enumerate(steps):
            if not isinstance(step, dict) or "registry_name" not in step or "class" in step:
                raise PolicyDirectoryError(
                    f"{name}: step {index} is not one of LeRobot's registered steps "
                    "(a step that names a class to import is never loaded)"
                )
            state = step.get("state_file")
            if state is not None and not _file_of_the_folder(state):
                raise PolicyDirectoryError(
                    f"{name}: step {index}'s state_file {state!r} is not a file's name "
                    "(a processor's state is a file of the policy's own folder)"
                )


def _file_of_the_folder(name: object) -> bool:
    """A processor's `state_file` names a file beside it: LeRobot joins it to the folder,
    so a path would read a file anywhere."""
    return (
        isinstance(name, str)
        and bool(name)
        and not name.startswith(".")
        and not any(c in name for c in "/\\\x00")
    )


class LoadedPolicy:
    """A policy with its pre- and post-processors, ready for observations."""

    def __init__(self, path: Path) -> None:
        started = time.perf_counter()
        check_directory(path)
        self.checkpoint = checkpoint_of(path / "model.safetensors")
        import lerobot
        import torch
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors
        from lerobot.processor import ProcessorStepRegistry

        torch.set_num_threads(max(1, (os.cpu_count() or 2) // 2))
        version = self.lerobot = str(lerobot.__version__)
        try:
            saved = json.loads((path / "config.json").read_text(encoding="utf-8"))
            kind = PreTrainedConfig.get_choice_class(saved["type"])
        except Exception as exc:  # not JSON, no type, a type this LeRobot does not have
            raise PolicyDirectoryError(
                f"config.json is not a LeRobot policy config (LeRobot {version}, which this "
                f"worker runs): {type(exc).__name__}: {exc}"
            ) from None
        check_steps(path, set(ProcessorStepRegistry.list()), version)
        known = {field.name for field in dataclasses.fields(kind)}
        with tempfile.TemporaryDirectory() as readable:
            # LeRobot reads a config from a folder: the adapted one goes into a folder of its own
            (Path(readable) / "config.json").write_text(
                json.dumps(adapt_config(saved, known, version)), encoding="utf-8"
            )
            try:
                self.config: Any = PreTrainedConfig.from_pretrained(readable)
            except Exception as exc:  # draccus and LeRobot raise many kinds
                raise PolicyDirectoryError(
                    f"config.json is not a LeRobot policy config: {exc}"
                ) from None
        self.policy: Any = get_policy_class(self.config.type).from_pretrained(
            str(path), config=self.config
        )
        self.policy.eval()
        self.policy.reset()
        self.pre, self.post = make_pre_post_processors(self.config, pretrained_path=str(path))
        self.torch = torch
        self.seconds = time.perf_counter() - started

    def features(self, which: dict[str, Any]) -> tuple[Feature, ...]:
        """`input_features` or `output_features` of the config as wire features."""
        return tuple(
            Feature(name, str(getattr(feature.type, "value", feature.type)), tuple(feature.shape))
            for name, feature in which.items()
        )

    def loaded(self) -> Loaded:
        """What the server is told once the policy is loaded."""
        chunk: Any = getattr(self.config, "chunk_size", None) or getattr(
            self.config, "n_action_steps", 1
        )
        return Loaded(
            policy_type=str(self.config.type),
            checkpoint=self.checkpoint,
            inputs=self.features(self.config.input_features),
            outputs=self.features(self.config.output_features),
            chunk_size=int(chunk),
            seconds=self.seconds,
            lerobot=self.lerobot,
            python=sys.version.split()[0],
        )

    def image(self, jpeg: bytes, shape: tuple[int, ...]) -> Any:
        """A camera's JPEG as the (C, H, W) float tensor in [0, 1] the policy's feature asks."""
        _, height, width = shape
        rgb = decode_jpeg(jpeg, width, height)
        return self.torch.from_numpy(rgb).permute(2, 0, 1).float() / 255.0

    def history(self, batch: dict[str, Any]) -> dict[str, Any]:
        """`batch` as the policy's chunk prediction reads it. A policy that looks at its last
        `n_obs_steps` observations (diffusion, VQ-BeT) keeps them in queues its `select_action`
        fills before predicting; LeRobot's async inference calls `predict_action_chunk`
        directly, so they are filled here the same way (images stacked as LeRobot does)."""
        queues = getattr(self.policy, "_queues", None)
        if queues is None:  # ACT: each chunk from this observation alone
            return batch
        from lerobot.policies.utils import populate_queues
        from lerobot.utils.constants import ACTION, OBS_IMAGES

        batch = {key: value for key, value in batch.items() if key != ACTION}  # (an empty one)
        cameras = list(getattr(self.config, "image_features", None) or ())
        if cameras:
            batch[OBS_IMAGES] = self.torch.stack([batch[name] for name in cameras], dim=-4)
        self.policy._queues = populate_queues(queues, batch)
        return batch

    def act(self, observation: Observe) -> Chunk:
        """The action chunk for one observation, in LeRobot's units."""
        started = time.perf_counter()
        torch = self.torch
        batch: dict[str, Any] = {"task": observation.task}
        for name, feature in self.config.input_features.items():
            if name == STATE:
                batch[name] = torch.tensor(observation.state, dtype=torch.float32)
            elif name == ENVIRONMENT:
                if not observation.environment_state:
                    raise ValueError(f"the observation has no {ENVIRONMENT}")
                batch[name] = torch.tensor(observation.environment_state, dtype=torch.float32)
            elif name.startswith(IMAGE_PREFIX):
                jpeg = observation.images.get(name.removeprefix(IMAGE_PREFIX))
                if jpeg is None:
                    raise ValueError(f"the observation has no image for {name}")
                batch[name] = self.image(jpeg, tuple(feature.shape))
        with torch.inference_mode():
            chunk = self.policy.predict_action_chunk(self.history(self.pre(batch)))
            if chunk.ndim == 2:
                chunk = chunk.unsqueeze(0)
            # LeRobot's postprocessor takes one action (B, D) at a time, as its policy server does.
            steps = [self.post(chunk[:, i, :]) for i in range(chunk.shape[1])]
            actions = torch.stack(steps, dim=1)[0].to("cpu", torch.float64).tolist()
        return Chunk(
            observation.timestep,
            tuple(tuple(row) for row in actions),
            time.perf_counter() - started,
        )


def decode_jpeg(jpeg: bytes, width: int, height: int) -> Any:
    """A JPEG as a (height, width, 3) uint8 RGB array: decoded and scaled by FFmpeg through
    PyAV (Arena's own JPEG codec) where the worker's Python has it, else by Pillow (LeRobot 0.6
    brings Pillow and not PyAV)."""
    try:
        import av
    except ImportError:
        import io

        import numpy as np
        from PIL import Image

        with Image.open(io.BytesIO(jpeg)) as picture:
            if picture.format != "JPEG":
                raise ValueError("a camera frame is not one JPEG image") from None
            scaled = picture.convert("RGB").resize((width, height), Image.Resampling.BILINEAR)
            return np.asarray(scaled)
    codec: Any = av.CodecContext.create("mjpeg", "r")
    frames = codec.decode(av.Packet(jpeg))
    if len(frames) != 1:
        raise ValueError("a camera frame is not one JPEG image")
    return frames[0].reformat(width=width, height=height, format="rgb24").to_ndarray()


def read_frame(stream: BinaryIO) -> bytes | None:
    """One frame's body from `stream`, or None at its end."""
    header = stream.read(HEADER.size)
    if len(header) < HEADER.size:
        return None
    length = frame_length(header)
    body = stream.read(length)
    if len(body) < length:
        return None
    return body


def serve(requests: BinaryIO, answers: BinaryIO) -> None:
    """Answer requests until `requests` ends."""
    policy: LoadedPolicy | None = None
    while True:
        try:
            body = read_frame(requests)
            if body is None:
                return
            request = decode_to_worker(body)
        except FrameError as exc:
            print(f"policy worker: {exc}; stopping", file=sys.stderr)
            return
        answer: FromWorker
        try:
            if isinstance(request, Load):
                policy = LoadedPolicy(Path(request.path))
                answer = policy.loaded()
            elif policy is None:
                answer = Failed("no policy is loaded")
            else:
                answer = policy.act(request)
        except PolicyDirectoryError as exc:
            answer = Failed(str(exc))
        except Exception as exc:  # a policy's own error is the server's to report, not fatal
            answer = Failed(f"{type(exc).__name__}: {exc}")
        answers.write(encode(answer))
        answers.flush()


def main() -> None:
    """Serve on stdin/stdout, with fd 1 pointed at stderr for everything else."""
    answers = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # LeRobot and torch print: keep it off the frames
    sys.stdout = sys.stderr
    serve(sys.stdin.buffer, answers)


if __name__ == "__main__":
    main()
