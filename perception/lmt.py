"""Converter for the TUM/LMT haptic material database layout the TouchFormer authors trained on.

Input layout (one folder per material instance, one MATLAB file per recording)::

    SRC/C<category>_S<subcategory>_M<material>[anything]/<recording>.mat

Each .mat holds a struct ``finalMaterialRecording`` with 1-D fields ``sound``, ``normalForce``,
``frictionForce`` and ``accelDFT``. The output is a data set folder (:mod:`perception.dataset`): one
:class:`~perception.streams.StrokeRecord` per recording, ``category`` from ``C`` (``"C<n>"`` or a name from
:attr:`LMTConfig.category_names`), ``instance`` = the folder name, ``meta["object_id"]`` = the folder name (an
LMT material is one physical sample).

Assumptions, all in :class:`LMTConfig`:

- Rates: sound 44.1 kHz; normal force, friction force and acceleration 10 kHz (the Texplorer2 rates).
- By default the streams are resampled (``scipy.signal.resample_poly``, anti-aliased) to our sensor's
  nominal rates (:data:`perception.streams.NOMINAL_RATE_HZ`: forces 100 Hz, acceleration 500 Hz), so converted
  strokes look like the fingertip's and share its front end; ``resample=False`` keeps the source rates (the
  front end's windows are in seconds, so both work).
- Forces: LMT measures one normal and one friction force for the whole contact. Our format has 16 taxels.
  The total is spread evenly: each taxel's z channel carries ``normalForce / 16`` (so the taxel sum is the
  measured force), each taxel's x shear carries ``frictionForce / 16`` and y shear 0 (the stroke direction
  is unknown, x is taken as the sliding axis). Real single-channel data thus maps to *uniform* taxels: the
  per-taxel spatial pattern our simulated uSkin provides carries no information in LMT data.
- Acceleration: ``accelDFT`` is the DFT321 signal, one channel that preserves the summed spectral energy of
  the three axes. It goes on the x axis, y and z are 0; our acceleration front end sums power over axes, so
  its features see the same spectrum.
- Units are kept as recorded; ``combustible`` is True for the categories in
  :attr:`LMTConfig.combustible_categories` (LMT has no such label).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Mapping

import numpy as np
import scipy.io
import scipy.signal
from tqdm.auto import tqdm

from perception.dataset import write_dataset
from perception.streams import NOMINAL_RATE_HZ, NUM_CHANNELS, Stream, StrokeRecord

STRUCT_NAME = "finalMaterialRecording"
FIELDS = ("sound", "normalForce", "frictionForce", "accelDFT")
FOLDER_PATTERN = re.compile(r"^C(\d+)_S(\d+)_M(\d+)")


class LMTFormatError(ValueError):
    """The source does not follow the LMT layout; the one-line message is ``"<file>: <problem>"``."""

    def __init__(self, path: Path | str, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = Path(path)
        self.problem = problem


@dataclass(frozen=True)
class LMTConfig:
    """Conversion assumptions.

    Attributes:
        sound_rate_hz: LMT sound rate, Hz.
        force_rate_hz: LMT normal and friction force rate, Hz.
        accel_rate_hz: LMT accelDFT rate, Hz.
        resample: resample forces and acceleration to our nominal rates (sound stays at its rate).
        category_names: category number -> name (default "C<n>").
        combustible_categories: category names labelled combustible.
        shard_size: strokes per shard file.
    """

    sound_rate_hz: float = 44_100.0
    force_rate_hz: float = 10_000.0
    accel_rate_hz: float = 10_000.0
    resample: bool = True
    category_names: Mapping[int, str] = field(default_factory=dict)
    combustible_categories: frozenset[str] = frozenset()
    shard_size: int = 128


@dataclass(frozen=True)
class LMTFolder:
    """One material instance folder: its path, C/S/M numbers and recordings (sorted)."""

    path: Path
    category: int
    subcategory: int
    material: int
    files: tuple[Path, ...]


def scan_lmt(root: str | os.PathLike) -> list[LMTFolder]:
    """Find the ``C*_S*_M*`` folders under ``root`` (sorted by name).

    Raises:
        LMTFormatError: ``root`` missing, no matching folder, or a matching folder without .mat files.
    """
    root = Path(root)
    if not root.is_dir():
        raise LMTFormatError(root, "LMT source folder not found")
    folders = []
    for sub in sorted(p for p in root.iterdir() if p.is_dir()):
        match = FOLDER_PATTERN.match(sub.name)
        if not match:
            continue
        files = tuple(sorted(sub.glob("*.mat")))
        if not files:
            raise LMTFormatError(sub, "material folder holds no .mat recordings")
        c, s, m = (int(g) for g in match.groups())
        folders.append(LMTFolder(path=sub, category=c, subcategory=s, material=m, files=files))
    if not folders:
        raise LMTFormatError(root, "no folders named C<category>_S<subcategory>_M<material> (not an LMT layout)")
    return folders


def _field(path: Path, rec: object, name: str) -> np.ndarray:
    if not hasattr(rec, name):
        raise LMTFormatError(path, f"{STRUCT_NAME} has no field {name!r} (needs {', '.join(FIELDS)})")
    try:
        x = np.asarray(getattr(rec, name), dtype=np.float64).squeeze()
    except (TypeError, ValueError):
        raise LMTFormatError(path, f"field {name!r} is not numeric") from None
    if x.ndim != 1 or x.size < 2:
        raise LMTFormatError(path, f"field {name!r} must be a 1-D signal, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise LMTFormatError(path, f"field {name!r} contains NaN or inf")
    return x


def _resample(x: np.ndarray, src_hz: float, dst_hz: float) -> np.ndarray:
    if src_hz == dst_hz:
        return x
    ratio = Fraction(dst_hz / src_hz).limit_denominator(1000)
    return scipy.signal.resample_poly(x, ratio.numerator, ratio.denominator)


def read_lmt_recording(path: str | os.PathLike, category: str, instance: str, combustible: bool,
                       config: LMTConfig = LMTConfig(), meta: Mapping[str, object] | None = None) -> StrokeRecord:
    """One LMT .mat recording as a :class:`StrokeRecord` (see the module docstring for the mapping).

    Raises:
        LMTFormatError: unreadable file, missing struct or field, malformed signal.
    """
    path = Path(path)
    try:
        mat = scipy.io.loadmat(str(path), squeeze_me=True, struct_as_record=False)
    except (OSError, ValueError, TypeError, NotImplementedError, scipy.io.matlab.MatReadError) as exc:
        raise LMTFormatError(path, f"not a readable MATLAB file ({exc.__class__.__name__}: {exc})") from None
    if STRUCT_NAME not in mat:
        raise LMTFormatError(path, f"no struct {STRUCT_NAME!r}; variables: {sorted(k for k in mat if not k.startswith('__'))}")
    rec = mat[STRUCT_NAME]
    sound, normal, friction, accel = (_field(path, rec, name) for name in FIELDS)
    force_hz = NOMINAL_RATE_HZ["normal"] if config.resample else config.force_rate_hz
    accel_hz = NOMINAL_RATE_HZ["accel"] if config.resample else config.accel_rate_hz
    normal = _resample(normal, config.force_rate_hz, force_hz)
    friction = _resample(friction, config.force_rate_hz, force_hz)
    accel = _resample(accel, config.accel_rate_hz, accel_hz)
    n_taxels = NUM_CHANNELS["normal"]
    normal_taxels = np.repeat(normal[:, None] / n_taxels, n_taxels, axis=1)  # (T, 16) even share of the total
    shear = np.zeros((friction.shape[0], NUM_CHANNELS["friction"]))  # (T, 32) taxel-major [x1, y1, ...]
    shear[:, 0::2] = friction[:, None] / n_taxels  # x: sliding direction; y stays 0
    accel_xyz = np.zeros((accel.shape[0], NUM_CHANNELS["accel"]))  # (T, 3)
    accel_xyz[:, 0] = accel  # DFT321 on x
    streams = {
        "sound": Stream(sound[:, None].astype(np.float32), config.sound_rate_hz),
        "normal": Stream(normal_taxels.astype(np.float32), force_hz),
        "friction": Stream(shear.astype(np.float32), force_hz),
        "accel": Stream(accel_xyz.astype(np.float32), accel_hz),
    }
    return StrokeRecord(streams=streams, category=category, instance=instance, combustible=combustible,
                        meta={"object_id": instance, "source": "lmt", "file": path.name, **dict(meta or {})})


def convert_lmt(src: str | os.PathLike, out_dir: str | os.PathLike, config: LMTConfig = LMTConfig(),
                progress: bool = True) -> Path:
    """Convert an LMT-layout folder into a data set folder (manifest + shards, env "clean").

    Returns:
        The manifest path.

    Raises:
        LMTFormatError: wrong layout or malformed recording (the message names the file).
    """
    folders = scan_lmt(src)
    records = []
    for folder in tqdm(folders, desc="lmt", disable=not progress):
        category = config.category_names.get(folder.category, f"C{folder.category}")
        for path in folder.files:
            records.append(read_lmt_recording(
                path, category, folder.path.name, category in config.combustible_categories, config,
                meta={"subcategory": folder.subcategory, "material": folder.material}))
    settings = {"source": "lmt", "src": str(src), "sound_rate_hz": config.sound_rate_hz,
                "force_rate_hz": config.force_rate_hz, "accel_rate_hz": config.accel_rate_hz,
                "resample": config.resample, "taxel_mapping": "uniform: normal/16 on z, friction/16 on x, y = 0",
                "accel_mapping": "DFT321 on x, y = z = 0"}
    return write_dataset(out_dir, records, env="clean", seed=0, config=settings, shard_size=config.shard_size)
