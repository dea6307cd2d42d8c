"""Layouts, the medium and the beam model (sonar_ring.geometry)."""

import copy

import numpy as np
import pytest
import yaml
from numpy.testing import assert_allclose, assert_array_equal

from sonar_ring import geometry
from sonar_ring.geometry import LayoutError, load_layout

SHIPPED = ("browne_ring", "barshan_kuc_pair", "barshan_kuc_array", "kreczmer_triad", "kreczmer_two_triads")


def raw(name):
    return yaml.safe_load(geometry.layout_path(name).read_text())


# --------------------------------------------------------------------------- shipped layouts

@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_layouts_load_consistently(name):
    layout = load_layout(name)
    assert layout.name == name
    k = {"ring": 2, "pair": 2, "triad": 3}[layout.kind]
    assert layout.groups.shape == (layout.n_groups, k)
    assert layout.group_receivers().shape == (layout.n_groups, k, 3)
    assert layout.group_transmitters.shape[0] == layout.n_groups
    assert np.all(layout.group_separation() > 0)
    assert layout.height_offset().shape == (layout.n_groups, layout.group_transmitters.shape[1], k)
    assert_allclose(layout.wavelength(343.0), 343.0 / layout.frequency, rtol=1e-15)


@pytest.mark.parametrize("name", SHIPPED)
def test_plan_is_the_layouts_geometry_from_above_and_read_only(name):
    layout = load_layout(name)
    plan = layout.plan
    assert layout.plan is plan  # computed once
    assert_array_equal(plan.receivers, layout.group_receivers()[..., :2])
    assert_array_equal(plan.transmitters, layout.transmitters[layout.group_transmitters, :2])
    assert_array_equal(plan.height_offset, layout.height_offset())
    assert_array_equal(plan.yaw, layout.group_yaw())
    assert_allclose(plan.facing, np.stack([np.cos(plan.yaw), np.sin(plan.yaw)], axis=-1), rtol=0, atol=0)
    for array in (plan.receivers, plan.transmitters, plan.height_offset, plan.facing, plan.yaw):
        assert array.flags.c_contiguous
        with pytest.raises(ValueError, match="read-only"):
            array[...] = 0.0


def test_browne_ring_geometry():
    ring = load_layout("browne_ring")
    assert ring.n_groups == 48
    # pairs every 7.5 deg, R1 (column 0) counter-clockwise of R2
    assert_allclose(np.degrees(ring.group_yaw()[:3]), [0.0, 7.5, 15.0], atol=1e-12)
    assert_allclose(ring.group_separation(), 0.040, rtol=1e-12)
    r1, r2 = ring.group_receivers()[0, 0], ring.group_receivers()[0, 1]
    assert_allclose(r1, [0.31, 0.02, 0.0], atol=1e-15)
    assert_allclose(r2, [0.31, -0.02, 0.0], atol=1e-15)
    for g in range(ring.n_groups):
        a, b = ring.group_receivers()[g, :, :2]
        assert a[0] * b[1] - a[1] * b[0] < 0  # R2 is clockwise of R1 seen from the centre
    # tiers alternate: emitter 80 mm above tier 0, 125 mm above tier 1
    assert_allclose(ring.height_offset()[:2, 0, :], [[0.08, 0.08], [0.125, 0.125]], atol=1e-15)
    assert ring.isotropic_emitter


def test_barshan_kuc_layouts():
    pair = load_layout("barshan_kuc_pair")
    assert_allclose(pair.group_separation(), [0.080], rtol=1e-15)
    assert_allclose(pair.transducer_of_transmitter, [0, 1])
    # transducer a transmits and is receiver column 0 (left, +y)
    assert_allclose(pair.transmitters[0], pair.receivers[pair.groups[0, 0]])
    assert pair.receivers[pair.groups[0, 0], 1] > 0
    array = load_layout("barshan_kuc_array")
    assert_allclose(array.group_separation(), [0.04, 0.12, 0.20], rtol=1e-12)
    assert_allclose(np.degrees(geometry.beam_half_angle(5.72e-3, 0.020)), 10.05, atol=0.01)


def test_kreczmer_triad_baselines():
    triad = load_layout("kreczmer_triad")
    rx = triad.group_receivers()[0, :, 1]
    assert_allclose(-np.diff(rx), [0.011, 0.004], atol=1e-12)
    assert_allclose(triad.wavelength(348.0), 8.7e-3, rtol=1e-12)


def test_two_triads_are_the_triad_module_turned_to_either_side():
    """Each module of kreczmer_two_triads is kreczmer_triad's, turned +-60 deg and moved to (0, +-0.1) m."""
    module, two = load_layout("kreczmer_triad"), load_layout("kreczmer_two_triads")
    assert two.n_groups == 2 and two.kind == "triad"
    assert_allclose(np.degrees(two.group_yaw()), [60.0, -60.0], atol=1e-12)
    for group, (turn, centre) in enumerate(((np.radians(60.0), [0.0, 0.1]), (np.radians(-60.0), [0.0, -0.1]))):
        rotation = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
        assert_allclose(two.group_receivers()[group, :, :2], module.group_receivers()[0, :, :2] @ rotation.T + centre,
                        atol=1e-6)  # the YAML's micrometres
        assert_allclose(two.group_viewpoint()[group], module.group_viewpoint()[0] @ rotation.T + centre, atol=1e-6)
        assert_allclose(two.height_offset()[group], module.height_offset()[0], atol=1e-12)


def test_every_shipped_layout_has_its_node_parameters():
    for name in SHIPPED:
        assert geometry.shipped_params(name) == geometry.config_path("params", name)
    assert geometry.shipped_params("no_such_layout") is None


