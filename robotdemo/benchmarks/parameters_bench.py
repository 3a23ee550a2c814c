"""How much of each object's material the strokes of a data set keep (`robotdemo bench parameters`).

The strokes do not store their objects' physical parameters; this draws them again from the seed in each
stroke's meta (:func:`robotdemo.dataset.drawn_material`, the recorder's own draw) and hands both to
:func:`perception.parameter_probe.run_parameter_probe`: a classifier given the exact parameters on the networks'
splits (the oracle), and how well a stroke's statistics regress each parameter (the recovery).
"""

from __future__ import annotations

import os

from perception.dataset import load_dataset
from perception.features import FeatureConfig
from perception.parameter_probe import ParameterProbeConfig, run_parameter_probe
from perception.pooled_statistics import PooledStatisticsConfig
from robotdemo.dataset import drawn_materials


def run_parameters_benchmark(data_dir: str | os.PathLike, read_test: bool = False, progress: bool = True,
                             features: FeatureConfig = FeatureConfig()) -> dict:
    """The parameter probe on ``data_dir`` (validation parts only unless ``read_test``), the strokes' statistics
    pooled from the front end ``features``.

    Raises:
        RobotDemoError: a stroke's object cannot be drawn again (:func:`robotdemo.dataset.drawn_material`).
    """
    data = load_dataset(data_dir)
    samples = drawn_materials(data.records, progress=progress)
    config = ParameterProbeConfig(splits=PooledStatisticsConfig(read_test=read_test, features=features))
    return {"data": os.fspath(data_dir), "data_manifest_sha256": data.manifest_sha256,
            **run_parameter_probe(data.records, samples, config, progress=progress)}
