"""Material catalogue: contents, validation errors, sampling, PyBullet contact values."""

from __future__ import annotations

import copy
import dataclasses
import tomllib

import numpy as np
import pytest

from perception.materials import (
    CATALOGUE_PATH,
    CATEGORIES,
    CatalogueError,
    MaterialSample,
    contact_dynamics,
    default_catalogue,
    load_catalogue,
    nominal_sample,
    parse_catalogue,
    sample_material,
    shore_a_to_youngs_modulus_pa,
)


@pytest.fixture(scope="module")
def raw_catalogue() -> dict:
    with CATALOGUE_PATH.open("rb") as fh:
        return tomllib.load(fh)


def test_catalogue_has_seven_categories_with_six_or_more_instances_each():
    cat = default_catalogue()
    assert cat.categories == CATEGORIES
    assert len(cat.instances) >= 42
    for category in CATEGORIES:
        assert len(cat.instances_of(category)) >= 6, category
    assert {c for c, burns in cat.combustible.items() if not burns} == {"metal", "stone"}
    for material in cat.instances.values():
        assert material.source.strip()
        assert material.combustible == (material.category not in ("metal", "stone"))
        assert material.friction_static.nominal >= material.friction_kinetic.nominal


def _expect_error(data: dict, *fragments: str) -> str:
    with pytest.raises(CatalogueError) as info:
        parse_catalogue(data, origin="test.toml")
    message = str(info.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message, message
    return message


def test_validation_errors_name_entry_and_field(raw_catalogue):
    data = copy.deepcopy(raw_catalogue)
    data["instances"]["oak"]["colour"] = "brown"
    _expect_error(data, "instances.oak.colour", "unknown key")

    data = copy.deepcopy(raw_catalogue)
    del data["instances"]["steel"]["loss_factor"]
    _expect_error(data, "instances.steel.loss_factor", "missing")

    data = copy.deepcopy(raw_catalogue)
    data["instances"]["granite"]["density_kg_m3"] = [-2700.0, 0.03]
    _expect_error(data, "instances.granite.density_kg_m3", "outside")

    data = copy.deepcopy(raw_catalogue)
    data["instances"]["pine"]["friction_static"] = [0.3, 0.1]
    _expect_error(data, "instances.pine.friction_static", "below kinetic")

    data = copy.deepcopy(raw_catalogue)
    data["instances"]["denim"]["category"] = "fabric"
    _expect_error(data, "instances.denim.category", "unknown category")

    data = copy.deepcopy(raw_catalogue)
    data["instances"]["abs"]["restitution"] = [0.5, 3.0]
    _expect_error(data, "instances.abs.restitution", "relative_spread")

    data = copy.deepcopy(raw_catalogue)
    data["instances"]["nitrile"]["youngs_modulus_pa"] = [5e6, 0.1]
    _expect_error(data, "instances.nitrile.shore_a", "not both")

    data = copy.deepcopy(raw_catalogue)
    data["instances"]["brass"]["speed_of_sound_mps"] = ["fast", 0.1]
    _expect_error(data, "instances.brass.speed_of_sound_mps", "number")

    data = copy.deepcopy(raw_catalogue)
    data["categories"]["metal"] = {"combustible": True}
    _expect_error(data, "categories.metal.combustible")

    data = copy.deepcopy(raw_catalogue)
    data["categories"]["glass"] = {"combustible": False}
    _expect_error(data, "categories.glass", "unknown category")


def test_load_catalogue_reports_bad_files(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[instances.oak\ncategory = 'wood'\n")
    with pytest.raises(CatalogueError, match="bad.toml: not valid TOML"):
        load_catalogue(bad)
    with pytest.raises(CatalogueError, match="not found"):
        load_catalogue(tmp_path / "missing.toml")
    with pytest.raises(CatalogueError, match="unknown material instance"):
        default_catalogue().instance("unobtainium")


def test_sampling_is_seeded_varied_and_physical():
    oak = default_catalogue().instance("oak")
    a = sample_material(oak, np.random.default_rng(1))
    b = sample_material(oak, np.random.default_rng(1))
    c = sample_material(oak, np.random.default_rng(2))
    assert a == b
    assert a != c  # two oak blocks are not identical
    rng = np.random.default_rng(0)
    for material in default_catalogue().instances.values():
        for _ in range(20):
            s = sample_material(material, rng)
            assert s.friction_static >= s.friction_kinetic > 0
            assert s.density_kg_m3 > 0 and s.youngs_modulus_pa > 0 and s.roughness_rms_m > 0
            assert 0 < s.restitution < 1 and 0 < s.hurst_exponent < 1
    densities = [sample_material(oak, rng).density_kg_m3 for _ in range(400)]
    assert 0.05 < np.std(np.log(densities)) < 0.15  # the catalogue's 10 % spread


def test_material_sample_rejects_inconsistent_friction_and_nan():
    s = nominal_sample(default_catalogue().instance("steel"))
    with pytest.raises(CatalogueError, match="friction_static"):
        dataclasses.replace(s, friction_static=0.1, friction_kinetic=0.5)
    with pytest.raises(CatalogueError, match="not finite"):
        dataclasses.replace(s, density_kg_m3=float("nan"))
    # zero friction used to pass and turn into NaN in the emulation, which divides by it
    with pytest.raises(CatalogueError, match="friction_kinetic must be positive, got 0.0"):
        dataclasses.replace(s, friction_kinetic=0.0)
    with pytest.raises(CatalogueError, match="restitution must be >= 0"):
        dataclasses.replace(s, restitution=-0.1)
    assert dataclasses.replace(s, restitution=0.0).restitution == 0.0


def test_shore_conversion_is_monotonic_and_plausible():
    moduli = [shore_a_to_youngs_modulus_pa(s) for s in (30, 50, 70, 90)]
    assert all(a < b for a, b in zip(moduli, moduli[1:]))
    assert 1.5e6 < shore_a_to_youngs_modulus_pa(50) < 3.5e6


def test_contact_dynamics_ranges_and_ordering():
    cat = default_catalogue()
    size = (0.06, 0.05, 0.04)

    def dyn(name: str):
        return contact_dynamics(nominal_sample(cat.instance(name)), size, "box")

    for name in cat.instances:
        d = dyn(name)
        assert 1e3 <= d.contact_stiffness_n_per_m <= 3e5
        assert d.contact_damping_n_s_per_m > 0 and d.mass_kg > 0
        assert d.lateral_friction == pytest.approx(cat.instance(name).friction_kinetic.nominal)
    assert dyn("steel").contact_stiffness_n_per_m > dyn("nitrile").contact_stiffness_n_per_m
    assert dyn("nitrile").contact_stiffness_n_per_m > dyn("polyester_fleece").contact_stiffness_n_per_m
    assert dyn("steel").mass_kg == pytest.approx(7850.0 * 0.06 * 0.05 * 0.04)
    cyl = contact_dynamics(nominal_sample(cat.instance("steel")), (0.05, 0.05, 0.1), "cylinder")
    assert cyl.mass_kg == pytest.approx(7850.0 * np.pi * 0.025**2 * 0.1)
    with pytest.raises(ValueError, match="shape"):
        contact_dynamics(nominal_sample(cat.instance("steel")), size, "torus")
    assert isinstance(nominal_sample(cat.instance("oak")), MaterialSample)