@pytest.mark.parametrize("name", SHIPPED)
def test_a_group_is_seen_from_its_transmitters(name):
    """The viewpoint of each group is its emitter (the middle of a pair's two): Browne's ring's centre."""
    layout = load_layout(name)
    assert_allclose(layout.group_viewpoint(), layout.transmitters[layout.group_transmitters, :2].mean(axis=1))
    if layout.kind == "ring":
        assert_array_equal(layout.group_viewpoint(), 0.0)


# --------------------------------------------------------------------------- rejection at load

def test_zero_separation_is_rejected_naming_the_field():
    ring = raw("browne_ring")
    ring["ring"]["separation"] = 0.0
    with pytest.raises(LayoutError, match="'separation'"):
        load_layout(ring)
    pair = raw("barshan_kuc_pair")
    pair["transducers"][1]["position"] = list(pair["transducers"][0]["position"])
    with pytest.raises(LayoutError, match="'groups'.*zero receiver separation"):
        load_layout(pair)


@pytest.mark.parametrize("name", SHIPPED)
@pytest.mark.parametrize("field", ["beam_half_angle_deg", "frequency_hz", "aperture_radius", "ping_rate_hz",
                                   "max_range", "kind"])
def test_missing_top_level_field_is_named(name, field):
    mapping = raw(name)
    del mapping[field]
    with pytest.raises(LayoutError, match=f"'{field}'"):
        load_layout(mapping)


@pytest.mark.parametrize("field", ["pairs", "separation", "emitter_height", "tiers"])
def test_missing_ring_field_is_named(field):
    mapping = raw("browne_ring")
    del mapping["ring"][field]
    with pytest.raises(LayoutError, match=f"'{field}'"):
        load_layout(mapping)


@pytest.mark.parametrize("field", ["position", "yaw_deg", "roles"])
def test_missing_transducer_field_is_named(field):
    mapping = raw("kreczmer_triad")
    del mapping["transducers"][2][field]
    with pytest.raises(LayoutError, match=rf"transducers\[2\].*'{field}'"):
        load_layout(mapping)


@pytest.mark.parametrize("field", ["transducers", "groups"])
def test_missing_list_field_is_named(field):
    mapping = raw("barshan_kuc_pair")
    del mapping[field]
    with pytest.raises(LayoutError, match=f"'{field}'"):
        load_layout(mapping)


def test_layout_from_file_names_the_file(tmp_path):
    path = tmp_path / "broken.yaml"
    mapping = raw("barshan_kuc_pair")
    del mapping["max_range"]
    path.write_text(yaml.safe_dump(mapping))
    with pytest.raises(LayoutError, match=r"broken\.yaml.*'max_range'"):
        load_layout(path)
    assert load_layout(geometry.layout_path("barshan_kuc_pair")).name == "barshan_kuc_pair"


# --------------------------------------------------------------------------- medium

def test_speed_of_sound_reference_values():
    assert_allclose(geometry.speed_of_sound(20.0), 343.3, atol=0.05)
    assert_allclose(geometry.speed_of_sound(0.0), 331.4, atol=0.1)
    humid = geometry.speed_of_sound(20.0, 50.0)
    assert humid > geometry.speed_of_sound(20.0)
    assert_allclose(humid, 344.0, atol=0.1)
    assert np.all(np.diff(geometry.speed_of_sound(20.0, [0.0, 25.0, 50.0, 100.0])) > 0)


def test_speed_of_sound_temperature_sensitivity():
    t = np.array([15.0, 20.0, 25.0])
    step = 1e-3
    slope = (geometry.speed_of_sound(t + step) - geometry.speed_of_sound(t - step)) / (2 * step)
    relative = slope / geometry.speed_of_sound(t)
    assert_allclose(relative, 1.7e-3, rtol=0.03)
    # 1 K of error is ~1.7 mm of range per metre
    assert_allclose(geometry.speed_of_sound(21.0) / 343.3 - 1.0, 1.7e-3, rtol=0.03)


def test_error_handling():
    with pytest.raises(ValueError, match="temperature"):
        geometry.speed_of_sound(-300.0)
    with pytest.raises(ValueError, match="humidity"):
        geometry.speed_of_sound(20.0, 120.0)
    with pytest.raises(ValueError, match="humidity"):
        geometry.speed_of_sound(20.0, -1.0)
    with pytest.raises(ValueError, match="pressure"):
        geometry.speed_of_sound(20.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="beam_half_angle"):
        geometry.beam_half_angle(0.05, 0.02)
    with pytest.raises(LayoutError, match="cannot read"):
        load_layout("no_such_layout")
    mapping = raw("browne_ring")
    mapping["kind"] = "hexapod"
    with pytest.raises(LayoutError, match="'kind'"):
        load_layout(mapping)
    mapping = copy.deepcopy(raw("browne_ring"))
    mapping["frequency_hz"] = "fast"
    with pytest.raises(LayoutError, match="'frequency_hz' must be a finite number > 0, got 'fast'"):
        load_layout(mapping)
    mapping = raw("barshan_kuc_pair")
    mapping["groups"][0]["receivers"] = ["a", "nobody"]
    with pytest.raises(LayoutError, match=r"groups\[0\]"):
        load_layout(mapping)
    mapping = raw("kreczmer_triad")
    mapping["groups"][0]["receivers"] = ["r0", "r1"]
    with pytest.raises(LayoutError, match="needs 3 receivers"):
        load_layout(mapping)
    assert issubclass(LayoutError, ValueError)
