"""Material classification of one recorded stroke, as the sorting state machine consumes it.

The state machine takes any callable ``classifier(record: StrokeRecord) -> Classification``; this module
defines that record and the production classifier built from a trained checkpoint
(:func:`perception.checkpoint.load_checkpoint`): featurize -> normalise -> collate -> model -> softmax.

Typical use::

    classify = TouchFormerClassifier.from_checkpoint("robotdemo/checkpoints/touchformer_fire")
    result = classify(record)          # Classification(category="wood", confidence=0.93, ...)
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Mapping

import numpy as np
import torch

from perception.checkpoint import Checkpoint, CheckpointError, load_checkpoint
from perception.features import collate, feature_dims, featurize
from perception.materials import default_catalogue
from perception.streams import MODALITIES, StrokeRecord
from perception.touchformer_infer import for_inference
from robotdemo.errors import RobotDemoError


@dataclass(frozen=True)
class Classification:
    """What a classifier concluded from one stroke (or from several, averaged).

    Attributes:
        category: predicted material category (a key of the material catalogue's ``combustible``).
        confidence: probability of ``category``, in [0, 1].
        probabilities: category -> probability (sums to 1).
        gate_weights: modality -> fusion weight alpha_m (TouchFormer's MAG; 0 for a missing or dropped
            modality); empty when the classifier has no such weights.
        modalities_present: modalities the record held, :data:`perception.streams.MODALITIES` order.
    """

    category: str
    confidence: float
    probabilities: Mapping[str, float]
    gate_weights: Mapping[str, float]
    modalities_present: tuple[str, ...]

    def __post_init__(self) -> None:
        if not (0.0 <= self.confidence <= 1.0 and math.isfinite(self.confidence)):
            raise ValueError(f"Classification.confidence must lie in [0, 1], got {self.confidence}")
        unknown = set(self.gate_weights) - set(MODALITIES)
        if unknown:
            raise ValueError(f"Classification.gate_weights has unknown modalities {sorted(unknown)}")


def average_classifications(results: list[Classification]) -> Classification:
    """The decision from several strokes of one object: mean probabilities and mean gate weights.

    The category is the arg-max of the mean probabilities (ties broken by category name); the modalities
    present are those present in any stroke.
    """
    if not results:
        raise ValueError("average_classifications needs at least one classification")
    if len(results) == 1:
        return results[0]
    categories = sorted({c for r in results for c in r.probabilities} | {r.category for r in results})
    probs = {c: float(np.mean([r.probabilities.get(c, 0.0) for r in results])) for c in categories}
    best = max(categories, key=lambda c: (probs[c], c))
    gates_keys = [m for m in MODALITIES if any(m in r.gate_weights for r in results)]
    gates = {m: float(np.mean([r.gate_weights.get(m, 0.0) for r in results])) for m in gates_keys}
    present = tuple(m for m in MODALITIES if any(m in r.modalities_present for r in results))
    return Classification(category=best, confidence=min(1.0, probs[best]), probabilities=probs,
                          gate_weights=gates, modalities_present=present)


def combustible_probability(result: Classification, combustible: Mapping[str, bool]) -> float:
    """P(the material burns): the summed probabilities of the combustible categories."""
    return float(sum(p for c, p in result.probabilities.items() if combustible[c]))


@dataclass(frozen=True)
class ZoneDecision:
    """What the robot does with a classification: which zone, and how sure it is of that.

    Attributes:
        combustible: the object goes to the combustible zone.
        combustible_probability: P(combustible), the sum over the combustible categories.
        confidence: probability of the chosen side, max(P, 1 - P), in [0.5, 1].
        category: the most probable category on the chosen side (so the reported category and the zone agree).
    """

    combustible: bool
    combustible_probability: float
    confidence: float
    category: str


def decide_zone(result: Classification, combustible: Mapping[str, bool]) -> ZoneDecision:
    """The sorting decision from category probabilities: the side (combustible or not) with the larger summed
    probability, which minimises the chance of a wrong zone; then the most probable category on that side
    (ties broken by name). The category's own arg-max can lie on the other side when the probability is spread
    over several categories of one side."""
    p_burn = combustible_probability(result, combustible)
    burns = p_burn >= 0.5
    side = [c for c in result.probabilities if combustible[c] == burns] or [result.category]
    category = max(side, key=lambda c: (result.probabilities.get(c, 0.0), c))
    return ZoneDecision(combustible=burns, combustible_probability=p_burn, confidence=max(p_burn, 1.0 - p_burn),
                        category=category)


class OracleClassifier:
    """Answers each record's true category with probability 1: a diagnostic that separates the robot's
    handling (strokes, grasps, placing) from the classifier's mistakes in ``robotdemo bench demo --oracle``.
    It reads the label, so no figure it produces is a sorting accuracy of the robot."""

    def __init__(self) -> None:
        self.categories = tuple(default_catalogue().combustible)

    def __call__(self, record: StrokeRecord) -> Classification:
        probs = {c: float(c == record.category) for c in self.categories}
        present = record.present
        return Classification(category=record.category, confidence=1.0, probabilities=probs,
                              gate_weights={m: (1.0 / len(present) if m in present else 0.0) for m in MODALITIES},
                              modalities_present=present)


class TouchFormerClassifier:
    """A trained checkpoint (TouchFormer or any model of :data:`perception.baselines.MODEL_REGISTRY`) as a
    ``StrokeRecord -> Classification`` callable, on CPU.

    Checkpoints whose classes are material instances (``"oak"``, ...) are folded into categories by summing
    the instances' probabilities (via the material catalogue).
    """

    def __init__(self, checkpoint: Checkpoint) -> None:
        self.checkpoint = checkpoint
        self.model = for_inference(checkpoint.model)  # TouchFormer repacked: same outputs, ~5x faster
        self.dims = feature_dims(checkpoint.feature_config)
        catalogue = default_catalogue()
        names = checkpoint.class_names
        if all(n in catalogue.combustible for n in names):
            self.class_category = tuple(names)
        elif all(n in catalogue.instances for n in names):
            self.class_category = tuple(catalogue.instances[n].category for n in names)
        else:
            unknown = [n for n in names if n not in catalogue.combustible and n not in catalogue.instances]
            raise RobotDemoError(f"checkpoint classes {unknown[:5]} are neither material categories nor instances")
        self.categories = tuple(dict.fromkeys(self.class_category))

    @classmethod
    def from_checkpoint(cls, directory: str | os.PathLike) -> "TouchFormerClassifier":
        """Load ``directory`` (``model.safetensors`` + ``config.json``).

        Raises:
            RobotDemoError: the folder is missing or the checkpoint cannot be loaded (one-line message).
        """
        if not os.path.isdir(directory):
            raise RobotDemoError(f"checkpoint folder {os.fspath(directory)} not found")
        try:
            return cls(load_checkpoint(directory))
        except CheckpointError as exc:
            raise RobotDemoError(f"cannot load checkpoint: {exc}") from None

    @torch.inference_mode()
    def __call__(self, record: StrokeRecord) -> Classification:
        ck = self.checkpoint
        batch = collate([featurize(record, ck.feature_config)], self.dims, stats=ck.norm_stats)
        out = self.model(batch)
        p_class = torch.softmax(out.logits[0].double() / ck.temperature, dim=-1).numpy()  # (K,), calibrated
        probs = {c: 0.0 for c in self.categories}
        for k, category in enumerate(self.class_category):
            probs[category] += float(p_class[k])
        best = max(self.categories, key=lambda c: (probs[c], c))
        alphas = out.alphas[0].double().numpy()  # (4,) MODALITIES order
        return Classification(category=best, confidence=min(1.0, probs[best]), probabilities=probs,
                              gate_weights={m: float(alphas[i]) for i, m in enumerate(MODALITIES)},
                              modalities_present=record.present)
