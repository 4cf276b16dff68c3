"""Field conditions without Blender: the ripple spectrum has the spec's rms height and a mean of zero, a new
surface per photo that a rerun repeats; the rippled mesh fades into the flat frame; the water body is a closed
box below every trough; targets sit on dry, gentle ground; ideal presets carry no trace of any of it."""

import math
from dataclasses import replace

import numpy as np
import pytest

from ragsplat.camera import Camera
from ragsplat.datagen import conditions, flight
from ragsplat.datagen.assets import FAR, scene_geometry
from ragsplat.datagen.bed import ground_truth, height_at, make_bed
from ragsplat.datagen.build import render_job, scene_metadata
from ragsplat.datagen.spec import CLEAR_RIVER, PRESETS, SceneSpec, preset, validate, with_conditions
from ragsplat.errors import SpecError

IDEAL = [name for name, spec in PRESETS.items() if spec.conditions is None]


def test_ripples_have_the_rms_height_asked_and_zero_mean():
    c = preset("small-field").conditions
    k, amplitude = conditions.ripple_waves(c, seed=0)
    xy = np.random.default_rng(1).uniform(-8, 8, (50_000, 2))
    heights = [conditions.ripple_height(xy, k, amplitude, conditions.ripple_phases(c, 0, v))
               for v in range(8)]
    h = np.concatenate(heights)
    assert h.std() == pytest.approx(c.ripple_amplitude, rel=0.05)
    assert abs(h.mean()) < 0.05 * c.ripple_amplitude  # the level is the mean surface
    lengths = 2 * np.pi / np.linalg.norm(k, axis=1)
    assert lengths.min() >= c.ripple_wavelengths[0] and lengths.max() <= c.ripple_wavelengths[1]
    # The rms slope from the spectrum is the slope of the surface (finite differences).
    e = 1e-4
    dx = (conditions.ripple_height(xy + [e, 0], k, amplitude, conditions.ripple_phases(c, 0, 0))
          - conditions.ripple_height(xy - [e, 0], k, amplitude, conditions.ripple_phases(c, 0, 0))) / (2 * e)
    dy = (conditions.ripple_height(xy + [0, e], k, amplitude, conditions.ripple_phases(c, 0, 0))
          - conditions.ripple_height(xy - [0, e], k, amplitude, conditions.ripple_phases(c, 0, 0))) / (2 * e)
    assert np.sqrt(np.mean(dx**2 + dy**2)) == pytest.approx(conditions.ripple_slope(k, amplitude), rel=0.1)
    # the surface's gradient (what a photo's refraction turns on) is the height's (central differences:
    # their error ~ e^2 |k|^3 a, under 1e-7 here)
    grad = conditions.ripple_gradient(xy, k, amplitude, conditions.ripple_phases(c, 0, 0))
    np.testing.assert_allclose(grad, np.stack([dx, dy], -1), atol=1e-6)


def test_every_photo_its_own_surface_and_a_rerun_the_same():
    c = preset("small-field").conditions
    a, b = conditions.ripple_phases(c, 0, 3), conditions.ripple_phases(c, 0, 4)
    assert not np.allclose(a, b)
    np.testing.assert_array_equal(a, conditions.ripple_phases(c, 0, 3))  # same numpy call: bit-equal
    assert not np.allclose(conditions.ripple_phases(c, 1, 3), a)  # another scene seed, other ripples
    k0, _ = conditions.ripple_waves(c, 0)
    np.testing.assert_array_equal(k0, conditions.ripple_waves(c, 0)[0])


def test_rippled_mesh_fades_into_the_flat_frame():
    spec = preset("smoke-field")
    verts, tris, weight = conditions.water_surface(spec, spec.bed.size, FAR)
    assert len(verts) == len(weight) and tris.max() < len(verts)
    edge = (np.isclose(np.abs(verts[:, :2]).max(1), spec.bed.size / 2)
            | (np.abs(verts[:, :2]).max(1) > spec.bed.size))
    assert (weight[edge] == 0).all() and weight.max() == 1.0
    inside = np.abs(verts[:, :2]).max(1) < spec.bed.size / 2 - spec.bed.taper
    assert (weight[inside] == 1).all()
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    normal_z = np.cross(b - a, c - a)[:, 2]
    assert (normal_z > 0).all()  # every triangle faces up, the frame's included
    area = 0.5 * normal_z.sum()
    assert area == pytest.approx((2 * FAR) ** 2, rel=1e-9)  # no hole, no overlap


