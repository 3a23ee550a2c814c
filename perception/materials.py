"""Material catalogue: loading and validating ``materials.toml``, drawing objects, PyBullet contact values.

The catalogue lists the paper's seven categories (metal, paper, polymer, rubber, stone, textiles, wood; metal
and stone non-combustible) with six instances each. Every physical parameter is stored as
``[nominal, relative_spread]``; :func:`sample_material` draws one object's parameters from a log-normal
spread around the nominal values, so two oak blocks are not identical.

:func:`contact_dynamics` turns a drawn material and an object's size into the values PyBullet's
``changeDynamics`` takes. This module is pure (numpy only): it never imports pybullet.

Typical use::

    catalogue = default_catalogue()
    sample = sample_material(catalogue.instance("oak"), rng)
    dyn = contact_dynamics(sample, size_m=(0.06, 0.06, 0.04), shape="box")
"""

from __future__ import annotations

import functools
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any, Mapping

import numpy as np

CATALOGUE_PATH = Path(__file__).with_name("materials.toml")

CATEGORIES: tuple[str, ...] = ("metal", "paper", "polymer", "rubber", "stone", "textiles", "wood")
"""The paper's seven material categories (FISHM)."""

NON_COMBUSTIBLE: frozenset[str] = frozenset({"metal", "stone"})

SHAPES: tuple[str, ...] = ("box", "cylinder", "sphere")

PARAMETER_RANGES: Mapping[str, tuple[float, float]] = MappingProxyType({
    "density_kg_m3": (10.0, 25_000.0),
    "youngs_modulus_pa": (1e4, 1e12),
    "friction_static": (0.01, 3.0),
    "friction_kinetic": (0.01, 3.0),
    "roughness_rms_m": (1e-9, 1e-3),
    "correlation_length_m": (1e-6, 1e-2),
    "hurst_exponent": (0.05, 1.0),
    "loss_factor": (1e-5, 2.0),
    "speed_of_sound_mps": (5.0, 10_000.0),
    "restitution": (0.0, 1.0),
})
"""Allowed range (inclusive) of every nominal value, SI units."""

SHORE_A_RANGE: tuple[float, float] = (5.0, 95.0)
MAX_RELATIVE_SPREAD = 1.0
_CLIP_SIGMAS = 2.5  # log-normal draws are clipped at +-2.5 sigma so no object is absurd


class CatalogueError(ValueError):
    """The material catalogue is malformed; the message names the entry and field."""


@dataclass(frozen=True)
class ParameterSpec:
    """One catalogue parameter.

    Attributes:
        nominal: nominal value, SI units (see the field name).
        rel_spread: 1-sigma relative spread of the log-normal draw (0.1 = about 10 %).
    """

    nominal: float
    rel_spread: float


@dataclass(frozen=True)
class Material:
    """One catalogue instance (a fine-grained class), e.g. ``oak``.

    Attributes:
        name: instance name, e.g. ``"oak"``.
        category: one of :data:`CATEGORIES`.
        combustible: whether the category burns.
        source: where the numbers come from (citation or stated estimate).
        density_kg_m3 .. restitution: see ``materials.toml`` for the meaning of each parameter.
    """

    name: str
    category: str
    combustible: bool
    source: str
    density_kg_m3: ParameterSpec
    youngs_modulus_pa: ParameterSpec
    friction_static: ParameterSpec
    friction_kinetic: ParameterSpec
    roughness_rms_m: ParameterSpec
    correlation_length_m: ParameterSpec
    hurst_exponent: ParameterSpec
    loss_factor: ParameterSpec
    speed_of_sound_mps: ParameterSpec
    restitution: ParameterSpec


