"""Converter for the TUM/LMT haptic material database layout the TouchFormer authors trained on.

Input layout (one folder per material instance, one MATLAB file per recording), either of::

    SRC/C<category>_S<subcategory>_M<material>[anything]/<recording>.mat
    SRC/C<category>/S<subcategory>/M<material>/<recording>.mat     (nested, as some copies of the database are)

at any depth under ``SRC``; a ``.mat`` (any case) elsewhere is skipped and counted (:class:`LMTScan`).

Each .mat holds a struct ``finalMaterialRecording`` with 1-D fields ``sound``, ``normalForce``,
``frictionForce`` and ``accelDFT``. The output is a data set folder (:mod:`perception.dataset`): one
:class:`~perception.streams.StrokeRecord` per recording, ``category`` from ``C`` (``"C<n>"`` or a name from
:attr:`LMTConfig.category_names`), ``instance`` = the folder name, ``meta["object_id"]`` = the folder name (an
LMT material is one physical sample).

Assumptions, all in :class:`LMTConfig`:

- Rates: sound 44.1 kHz; normal force, friction force and acceleration 10 kHz (the Texplorer2 rates). These
  are assumptions: some public loaders of the database read the forces and the acceleration at 3 kHz. A
  recording whose streams, at the configured rates, last more than 10 % apart (``max_duration_mismatch``) is
  refused with the durations in the message, so a wrong rate does not pass silently (``robotdemo convert-lmt
  --force-rate-hz ...``).
- A missing or empty field is an absent stream (``None``), as the format allows; a malformed one (NaN, not
  1-D, complex) is an error naming the file, or with ``skip_bad`` the file is skipped and counted.
- By default the streams are resampled (``scipy.signal.resample_poly``, anti-aliased, the ends padded by
  extrapolating the signal rather than with zeros) to our sensor's
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

import math
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
NESTED_PATTERNS = (re.compile(r"^C(\d+)$"), re.compile(r"^S(\d+)$"), re.compile(r"^M(\d+)$"))


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
        skip_bad: skip (and count) a recording that cannot be read or is malformed, instead of stopping.
        max_duration_mismatch: largest relative difference between the streams' durations at the configured
            rates (a guard against a wrong rate; raise it for recordings whose streams do differ in length).
    """

    sound_rate_hz: float = 44_100.0
    force_rate_hz: float = 10_000.0
    accel_rate_hz: float = 10_000.0
    resample: bool = True
    category_names: Mapping[int, str] = field(default_factory=dict)
    combustible_categories: frozenset[str] = frozenset()
    shard_size: int = 128
    skip_bad: bool = False
    max_duration_mismatch: float = 0.10

    def __post_init__(self) -> None:
        for name in ("sound_rate_hz", "force_rate_hz", "accel_rate_hz"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"LMTConfig: {name} must be a positive number of Hz, got {value!r}")
        if not self.max_duration_mismatch >= 0:
            raise ValueError(f"LMTConfig: max_duration_mismatch must be >= 0, got {self.max_duration_mismatch!r}")


@dataclass(frozen=True)
class LMTFolder:
    """One material instance folder: its path, C/S/M numbers and recordings (sorted)."""

    path: Path
    category: int
    subcategory: int
    material: int
    files: tuple[Path, ...]


@dataclass(frozen=True)
class LMTScan:
    """What :func:`scan_lmt` found: the material folders and the .mat files outside any of them."""

    folders: tuple[LMTFolder, ...]
    skipped: tuple[Path, ...]


def _material_of(folder: Path, root: Path) -> tuple[int, int, int] | None:
    """(C, S, M) of a folder named ``C<c>_S<s>_M<m>...`` or of the last of nested ``C<c>/S<s>/M<m>``."""
    match = FOLDER_PATTERN.match(folder.name)
    if match:
        return tuple(int(g) for g in match.groups())  # type: ignore[return-value]
    parts = folder.relative_to(root).parts
    if len(parts) >= 3:
        matches = [p.match(name) for p, name in zip(NESTED_PATTERNS, parts[-3:])]
        if all(matches):
            return tuple(int(m.group(1)) for m in matches)  # type: ignore[return-value, union-attr]
    return None


