"""`arena bench workers`: a policy worker's start-up and inference on this CPU, for ACT and
diffusion (LeRobot's default architectures, `arena/bench/act.py`), in Arena's own Python and, with
`ARENA_POLICY_PYTHON` set (`make compat` builds one: `.compat/python`), in that one too.
The diffusion policy denoises in 10 steps (LeRobot's default 100 take most of a minute a chunk
here).

Each worker is started, loads the policy (start-up: from the start of the process to the policy
loaded) and answers the same observation (a 640x480 camera frame scaled to the policy's 240x320,
and a state) `COUNT[kind]` times; the worker's own inference time is taken (decode, preprocess,
inference, postprocess), the pipe not included. One worker at a time, on an otherwise idle
machine for figures worth comparing.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from arena.bench.common import percentile
from arena.policy.process import PolicyProcess, worker_command
from arena.policy.wire import Observe
from arena.sensors.sources import JpegEncoder, pattern_image

#: Inferences measured per worker (diffusion's denoising takes seconds on a CPU).
COUNT = {"act": 20, "diffusion": 5}


def _pythons() -> dict[str, str | None]:
    """The Pythons to run workers in, by the LeRobot each has."""
    found: dict[str, str | None] = {}
    for python in (None, os.environ.get("ARENA_POLICY_PYTHON") or None):
        command = [python or sys.executable, "-c", "import lerobot; print(lerobot.__version__)"]
        version = subprocess.run(command, capture_output=True, text=True, check=True)
        found["lerobot" + version.stdout.strip().replace(".", "")] = python
    return found


async def workers() -> dict[str, float]:
    """Start-up (s) and inference p50/p99 (ms) of each worker and policy."""
    jpeg = JpegEncoder(640, 480, 30).encode_rgb(pattern_image(0, 640, 480))
    observation = Observe(0, (0.0, 10.0, -10.0, 5.0, 0.0, 20.0), {"front": jpeg}, "")
    results: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as folder:
        for kind in COUNT:
            path = Path(folder) / kind
            save = [sys.executable, "-m", "arena.bench.act", str(path), "--type", kind]
            subprocess.run(save, check=True, capture_output=True)
            for label, python in _pythons().items():
                started = time.perf_counter()
                worker = await PolicyProcess.start(worker_command(python))
                try:
                    await worker.load(path)
                    up = time.perf_counter() - started
                    latencies = [
                        (await worker.act(observation)).latency for _ in range(COUNT[kind])
                    ]
                finally:
                    await worker.close()
                key = f"workers_{kind}_{label}"
                results[f"{key}_startup_s"] = up
                results[f"{key}_inference_p50_ms"] = statistics.median(latencies) * 1e3
                results[f"{key}_inference_p99_ms"] = percentile(latencies, 0.99) * 1e3
    return results
