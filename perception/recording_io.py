"""On-disk format for recorded strokes: one ``.npz`` file holds one or more strokes.

Layout of a file (NumPy ``.npz``, read with ``allow_pickle=False`` so nothing is unpickled):

- ``index.json``: a uint8 array holding UTF-8 JSON: ``{"format": "robotdemo-strokes", "version": 1,
  "strokes": [{"category", "instance", "combustible", "meta", "streams": {key: {"rate_hz", "t0_s"} | null}}]}``
- ``<i>/<modality>``: float32 (T, C) samples of stroke ``i`` for each present modality (see
  :mod:`perception.streams` for channel layouts). A missing modality has no array and ``null`` in the index.

Files are written atomically (temporary file in the same folder, then ``os.replace``), so a reader never
sees half a file and an interrupted writer leaves what was there before.
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from perception.atomic import atomic_write
from perception.streams import MODALITIES, Stream, StreamError, StrokeRecord

FORMAT_NAME = "robotdemo-strokes"
FORMAT_VERSION = 1


class RecordingFormatError(ValueError):
    """A stroke file is missing, truncated or not in the expected layout."""


def _encode_index(records: Sequence[StrokeRecord]) -> np.ndarray:
    strokes = []
    for rec in records:
        streams = {
            key: (None if rec.streams.get(key) is None else
                  {"rate_hz": float(rec.streams[key].rate_hz), "t0_s": float(rec.streams[key].t0_s)})
            for key in MODALITIES
        }
        strokes.append({"category": rec.category, "instance": rec.instance,
                        "combustible": bool(rec.combustible), "meta": dict(rec.meta), "streams": streams})
    text = json.dumps({"format": FORMAT_NAME, "version": FORMAT_VERSION, "strokes": strokes}, sort_keys=True)
    return np.frombuffer(text.encode("utf-8"), dtype=np.uint8)


def write_strokes(path: str | os.PathLike, records: Iterable[StrokeRecord]) -> Path:
    """Write ``records`` to ``path`` atomically. Returns the path written."""
    path = Path(path)
    records = list(records)
    arrays: dict[str, np.ndarray] = {"index.json": _encode_index(records)}
    for i, rec in enumerate(records):
        for key in MODALITIES:
            stream = rec.streams.get(key)
            if stream is not None:
                arrays[f"{i}/{key}"] = np.ascontiguousarray(stream.data, dtype=np.float32)
    def write(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
            fh.flush()
            os.fsync(fh.fileno())
    atomic_write(path, write)
    return path


def read_strokes(path: str | os.PathLike) -> list[StrokeRecord]:
    """Read every stroke in ``path``.

    Raises:
        RecordingFormatError: the file is missing, truncated, or malformed (the message names the file).
    """
    path = Path(path)
    if not path.is_file():
        raise RecordingFormatError(f"{path}: stroke file not found")
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        raise RecordingFormatError(f"{path}: not a readable stroke file ({exc.__class__.__name__}: {exc})") from None
    if "index.json" not in arrays:
        raise RecordingFormatError(f"{path}: no index.json entry; not a {FORMAT_NAME} file")
    try:
        index = json.loads(arrays["index.json"].tobytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RecordingFormatError(f"{path}: index.json is not valid JSON ({exc})") from None
    if not isinstance(index, dict):
        raise RecordingFormatError(f"{path}: index.json is not a JSON object")
    if index.get("format") != FORMAT_NAME or index.get("version") != FORMAT_VERSION:
        raise RecordingFormatError(
            f"{path}: format {index.get('format')!r} v{index.get('version')!r}, expected {FORMAT_NAME} v{FORMAT_VERSION}")
    records = []
    entries = index.get("strokes", [])
    if not isinstance(entries, list):
        raise RecordingFormatError(f"{path}: index.json 'strokes' is not a list")
    for i, entry in enumerate(entries):
        streams: dict[str, Stream | None] = {}
        try:
            if not isinstance(entry.get("meta", {}), dict):
                raise RecordingFormatError(f"{path}: stroke {i}: 'meta' is not a JSON object")
            for key in MODALITIES:
                info = entry["streams"].get(key)
                if info is None:
                    streams[key] = None
                    continue
                name = f"{i}/{key}"
                if name not in arrays:
                    raise RecordingFormatError(f"{path}: stroke {i} lists {key} but has no array {name!r}")
                streams[key] = Stream(arrays[name], rate_hz=float(info["rate_hz"]), t0_s=float(info["t0_s"]))
            records.append(StrokeRecord(streams=streams, category=entry["category"], instance=entry["instance"],
                                        combustible=bool(entry["combustible"]), meta=entry.get("meta", {})))
        except (KeyError, TypeError, AttributeError) as exc:
            raise RecordingFormatError(f"{path}: stroke {i} index entry is malformed "
                                       f"({exc.__class__.__name__}: {exc})") from None
        except StreamError as exc:
            raise RecordingFormatError(f"{path}: stroke {i}: {exc}") from None
    return records
