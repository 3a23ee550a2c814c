"""The outcomes of finished evaluation runs, kept in one JSON Lines file beside the report.

A full evaluation trains some 460 networks: 6-7 hours on two cores, longer than one sitting, and its run folders
(checkpoints, resume state) are too big to keep with the report. What the report needs from a finished run is
small: its training summary (best epoch, accuracy curves) and its predictions on its test strokes. The store
keeps exactly that, one line per run, keyed by the run's identity (:func:`outcome_id`: everything that decides
what the run trains on and how it is tested), so an evaluation resumes from it without the run folders and
trains only what the store lacks. A line is appended as soon as its run is scored, under an exclusive lock, so
two training workers can share the file and a killed evaluation loses at most the runs in flight.
"""

from __future__ import annotations

import base64
import fcntl
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

STORE_VERSION = 1
"""Part of every outcome id: raise it when what an outcome holds, or how a run is scored, changes."""


class RunStoreError(ValueError):
    """A store file that cannot be read (a malformed line other than an unfinished last one)."""


def outcome_id(identity: Mapping[str, Any]) -> str:
    """sha256 of ``identity`` (JSON data) written canonically, with :data:`STORE_VERSION`."""
    text = json.dumps({"store_version": STORE_VERSION, **identity}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def indices_sha256(indices: np.ndarray) -> str:
    """sha256 of an index array (as int64), to name a split in an identity without listing it."""
    return hashlib.sha256(np.ascontiguousarray(indices, dtype=np.int64).tobytes()).hexdigest()


def encode_array(values: np.ndarray) -> dict[str, Any]:
    """A float array as float16 bytes in base64 (an embedding: 378 x 64 values in 48 kB)."""
    values = np.asarray(values, dtype="<f2")
    return {"shape": list(values.shape), "float16_b64": base64.b64encode(values.tobytes()).decode("ascii")}


def decode_array(data: Mapping[str, Any]) -> np.ndarray:
    """The float32 array :func:`encode_array` wrote."""
    raw = np.frombuffer(base64.b64decode(data["float16_b64"]), dtype="<f2")
    return raw.reshape(data["shape"]).astype(np.float32)


@dataclass(frozen=True)
class RunStore:
    """One JSON Lines file of ``{"id", "run", "outcome"}`` records; a later line for an id replaces an earlier one."""

    path: Path

    def load(self) -> dict[str, dict[str, Any]]:
        """id -> outcome of every run in the file (empty when there is no file). An unfinished last line (an
        evaluation killed while writing it) is left out; any other malformed line raises :class:`RunStoreError`
        naming the file and line."""
        if not self.path.is_file():
            return {}
        text = self.path.read_text(encoding="utf-8")
        lines = text.split("\n")
        outcomes: dict[str, dict[str, Any]] = {}
        for number, line in enumerate(lines, start=1):
            if not line.strip():
                continue
            try:
                record = json.loads(line)
                outcomes[str(record["id"])] = dict(record["outcome"])
            except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
                if number == len(lines) and not text.endswith("\n"):
                    continue  # cut off mid-write: that run is scored again
                raise RunStoreError(f"{self.path}: line {number} is not a run outcome ({exc})") from None
        return outcomes

    def append(self, run_id: str, run: str, outcome: Mapping[str, Any]) -> None:
        """Add one outcome (``run``: the run's folder name, for a reader) in one locked write, dropping an
        unfinished last line first."""
        line = json.dumps({"id": run_id, "run": run, "outcome": outcome}, separators=(",", ":")) + "\n"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "a+b") as handle:
            fcntl.flock(handle, fcntl.LOCK_EX)
            try:
                handle.seek(0)
                text = handle.read()
                if text and not text.endswith(b"\n"):
                    tail = text[text.rfind(b"\n") + 1:]
                    if _parses(tail):  # a whole record without its newline (an edit): keep it
                        handle.write(b"\n")
                    else:  # an unfinished line (a killed writer): drop it
                        handle.truncate(len(text) - len(tail))
                handle.write(line.encode("utf-8"))
                handle.flush()
                os.fsync(handle.fileno())
            finally:
                fcntl.flock(handle, fcntl.LOCK_UN)


def _parses(line: bytes) -> bool:
    try:
        record = json.loads(line)
        return isinstance(record, dict) and "id" in record and "outcome" in record
    except (json.JSONDecodeError, UnicodeDecodeError):
        return False
