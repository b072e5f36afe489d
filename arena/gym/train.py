"""Train a small LeRobot ACT policy on a state-only dataset, on the CPU, with nothing downloaded
(specs/learning.md says why ACT and why these sizes). torch and LeRobot are imported here only,
inside the functions: `arena learn` pays for them, nothing else does.

The loop is LeRobot's own recipe written small: the dataset with `delta_timestamps` giving each
frame its chunk of actions, LeRobot's preprocessor (normalisation from the dataset's
statistics), `ACTPolicy.forward` for the loss, AdamW. The result is saved as LeRobot saves a
policy (`config.json`, `model.safetensors`, the processors), which a policy master loads.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np


def action_chunks(episodes: Any, size: int) -> tuple[Any, Any]:
    """For each frame, the rows of the `size` actions from it on within its episode (the last
    repeated past the episode's end) and which of them lie past it (LeRobot's
    `action_is_pad`). `episodes`: each row's episode index, episodes in consecutive rows."""
    count = len(episodes)
    rows = np.arange(count)[:, None] + np.arange(size)[None, :]
    last = np.empty(count, dtype=np.int64)
    ends = np.flatnonzero(np.diff(episodes)) + 1  # first row of each next episode
    for begin, end in zip(np.r_[0, ends], np.r_[ends, count], strict=True):
        last[begin:end] = end - 1
    padded = rows > last[:, None]
    return np.minimum(rows, last[:, None]), padded


@dataclass(frozen=True, slots=True)
class TrainSettings:
    """The policy's size and the training's length."""

    steps: int = 3000
    batch_size: int = 64
    learning_rate: float = 1e-3
    chunk_size: int = 10  # actions per inference (at 30 fps, a third of a second)
    dim_model: int = 128
    dim_feedforward: int = 512
    n_encoder_layers: int = 2
    dropout: float = 0.1  # ACT's default; `--dagger` trains without (specs/learning.md)
    seed: int = 0


def train_act(
    dataset: Path,
    repo_id: str,
    out: Path,
    settings: TrainSettings = TrainSettings(),
    say: Callable[[str], None] = print,
) -> float:
    """Train ACT on the dataset at `dataset` and save it in `out`; the last loss."""
    return train_act_on([(dataset, repo_id)], out, settings, say)


#: What relabels a dataset: from its columns (`observation.state`, the environment state,
#: `episode_index`, ..., each a numpy array of rows), the action of each row.
Relabel = Callable[[dict[str, Any]], Any]
#: A dataset to train on: its root and repo id, and optionally what relabels its actions.
Source = tuple[Path, str] | tuple[Path, str, Relabel]