def test_water_body_is_a_closed_box_below_the_ripples():
    spec = preset("smoke-field")
    verts, tris = conditions.water_body(spec, -5.0, 100.0)
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6  # > 0: outward faces
    top = spec.level - 4 * spec.conditions.ripple_amplitude - 0.001
    assert volume == pytest.approx(200.0 * 200.0 * (top + 5.0), rel=1e-9)
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    _, count = np.unique(edges, axis=0, return_counts=True)
    assert (count == 2).all()  # watertight: each edge shared by two faces


def test_targets_sit_on_dry_gentle_ground_and_show_a_checker():
    spec = preset("small-field")
    c, bed = spec.conditions, make_bed(spec)
    _, banks = ground_truth(spec, bed, flight.eval_region(spec), 0.05)
    centres = conditions.place_targets(c, lambda xy: height_at(bed, xy), banks, spec.level, spec.seed)
    assert centres.shape == (c.targets, 3)
    ground = height_at(bed, centres[:, :2])
    assert ((ground > spec.level + 0.03).all()
            and (centres[:, 2] >= ground + conditions.TARGET_LIFT - 1e-12).all())
    gaps = np.linalg.norm(centres[:, None, :2] - centres[None, :, :2], axis=-1) + np.eye(len(centres)) * 1e9
    assert gaps.min() > 2 * c.target_size  # spread apart, never overlapping
    meshes = conditions.target_meshes(c, centres)
    for verts, _ in meshes.values():
        assert len(verts) == 8 * c.targets  # two squares of each colour per target
    # The black squares lie on the (-x, -y) / (+x, +y) diagonal, the white on the other one.
    black = meshes["black"][0].reshape(c.targets, 2, 4, 3).mean(2) - centres[:, None]
    white = meshes["white"][0].reshape(c.targets, 2, 4, 3).mean(2) - centres[:, None]
    assert (np.sign(black[..., 0]) == np.sign(black[..., 1])).all()
    assert (np.sign(white[..., 0]) == -np.sign(white[..., 1])).all()
    assert np.allclose(black[..., 2], 0) and np.allclose(white[..., 2], 0)


@pytest.mark.parametrize("name", IDEAL)
def test_ideal_presets_carry_no_trace_of_the_conditions(name, tmp_path):
    spec = preset(name)
    assert "conditions" not in spec.to_dict()
    cam = Camera.look_at([0, 0, 5], [0, 0, 0], 64, 64, 70.0)
    job = render_job(spec, tmp_path, cam, [])
    assert job.ripples is None and job.glossy_bounces == 0
    assert not any(getattr(o.material, "reflect", False) or o.wet_only for o in job.objects)
    assert [o.name for o in job.objects] == ["bed", "floor"] + (["water"] if spec.water else [])
    if name == "smoke":
        geo = scene_geometry(spec, make_bed(spec))
        assert set(geo) == {"bed_verts", "bed_tris", "bed_uv", "floor_verts", "floor_tris", "floor_uv",
                            "water_verts", "water_tris"}
        assert len(geo["water_verts"]) == 4
        poses = flight.plan(spec)
        assert "conditions" not in scene_metadata(spec, poses, np.zeros((4, 3)) + [0, 0, -1])