@dataclass(frozen=True)
class MaterialSample:
    """The physical parameters of one object, drawn from its material's spread.

    The names (``instance``, ``category``, ``combustible``) are labels only: the sensor emulation reads
    nothing but the physical fields.

    Attributes:
        instance: catalogue instance name.
        category: material category.
        combustible: label derived from the category.
        density_kg_m3: bulk density, kg/m^3.
        youngs_modulus_pa: modulus normal to the stroked face, Pa.
        friction_static: static friction coefficient against the silicone pad.
        friction_kinetic: kinetic friction coefficient against the silicone pad (<= friction_static).
        roughness_rms_m: RMS surface height, m.
        correlation_length_m: lateral correlation length of the height profile, m.
        hurst_exponent: self-affine slope of the roughness spectrum, 0..1.
        loss_factor: structural loss factor eta (modal damping ratio = eta / 2).
        speed_of_sound_mps: bar wave speed along the object's long axis, m/s.
        restitution: coefficient of restitution against the pad, 0..1.
    """

    instance: str
    category: str
    combustible: bool
    density_kg_m3: float
    youngs_modulus_pa: float
    friction_static: float
    friction_kinetic: float
    roughness_rms_m: float
    correlation_length_m: float
    hurst_exponent: float
    loss_factor: float
    speed_of_sound_mps: float
    restitution: float

    def __post_init__(self) -> None:
        for name in PARAMETER_RANGES:
            value = getattr(self, name)
            if not math.isfinite(value):
                raise CatalogueError(f"material sample {self.instance!r}: {name} is not finite ({value})")
            if value < 0 or (value == 0 and PARAMETER_RANGES[name][0] > 0):  # the emulation divides by them
                raise CatalogueError(f"material sample {self.instance!r}: {name} must be "
                                     f"{'positive' if PARAMETER_RANGES[name][0] > 0 else '>= 0'}, got {value}")
        if self.friction_static < self.friction_kinetic:
            raise CatalogueError(
                f"material sample {self.instance!r}: friction_static {self.friction_static} < "
                f"friction_kinetic {self.friction_kinetic}"
            )


@dataclass(frozen=True)
class MaterialCatalogue:
    """The validated catalogue.

    Attributes:
        combustible: category -> combustible flag.
        instances: instance name -> :class:`Material`, in file order.
    """

    combustible: Mapping[str, bool]
    instances: Mapping[str, Material]

    def instance(self, name: str) -> Material:
        """The instance called ``name``; raises :class:`CatalogueError` if there is none."""
        try:
            return self.instances[name]
        except KeyError:
            raise CatalogueError(f"unknown material instance {name!r}") from None

    def instances_of(self, category: str) -> tuple[str, ...]:
        """Instance names of one category, in file order."""
        if category not in self.combustible:
            raise CatalogueError(f"unknown material category {category!r}")
        return tuple(n for n, m in self.instances.items() if m.category == category)

    @property
    def categories(self) -> tuple[str, ...]:
        return tuple(c for c in CATEGORIES if c in self.combustible)


# --------------------------------------------------------------------------------------------- loading

_PARAMETER_NAMES: tuple[str, ...] = tuple(PARAMETER_RANGES)
_INSTANCE_KEYS = frozenset({"category", "source", "shore_a", *_PARAMETER_NAMES})