def columns_stats(columns: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Each column's statistics as LeRobot's normalisation reads them (over all rows)."""
    stats = {}
    for name, values in columns.items():
        rows = np.asarray(values, dtype=np.float64).reshape(len(values), -1)
        stats[name] = {
            "mean": rows.mean(axis=0),
            "std": rows.std(axis=0),
            "min": rows.min(axis=0),
            "max": rows.max(axis=0),
            "count": np.array([len(rows)]),
        }
    return stats


def train_act_on(
    datasets: Sequence[Source],
    out: Path,
    settings: TrainSettings = TrainSettings(),
    say: Callable[[str], None] = print,
) -> float:
    """Train ACT on the frames of several datasets (root, repo id) taken as one, and save it
    in `out`; the last loss. The first dataset names the features (the others may have more,
    `intervention` say: unused); normalisation comes from all of them (LeRobot's
    `aggregate_stats`). A dataset given with a `Relabel` is trained on with the actions it
    returns, not the recorded ones (DAgger's labels: what the expert would have done in the
    states the policy reached), and normalisation then comes from the frames as trained on.
    `arena learn reach --dagger` trains on its demonstrations and every round's relabelled
    deployments so."""
    import torch
    from lerobot.configs.types import FeatureType, NormalizationMode
    from lerobot.datasets.compute_stats import aggregate_stats
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata

    try:  # where LeRobot 0.6 keeps it
        from lerobot.utils.feature_utils import dataset_to_policy_features
    except ImportError:  # LeRobot 0.4
        from lerobot.datasets.utils import dataset_to_policy_features
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    torch.manual_seed(settings.seed)
    # One thread: on a small shared machine more threads fight over the cores (two threads
    # made a step of this small model 20 times slower here, not faster).
    torch.set_num_threads(1)
    metas = [LeRobotDatasetMetadata(source[1], root=source[0]) for source in datasets]
    meta = metas[0]
    features = dataset_to_policy_features(meta.features)
    outputs = {k: f for k, f in features.items() if f.type is FeatureType.ACTION}
    inputs = {k: f for k, f in features.items() if k not in outputs}
    config = ACTConfig(
        input_features=inputs,
        output_features=outputs,
        chunk_size=settings.chunk_size,
        n_action_steps=settings.chunk_size,
        dim_model=settings.dim_model,
        dim_feedforward=settings.dim_feedforward,
        n_encoder_layers=settings.n_encoder_layers,
        n_decoder_layers=1,
        dropout=settings.dropout,
        use_vae=False,  # one right answer per state here: no modes for a VAE to model
        pretrained_backbone_weights=None,  # no images, no backbone, nothing downloaded
        normalization_mapping={
            "VISUAL": NormalizationMode.MEAN_STD,
            "STATE": NormalizationMode.MEAN_STD,
            "ENV": NormalizationMode.MEAN_STD,  # the target, in metres: scaled like the rest
            "ACTION": NormalizationMode.MEAN_STD,
        },
        device="cpu",
    )
    policy: Any = ACTPolicy(config)
    policy.train()
    parts: dict[str, list[Any]] = {name: [] for name in (*inputs, "action", "episode_index")}
    episodes = 0
    for root, repo_id, *relabel in datasets:
        table = LeRobotDataset(repo_id, root=root).hf_dataset.with_format("numpy")
        read = {name: np.asarray(table[name]) for name in parts}
        for function in relabel:
            read["action"] = np.asarray(function(read), dtype=np.float32)
        # Episodes of the next dataset numbered after this one's: chunks never cross them.
        read["episode_index"] = read["episode_index"] + episodes
        episodes = int(read["episode_index"].max()) + 1
        for name, values in parts.items():
            values.append(read[name])
    columns = {name: np.concatenate(values) for name, values in parts.items()}
    if any(len(source) > 2 for source in datasets):  # from the labels trained on
        stats = columns_stats({n: v for n, v in columns.items() if n != "episode_index"})
    elif len(metas) == 1:
        stats = meta.stats
    else:
        stats = aggregate_stats([m.stats for m in metas])
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    chunks, padded = action_chunks(columns["episode_index"], settings.chunk_size)
    tensors = {name: torch.as_tensor(columns[name], dtype=torch.float32) for name in inputs}
    actions = torch.as_tensor(columns["action"], dtype=torch.float32)
    chunk_index, pad = torch.as_tensor(chunks), torch.as_tensor(padded)
    optimizer = torch.optim.AdamW(policy.parameters(), lr=settings.learning_rate)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, settings.steps)
    generator = torch.Generator().manual_seed(settings.seed)
    loss_value, started = float("nan"), time.perf_counter()
    for step in range(1, settings.steps + 1):
        # The frames are a few thousand rows: held in memory, a batch is an index away
        # (LeRobot's own loader reads each frame's chunk from the parquet: ~100 times slower).
        rows = torch.randint(len(actions), (settings.batch_size,), generator=generator)
        batch = {name: values[rows] for name, values in tensors.items()}
        batch["action"] = actions[chunk_index[rows]]
        batch["action_is_pad"] = pad[rows]
        loss, _ = policy.forward(pre(batch))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        schedule.step()
        loss_value = float(loss.item())
        if step % max(1, settings.steps // 10) == 0:
            took = time.perf_counter() - started
            say(f"  step {step}/{settings.steps}: loss {loss_value:.4f} ({took:.0f} s)")
    policy.eval()
    out.mkdir(parents=True, exist_ok=True)
    policy.save_pretrained(out)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    return loss_value