def scan_lmt(root: str | os.PathLike) -> LMTScan:
    """Find the material folders (``C*_S*_M*`` or nested ``C*/S*/M*``, at any depth) under ``root`` and their
    .mat recordings (any case of the extension), sorted by path.

    Raises:
        LMTFormatError: ``root`` missing or no .mat file in a material folder.
    """
    root = Path(root)
    if not root.is_dir():
        raise LMTFormatError(root, "LMT source folder not found")
    by_folder: dict[Path, list[Path]] = {}
    skipped = []
    for path in sorted(p for p in root.rglob("*") if p.is_file() and p.suffix.lower() == ".mat"):
        if _material_of(path.parent, root) is None:
            skipped.append(path)
        else:
            by_folder.setdefault(path.parent, []).append(path)
    folders = []
    for folder, files in sorted(by_folder.items()):
        c, s, m = _material_of(folder, root)  # type: ignore[misc]
        folders.append(LMTFolder(path=folder, category=c, subcategory=s, material=m, files=tuple(files)))
    if not folders:
        raise LMTFormatError(root, "no .mat recordings in folders named C<category>_S<subcategory>_M<material> "
                                   "or C<category>/S<subcategory>/M<material> (not an LMT layout)")
    return LMTScan(folders=tuple(folders), skipped=tuple(skipped))


def _instance_name(folder: LMTFolder, root: Path) -> str:
    """The instance label: the folder name, or ``C<c>_S<s>_M<m>`` for the nested layout."""
    if FOLDER_PATTERN.match(folder.path.name):
        return folder.path.name
    return f"C{folder.category}_S{folder.subcategory}_M{folder.material}"


def _field(path: Path, rec: object, name: str) -> np.ndarray | None:
    """The field as a 1-D float signal, or None where it is missing or empty (an absent stream)."""
    if not hasattr(rec, name):
        return None
    raw = np.asarray(getattr(rec, name))
    if raw.size == 0:
        return None
    if np.iscomplexobj(raw):
        raise LMTFormatError(path, f"field {name!r} is complex; expected a real 1-D signal")
    try:
        x = np.asarray(raw, dtype=np.float64).squeeze()
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
    return scipy.signal.resample_poly(x, ratio.numerator, ratio.denominator, padtype="line")


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
    if isinstance(rec, np.ndarray):  # a struct array: one recording per file is expected
        if rec.size != 1:
            raise LMTFormatError(path, f"{STRUCT_NAME} holds {rec.size} recordings; expected one per file")
        rec = rec.item()
    sound, normal, friction, accel = (_field(path, rec, name) for name in FIELDS)
    if all(x is None for x in (sound, normal, friction, accel)):
        raise LMTFormatError(path, f"{STRUCT_NAME} has none of the fields {', '.join(FIELDS)}")
    if normal is not None and friction is not None and len(normal) != len(friction):
        raise LMTFormatError(path, f"normalForce and frictionForce differ in length ({len(normal)} and "
                                   f"{len(friction)} samples)")
    durations = {name: len(x) / rate for name, x, rate in (
        ("sound", sound, config.sound_rate_hz), ("forces", normal if normal is not None else friction,
                                                 config.force_rate_hz),
        ("accelDFT", accel, config.accel_rate_hz)) if x is not None}
    if max(durations.values()) > (1 + config.max_duration_mismatch) * min(durations.values()):
        listed = ", ".join(f"{k} {v:.3g} s" for k, v in durations.items())
        raise LMTFormatError(path, f"the streams last different times at the configured rates ({listed}); check "
                                   f"the rates (sound {config.sound_rate_hz:g} Hz, forces {config.force_rate_hz:g} "
                                   f"Hz, accelDFT {config.accel_rate_hz:g} Hz)")
    force_hz = NOMINAL_RATE_HZ["normal"] if config.resample else config.force_rate_hz
    accel_hz = NOMINAL_RATE_HZ["accel"] if config.resample else config.accel_rate_hz
    n_taxels = NUM_CHANNELS["normal"]
    streams: dict[str, Stream | None] = {
        "sound": None if sound is None else Stream(sound[:, None].astype(np.float32), config.sound_rate_hz),
        "normal": None, "friction": None, "accel": None}
    if normal is not None:
        normal = _resample(normal, config.force_rate_hz, force_hz)
        normal_taxels = np.repeat(normal[:, None] / n_taxels, n_taxels, axis=1)  # (T, 16) even share of the total
        streams["normal"] = Stream(normal_taxels.astype(np.float32), force_hz)
    if friction is not None:
        friction = _resample(friction, config.force_rate_hz, force_hz)
        shear = np.zeros((friction.shape[0], NUM_CHANNELS["friction"]))  # (T, 32) taxel-major [x1, y1, ...]
        shear[:, 0::2] = friction[:, None] / n_taxels  # x: sliding direction; y stays 0
        streams["friction"] = Stream(shear.astype(np.float32), force_hz)
    if accel is not None:
        accel = _resample(accel, config.accel_rate_hz, accel_hz)
        accel_xyz = np.zeros((accel.shape[0], NUM_CHANNELS["accel"]))  # (T, 3)
        accel_xyz[:, 0] = accel  # DFT321 on x
        streams["accel"] = Stream(accel_xyz.astype(np.float32), accel_hz)
    return StrokeRecord(streams=streams, category=category, instance=instance, combustible=combustible,
                        meta={"object_id": instance, "source": "lmt", "file": path.name, **dict(meta or {})})