def shore_a_to_youngs_modulus_pa(shore_a: float) -> float:
    """Gent's (1958) relation between Shore A hardness and Young's modulus.

    Args:
        shore_a: Shore A hardness, 5..95.

    Returns:
        Young's modulus in Pa.
    """
    return 0.0981e6 * (56.0 + 7.62336 * shore_a) / (0.137505 * (254.0 - 2.54 * shore_a))


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise CatalogueError(f"{where}: expected a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise CatalogueError(f"{where}: value is not finite ({value})")
    return value


def _parameter(raw: Any, where: str, value_range: tuple[float, float]) -> ParameterSpec:
    if not isinstance(raw, (list, tuple)) or len(raw) != 2:
        raise CatalogueError(f"{where}: expected [nominal, relative_spread], got {raw!r}")
    nominal = _number(raw[0], where + " nominal")
    spread = _number(raw[1], where + " relative_spread")
    lo, hi = value_range
    if not lo <= nominal <= hi:
        raise CatalogueError(f"{where}: nominal {nominal:g} outside the allowed range [{lo:g}, {hi:g}]")
    if not 0.0 <= spread <= MAX_RELATIVE_SPREAD:
        raise CatalogueError(f"{where}: relative_spread {spread:g} outside [0, {MAX_RELATIVE_SPREAD:g}]")
    return ParameterSpec(nominal, spread)


def _modulus_from_shore(raw: Any, where: str) -> ParameterSpec:
    shore = _parameter(raw, where, SHORE_A_RANGE)
    modulus = shore_a_to_youngs_modulus_pa(shore.nominal)
    # Propagate the relative spread through the (steep) conversion: d ln E / d S * S * spread.
    step = 0.5
    dlog = (math.log(shore_a_to_youngs_modulus_pa(shore.nominal + step))
            - math.log(shore_a_to_youngs_modulus_pa(shore.nominal - step))) / (2 * step)
    return ParameterSpec(modulus, min(MAX_RELATIVE_SPREAD, dlog * shore.nominal * shore.rel_spread))


def _parse_instance(name: str, raw: Any, combustible: Mapping[str, bool], origin: str) -> Material:
    where = f"{origin}: instances.{name}"
    if not isinstance(raw, Mapping):
        raise CatalogueError(f"{where}: expected a table, got {type(raw).__name__}")
    unknown = sorted(set(raw) - _INSTANCE_KEYS)
    if unknown:
        raise CatalogueError(f"{where}.{unknown[0]}: unknown key")
    category = raw.get("category")
    if category is None:
        raise CatalogueError(f"{where}.category: missing value")
    if category not in combustible:
        raise CatalogueError(f"{where}.category: unknown category {category!r}")
    source = raw.get("source")
    if not isinstance(source, str) or not source.strip():
        raise CatalogueError(f"{where}.source: missing value (cite a source or state an estimate)")
    if "shore_a" in raw and "youngs_modulus_pa" in raw:
        raise CatalogueError(f"{where}.shore_a: give either shore_a or youngs_modulus_pa, not both")
    params: dict[str, ParameterSpec] = {}
    for field_name in _PARAMETER_NAMES:
        if field_name == "youngs_modulus_pa" and "shore_a" in raw:
            params[field_name] = _modulus_from_shore(raw["shore_a"], f"{where}.shore_a")
            continue
        if field_name not in raw:
            raise CatalogueError(f"{where}.{field_name}: missing value")
        params[field_name] = _parameter(raw[field_name], f"{where}.{field_name}", PARAMETER_RANGES[field_name])
    if params["friction_static"].nominal < params["friction_kinetic"].nominal:
        raise CatalogueError(
            f"{where}.friction_static: static friction {params['friction_static'].nominal:g} is below "
            f"kinetic friction {params['friction_kinetic'].nominal:g}"
        )
    return Material(name=name, category=category, combustible=combustible[category], source=source, **params)


def parse_catalogue(data: Mapping[str, Any], origin: str = "<catalogue>") -> MaterialCatalogue:
    """Validate a decoded catalogue (the TOML's tables as dicts).

    Args:
        data: mapping with ``categories`` and ``instances`` tables, laid out as ``materials.toml``.
        origin: file name or label used in error messages.

    Returns:
        The validated catalogue.

    Raises:
        CatalogueError: one line naming the entry and field: unknown keys or categories, missing values,
            out-of-range numbers, static friction below kinetic friction, a wrong combustible flag.
    """
    unknown = sorted(set(data) - {"categories", "instances"})
    if unknown:
        raise CatalogueError(f"{origin}: unknown top-level key {unknown[0]!r}")
    categories = data.get("categories")
    if not isinstance(categories, Mapping) or not categories:
        raise CatalogueError(f"{origin}: categories: missing table")
    combustible: dict[str, bool] = {}
    for cat, entry in categories.items():
        where = f"{origin}: categories.{cat}"
        if cat not in CATEGORIES:
            raise CatalogueError(f"{where}: unknown category (expected one of {', '.join(CATEGORIES)})")
        if not isinstance(entry, Mapping) or set(entry) != {"combustible"}:
            raise CatalogueError(f"{where}: expected exactly {{ combustible = true|false }}")
        flag = entry["combustible"]
        if not isinstance(flag, bool):
            raise CatalogueError(f"{where}.combustible: expected true or false, got {flag!r}")
        if flag == (cat in NON_COMBUSTIBLE):
            raise CatalogueError(f"{where}.combustible: {cat} must be {'false' if flag else 'true'} (paper)")
        combustible[cat] = flag
    raw_instances = data.get("instances")
    if not isinstance(raw_instances, Mapping) or not raw_instances:
        raise CatalogueError(f"{origin}: instances: missing table")
    instances = {name: _parse_instance(name, raw, combustible, origin) for name, raw in raw_instances.items()}
    return MaterialCatalogue(combustible=MappingProxyType(combustible), instances=MappingProxyType(instances))


def load_catalogue(path: str | Path = CATALOGUE_PATH) -> MaterialCatalogue:
    """Read and validate a TOML catalogue.

    Raises:
        CatalogueError: the file is missing, not TOML, or fails validation (see :func:`parse_catalogue`).
    """
    path = Path(path)
    try:
        with path.open("rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise CatalogueError(f"{path}: catalogue file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise CatalogueError(f"{path}: not valid TOML ({exc})") from None
    return parse_catalogue(data, origin=path.name)


@functools.lru_cache(maxsize=1)
def default_catalogue() -> MaterialCatalogue:
    """The package's ``materials.toml``, loaded once."""
    return load_catalogue(CATALOGUE_PATH)


# --------------------------------------------------------------------------------------------- sampling


def _lognormal(spec: ParameterSpec, rng: np.random.Generator) -> float:
    z = float(np.clip(rng.standard_normal(), -_CLIP_SIGMAS, _CLIP_SIGMAS))
    return spec.nominal * math.exp(spec.rel_spread * z)


def sample_material(material: Material, rng: np.random.Generator) -> MaterialSample:
    """Draw one object's physical parameters around a catalogue instance.

    Each parameter is log-normal around its nominal value with its relative spread (clipped at 2.5
    sigma); the static friction spread applies to the static/kinetic ratio, which is kept >= 1; the
    Hurst exponent and restitution are clipped to their ranges.

    Args:
        material: the catalogue instance.
        rng: random generator (the only source of randomness).

    Returns:
        The object's :class:`MaterialSample`.
    """
    draws = {name: _lognormal(getattr(material, name), rng) for name in _PARAMETER_NAMES}
    ratio_nominal = material.friction_static.nominal / material.friction_kinetic.nominal
    ratio = max(1.0, _lognormal(ParameterSpec(ratio_nominal, material.friction_static.rel_spread), rng))
    mu_k = float(np.clip(draws["friction_kinetic"], *PARAMETER_RANGES["friction_kinetic"]))
    draws["friction_kinetic"] = mu_k
    draws["friction_static"] = min(mu_k * ratio, PARAMETER_RANGES["friction_static"][1])
    draws["hurst_exponent"] = float(np.clip(draws["hurst_exponent"], 0.1, 0.95))
    draws["restitution"] = float(np.clip(draws["restitution"], 0.02, 0.95))
    return MaterialSample(instance=material.name, category=material.category,
                          combustible=material.combustible, **draws)


def nominal_sample(material: Material) -> MaterialSample:
    """The instance's nominal parameters as a sample (no spread), for tests and reference values."""
    return MaterialSample(instance=material.name, category=material.category, combustible=material.combustible,
                          **{name: getattr(material, name).nominal for name in _PARAMETER_NAMES})


# --------------------------------------------------------------------------------------------- dynamics



FINGERTIP_MASS_KG = 0.1
"""Effective mass of the thumb's fingertip behind the tactile pad, kg: the distal segment (0.08 kg), tip
(0.04 kg) and pad (0.005 kg) of urdf/dg3f_lite, less the share the distal joint carries. The one value the
contact model, the impact and friction excitation, the IMU and the sound all use.
"""

@dataclass(frozen=True)
class ContactModelConfig:
    """How material parameters map to PyBullet contact values.

    PyBullet combines two bodies' contact stiffnesses in series and adds their dampings; lateral
    friction and restitution are multiplied. The values below are the object's half: give the pad link
    ``lateralFriction=1`` so that the combined friction equals the object's friction against silicone.

    Attributes:
        contact_radius_m: radius of the reference flat contact used for the stiffness (2 E* a).
        poisson_ratio: Poisson ratio used for the plane-strain modulus E* = E / (1 - nu^2).
        stiffness_min_n_per_m: lower clamp: softer contacts sink through at a 1 kHz step.
        stiffness_max_n_per_m: the stiffness the simulator can still resolve stably at a 1 kHz step with
            a 0.05-0.2 kg fingertip (omega * dt ~ 1.7 at 0.1 kg); stiffer materials are combined with it
            in series, so the map stays monotonic and saturates smoothly.
        fingertip_mass_kg: effective mass the damping is tuned for.
        damping_ratio_range: the damping ratio from restitution is clipped to this range (critical-ish
            damping keeps the contact from chattering).
        spinning_radius_m: effective contact radius turning friction into spinning friction.
    """

    contact_radius_m: float = 0.005
    poisson_ratio: float = 0.3
    stiffness_min_n_per_m: float = 1.0e3
    stiffness_max_n_per_m: float = 3.0e5
    fingertip_mass_kg: float = FINGERTIP_MASS_KG
    damping_ratio_range: tuple[float, float] = (0.3, 1.0)
    spinning_radius_m: float = 0.002


@dataclass(frozen=True)
class ContactDynamics:
    """Values for ``p.changeDynamics`` of an object body.

    Attributes:
        mass_kg: object mass from density and volume, kg.
        lateral_friction: Coulomb coefficient (the kinetic one: steady sliding friction).
        spinning_friction: torsional friction coefficient, m.
        rolling_friction: rolling resistance coefficient, m (hysteresis: loss factor x contact radius).
        restitution: coefficient of restitution.
        contact_stiffness_n_per_m: ``contactStiffness``, N/m.
        contact_damping_n_s_per_m: ``contactDamping``, N s/m (always set together with the stiffness).
    """

    mass_kg: float
    lateral_friction: float
    spinning_friction: float
    rolling_friction: float
    restitution: float
    contact_stiffness_n_per_m: float
    contact_damping_n_s_per_m: float


def object_volume_m3(size_m: tuple[float, float, float], shape: str = "box") -> float:
    """Volume of an object from its bounding size (x, y, z), m^3.

    ``box``: x y z; ``cylinder``: axis along z, diameter the mean of x and y; ``sphere``: diameter the
    mean of x, y and z.
    """
    x, y, z = (float(s) for s in size_m)
    if not (x > 0 and y > 0 and z > 0 and math.isfinite(x * y * z)):
        raise ValueError(f"object size must be three positive finite lengths, got {size_m}")
    if shape == "box":
        return x * y * z
    if shape == "cylinder":
        return math.pi * (0.25 * (x + y)) ** 2 * z
    if shape == "sphere":
        return math.pi / 6.0 * ((x + y + z) / 3.0) ** 3
    raise ValueError(f"unknown shape {shape!r}; expected one of {SHAPES}")


def local_contact_stiffness_n_per_m(sample: MaterialSample, config: ContactModelConfig = ContactModelConfig()) -> float:
    """Unclamped stiffness of the object's surface under a flat contact of radius a: 2 E* a, N/m."""
    e_star = sample.youngs_modulus_pa / (1.0 - config.poisson_ratio**2)
    return 2.0 * e_star * config.contact_radius_m


def damping_ratio_from_restitution(restitution: float) -> float:
    """Damping ratio of a linear spring-dashpot contact with the given coefficient of restitution."""
    log_e = math.log(min(max(restitution, 1e-6), 1.0 - 1e-9))
    return -log_e / math.sqrt(math.pi**2 + log_e**2)


def contact_dynamics(sample: MaterialSample, size_m: tuple[float, float, float], shape: str = "box",
                     config: ContactModelConfig = ContactModelConfig()) -> ContactDynamics:
    """PyBullet ``changeDynamics`` values for an object of a drawn material.

    Stiffness is 2 E* a (flat contact of radius ``config.contact_radius_m``) combined in series with
    ``stiffness_max`` and floored at ``stiffness_min``: about 1e3..3e5 N/m, soft rubber and textiles low,
    metal and stone at the top. Damping is c = 2 zeta sqrt(k m) for the fingertip mass, with zeta from the
    restitution clipped to a critical-ish range.

    Args:
        sample: the object's material parameters.
        size_m: bounding size (x, y, z), m.
        shape: ``"box"``, ``"cylinder"`` or ``"sphere"``.
        config: mapping constants.

    Returns:
        The :class:`ContactDynamics`.
    """
    mass = sample.density_kg_m3 * object_volume_m3(size_m, shape)
    k_raw = local_contact_stiffness_n_per_m(sample, config)
    k = 1.0 / (1.0 / k_raw + 1.0 / config.stiffness_max_n_per_m)
    k = max(k, config.stiffness_min_n_per_m)
    zeta = float(np.clip(damping_ratio_from_restitution(sample.restitution), *config.damping_ratio_range))
    damping = 2.0 * zeta * math.sqrt(k * config.fingertip_mass_kg)
    return ContactDynamics(
        mass_kg=mass,
        lateral_friction=sample.friction_kinetic,
        spinning_friction=sample.friction_kinetic * config.spinning_radius_m,
        rolling_friction=float(np.clip(sample.loss_factor * config.contact_radius_m, 1e-6, 1e-3)),
        restitution=sample.restitution,
        contact_stiffness_n_per_m=k,
        contact_damping_n_s_per_m=damping,
    )

