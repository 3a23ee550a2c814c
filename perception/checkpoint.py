"""Model checkpoints: a folder with ``model.safetensors`` (the state_dict) and ``config.json``.

``config.json`` holds ``{"format": "robotdemo-checkpoint", "version": 1, "model_name", "model_config",
"feature_config", "norm_stats", "class_names", "meta"}``; ``meta`` is free-form (training command, seed, ...).
Nothing is ever unpickled. Every loading problem raises :class:`CheckpointError` whose one-line message
names the file and the problem.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import safetensors.torch
import torch
import torch.nn as nn

from perception.baselines import MODEL_REGISTRY
from perception.atomic import atomic_write
from perception.features import FeatureConfig, NormStats, feature_dims, frame_clock_s
from perception.streams import MODALITIES

FORMAT_NAME = "robotdemo-checkpoint"
FORMAT_VERSION = 1
WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.json"


class CheckpointError(RuntimeError):
    """A checkpoint cannot be loaded; the message is ``"<file>: <problem>"``."""

    def __init__(self, path: Path, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = path
        self.problem = problem


@dataclass(frozen=True)
class Checkpoint:
    """A loaded checkpoint: the model (in eval mode) and everything needed to feed it.

    Attributes:
        model_name: key of :data:`perception.baselines.MODEL_REGISTRY`.
        model_config: the model's config dataclass.
        model: the model with its weights loaded, in eval mode.
        feature_config: front-end settings the model was trained with.
        norm_stats: feature normalisation fitted on the training split.
        class_names: class index -> name.
        meta: free-form training record (command, seed, ...).
        temperature: divides the logits before the softmax when probabilities are wanted
            (:mod:`perception.calibration`, fitted on the validation split; 1.0 when the checkpoint has none).
    """

    model_name: str
    model_config: Any
    model: nn.Module
    feature_config: FeatureConfig
    norm_stats: NormStats
    class_names: tuple[str, ...]
    meta: Mapping[str, Any]
    temperature: float = 1.0


def config_to_dict(config: Any) -> dict[str, Any]:
    """A (nested) config dataclass as plain JSON data."""
    return dataclasses.asdict(config)


def tuplify(value: Any) -> Any:
    """Lists (JSON's) and tuples as tuples, nested ones too; anything else as it is."""
    return tuple(tuplify(v) for v in value) if isinstance(value, (list, tuple)) else value


def config_from_dict(cls: type, data: Mapping[str, Any]) -> Any:
    """Rebuild a (nested) frozen config dataclass from JSON data; lists become tuples. A field missing from
    ``data`` takes its default, or, where the class lists it in a ``SAVED_BEFORE`` class variable, the value
    that configs saved before the field existed had.

    Raises:
        ValueError: missing or unknown fields, or values the dataclass rejects.
    """
    if not isinstance(data, Mapping):
        raise ValueError(f"{cls.__name__} must be a JSON object, got {type(data).__name__}")
    data = {**getattr(cls, "SAVED_BEFORE", {}), **data}
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"{cls.__name__} has no field(s) {unknown}")
    kwargs = {}
    for key, value in data.items():
        hint = hints.get(key)
        if dataclasses.is_dataclass(hint):
            kwargs[key] = config_from_dict(hint, value)
        else:
            kwargs[key] = tuplify(value)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{cls.__name__}: {exc}") from None