@dataclass(frozen=True)
class LMTConversion:
    """What :func:`convert_lmt` did.

    Attributes:
        manifest: the written manifest's path.
        n_recordings: recordings converted.
        skipped_outside: .mat files outside any material folder, not read.
        skipped_bad: (file, problem) of recordings skipped as unreadable or malformed (``skip_bad``).
        absent_streams: stream name -> recordings without it (missing or empty field).
    """

    manifest: Path
    n_recordings: int
    skipped_outside: tuple[Path, ...]
    skipped_bad: tuple[tuple[Path, str], ...]
    absent_streams: Mapping[str, int]


def convert_lmt(src: str | os.PathLike, out_dir: str | os.PathLike, config: LMTConfig = LMTConfig(),
                progress: bool = True) -> LMTConversion:
    """Convert an LMT-layout folder into a data set folder (manifest + shards, env "clean").

    Returns:
        The :class:`LMTConversion` (what was converted and what was skipped, and why).

    Raises:
        LMTFormatError: wrong layout, or a malformed recording without ``skip_bad`` (the message names the file),
            or nothing left to convert.
    """
    scan = scan_lmt(src)
    root = Path(src)
    records, bad = [], []
    for folder in tqdm(scan.folders, desc="lmt", disable=not progress):
        category = config.category_names.get(folder.category, f"C{folder.category}")
        for path in folder.files:
            try:
                records.append(read_lmt_recording(
                    path, category, _instance_name(folder, root), category in config.combustible_categories, config,
                    meta={"subcategory": folder.subcategory, "material": folder.material}))
            except LMTFormatError as exc:
                if not config.skip_bad:
                    raise
                bad.append((path, exc.problem))
    if not records:
        raise LMTFormatError(root, f"no recording could be converted ({len(bad)} malformed)")
    settings = {"source": "lmt", "src": str(src), "sound_rate_hz": config.sound_rate_hz,
                "force_rate_hz": config.force_rate_hz, "accel_rate_hz": config.accel_rate_hz,
                "resample": config.resample, "taxel_mapping": "uniform: normal/16 on z, friction/16 on x, y = 0",
                "accel_mapping": "DFT321 on x, y = z = 0", "skipped_outside": len(scan.skipped),
                "skipped_bad": len(bad)}
    manifest = write_dataset(out_dir, records, env="clean", seed=0, config=settings, shard_size=config.shard_size)
    absent = {m: sum(r.streams.get(m) is None for r in records) for m in NOMINAL_RATE_HZ}
    return LMTConversion(manifest=manifest, n_recordings=len(records), skipped_outside=scan.skipped,
                         skipped_bad=tuple(bad), absent_streams=absent)