def test_field_preset_job_and_record(tmp_path):
    spec = preset("smoke-field")
    cam = Camera.look_at([0, 0, 5], [0, 0, 0], 64, 64, 70.0)
    job = render_job(spec, tmp_path, cam, [])
    names = [o.name for o in job.objects]
    assert names == ["bed", "floor", "water", "volume", "target_black", "target_white"]
    assert job.objects[2].material.reflect and job.objects[3].wet_only
    assert job.glossy_bounces == 1 and len(job.ripples.k) == spec.conditions.ripple_waves
    absorption = job.objects[3].material.absorption
    assert absorption[0] > absorption[1]  # red is absorbed most
    poses = flight.plan(spec)
    record = scene_metadata(spec, poses, np.zeros((4, 3)) + [0, 0, -1])["conditions"]
    assert record["absorption_per_m"] == list(spec.conditions.absorption)
    assert 0 < record["ripple_rms_slope_deg"] < 10
    assert SceneSpec.from_dict(spec.to_dict()) == spec


def test_one_effect_at_a_time_from_an_ideal_preset():
    turbid = with_conditions(preset("small"), turbidity=1.0)
    c = turbid.conditions
    assert c.turbid and not c.reflection and c.ripple_amplitude == 0 and c.targets == 0
    assert c.absorption == CLEAR_RIVER.absorption
    assert with_conditions(preset("small"), turbidity=0.0).conditions is None  # nothing on: the ideal spec
    assert with_conditions(preset("small"), reflection=True).conditions.reflection
    dry = with_conditions(preset("small-field"), turbidity=0.0, reflection=False, ripple_amplitude=0.0)
    assert not dry.conditions.turbid and dry.conditions.targets == CLEAR_RIVER.targets  # targets stay
    doubled = with_conditions(preset("small-field"), turbidity=2.0)
    np.testing.assert_allclose(conditions.attenuation(doubled.conditions)[0],
                               2 * np.array(CLEAR_RIVER.absorption))


@pytest.mark.parametrize("change, message", [
    ({"ripple_amplitude": -0.01}, ">= 0"),
    ({"ripple_cell": 0.1}, "a sixth of the shortest ripple"),
    ({"ripple_wavelengths": (0.5, 0.2)}, "shortest <= longest"),
])
def test_bad_conditions_are_refused(change, message):
    spec = preset("small-field")
    with pytest.raises(SpecError, match=message):
        validate(replace(spec, conditions=replace(spec.conditions, **change)))
    with pytest.raises(SpecError, match="need water"):
        validate(replace(spec, water=None))
    with pytest.raises(SpecError, match="need a reach"):
        validate(replace(preset("small-bed"), conditions=CLEAR_RIVER))
    with pytest.raises(SpecError, match="sun elevation"):
        validate(replace(spec, light=replace(spec.light, sun_elevation=-5.0)))
    with pytest.raises(SpecError, match="azimuth finite"):
        validate(replace(spec, light=replace(spec.light, sun_azimuth=math.inf)))
    with pytest.raises(SpecError, match="finite and >= 0"):  # NaN passes every comparison
        validate(with_conditions(spec, ripple_amplitude=math.nan))


def test_the_secchi_like_depth_from_the_beams_down_and_up():
    """Clear water: no depth; the sun overhead: the path down equals the path up, so the contrast share
    exp(-2 c z) is reached at ln(1 / share) / 2c; a sun 30 degrees up doubles the path down (the renderer's
    straight shadow ray); turbidity scales the depth down as 1 / T."""
    share = conditions.CONTRAST_SHARE
    c = np.array([0.0, 0.5, 2.0])
    z = conditions.secchi_depth(c, 90.0)
    assert np.isinf(z[0])
    np.testing.assert_allclose(z[1:], math.log(1 / share) / (2 * c[1:]))
    np.testing.assert_allclose(np.exp(-c[1] * z[1] * 2), share)
    np.testing.assert_allclose(conditions.secchi_depth(c, 30.0)[1], math.log(1 / share) / (0.5 * 3))
    field = conditions.figures(preset("small-field"))
    murkier = conditions.figures(with_conditions(preset("small-field"), turbidity=2.0))
    np.testing.assert_allclose(murkier["secchi_like_depth_m"], np.array(field["secchi_like_depth_m"]) / 2)
    assert conditions.figures(with_conditions(preset("small-field"), turbidity=0.0))["secchi_like_depth_m"] \
        == [None, None, None]