def save_checkpoint(directory: str | os.PathLike, model_name: str, model: nn.Module, model_config: Any,
                    feature_config: FeatureConfig, norm_stats: NormStats, class_names: Sequence[str],
                    meta: Mapping[str, Any] | None = None) -> Path:
    """Write ``directory/model.safetensors`` and ``directory/config.json`` (each atomically).

    Args:
        directory: checkpoint folder (created if needed).
        model_name: key of :data:`MODEL_REGISTRY`.
        model: the model; its ``state_dict`` is saved.
        model_config: the config the model was built from.
        feature_config: front-end settings.
        norm_stats: normalisation fitted on the training split.
        class_names: class index -> name.
        meta: JSON-serialisable training record (command line, seed, metrics...).

    Returns:
        The folder written.
    """
    if model_name not in MODEL_REGISTRY:
        raise KeyError(f"unknown model {model_name!r}; known: {sorted(MODEL_REGISTRY)}")
    config_cls, _ = MODEL_REGISTRY[model_name]
    if type(model_config) is not config_cls:
        raise TypeError(f"model {model_name!r} needs a {config_cls.__name__}, got {type(model_config).__name__}")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    record = {
        "format": FORMAT_NAME, "version": FORMAT_VERSION, "model_name": model_name,
        "model_config": config_to_dict(model_config), "feature_config": config_to_dict(feature_config),
        "norm_stats": norm_stats.to_dict(), "class_names": list(class_names), "meta": dict(meta or {}),
    }
    text = json.dumps(record, indent=2, sort_keys=True)
    atomic_write(directory / WEIGHTS_FILE, lambda tmp: safetensors.torch.save_file(state, tmp))
    atomic_write(directory / CONFIG_FILE, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
    return directory


def _read_config(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise CheckpointError(path, "config file not found")
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CheckpointError(path, f"not valid JSON ({exc})") from None
    if not isinstance(record, dict) or record.get("format") != FORMAT_NAME:
        raise CheckpointError(path, f"not a {FORMAT_NAME} config")
    if record.get("version") != FORMAT_VERSION:
        raise CheckpointError(path, f"version {record.get('version')!r}, expected {FORMAT_VERSION}")
    missing = sorted({"model_name", "model_config", "feature_config", "norm_stats", "class_names"} - set(record))
    if missing:
        raise CheckpointError(path, f"missing entries {missing}")
    return record


def _check_state(path: Path, state: Mapping[str, torch.Tensor], expected: Mapping[str, torch.Tensor]) -> None:
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    if missing or unexpected:
        raise CheckpointError(path, f"state_dict keys do not match the config: missing {missing[:5]}"
                                    f"{' ...' if len(missing) > 5 else ''}, unexpected {unexpected[:5]}"
                                    f"{' ...' if len(unexpected) > 5 else ''}")
    for key, tensor in expected.items():
        if tuple(state[key].shape) != tuple(tensor.shape):
            raise CheckpointError(path, f"tensor {key!r} has shape {tuple(state[key].shape)}, "
                                        f"the config builds {tuple(tensor.shape)}")
        if state[key].is_floating_point() and not bool(torch.isfinite(state[key]).all()):
            raise CheckpointError(path, f"tensor {key!r} holds NaN or infinite values")


def load_checkpoint(directory: str | os.PathLike, device: str | torch.device = "cpu") -> Checkpoint:
    """Load a checkpoint written by :func:`save_checkpoint`.

    Args:
        directory: checkpoint folder.
        device: where to put the weights.

    Returns:
        The :class:`Checkpoint`, model in eval mode.

    Raises:
        CheckpointError: missing file, corrupt or truncated weights, invalid or inconsistent config,
            missing/unexpected tensors or wrong shapes.
    """
    directory = Path(directory)
    config_path, weights_path = directory / CONFIG_FILE, directory / WEIGHTS_FILE
    record = _read_config(config_path)
    name = record["model_name"]
    if name not in MODEL_REGISTRY:
        raise CheckpointError(config_path, f"unknown model {name!r}; known: {sorted(MODEL_REGISTRY)}")
    config_cls, model_cls = MODEL_REGISTRY[name]
    try:
        model_config = config_from_dict(config_cls, record["model_config"])
        feature_config = config_from_dict(FeatureConfig, record["feature_config"])
        norm_stats = NormStats.from_dict(record["norm_stats"])
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise CheckpointError(config_path, f"config does not match the code: {exc}") from None
    dims = feature_dims(feature_config)
    if tuple(model_config.in_dims) != tuple(dims[m] for m in MODALITIES):
        raise CheckpointError(config_path, f"model in_dims {tuple(model_config.in_dims)} do not match the "
                                           f"feature config's {tuple(dims[m] for m in MODALITIES)}")
    clock = frame_clock_s(feature_config)
    if getattr(model_config, "time_bias", False) and tuple(model_config.frame_clock_s) != clock:
        raise CheckpointError(config_path, f"model frame_clock_s {tuple(model_config.frame_clock_s)} does not match "
                                           f"the feature config's {clock}")
    for m in MODALITIES:
        if len(norm_stats.mean.get(m, ())) != dims[m] or len(norm_stats.std.get(m, ())) != dims[m]:
            raise CheckpointError(config_path, f"norm_stats for {m} do not have {dims[m]} channels")
        values = norm_stats.mean[m] + norm_stats.std[m]
        if not all(math.isfinite(v) for v in values) or min(norm_stats.std[m], default=1.0) <= 0:
            raise CheckpointError(config_path, f"norm_stats for {m} hold NaN, infinite or non-positive std values")
    class_names = tuple(str(c) for c in record["class_names"])
    if len(class_names) != model_config.n_classes:
        raise CheckpointError(config_path, f"{len(class_names)} class names for n_classes={model_config.n_classes}")

    if not weights_path.is_file():
        raise CheckpointError(weights_path, "weights file not found")
    try:
        state = safetensors.torch.load_file(str(weights_path), device=str(device))
    except Exception as exc:  # safetensors raises its own SafetensorError or OSError on corrupt files
        detail = (str(exc).splitlines() or [""])[0]
        raise CheckpointError(weights_path, f"corrupt or truncated safetensors file "
                                            f"({exc.__class__.__name__}: {detail})") from None
    model = model_cls(model_config)
    _check_state(weights_path, state, model.state_dict())
    model.load_state_dict(state, strict=True)
    model.to(device).eval()
    temperature = record.get("temperature", 1.0)
    if not (isinstance(temperature, (int, float)) and math.isfinite(temperature) and temperature > 0):
        raise CheckpointError(config_path, f"temperature must be a positive number, got {temperature!r}")
    return Checkpoint(model_name=name, model_config=model_config, model=model, feature_config=feature_config,
                      norm_stats=norm_stats, class_names=class_names, meta=record.get("meta", {}),
                      temperature=float(temperature))


def set_temperature(directory: str | os.PathLike, temperature: float) -> None:
    """Store a fitted temperature in ``directory/config.json`` (atomically; the weights are untouched)."""
    if not (math.isfinite(temperature) and temperature > 0):
        raise ValueError(f"temperature must be a positive number, got {temperature}")
    path = Path(directory) / CONFIG_FILE
    record = _read_config(path)
    record["temperature"] = float(temperature)
    text = json.dumps(record, indent=2, sort_keys=True)
    atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
