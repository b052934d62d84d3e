import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.motion.trajectory import quat_from_rotvec, quat_to_matrix
from twinfocus.scene import (
    DEFAULT_SPACING_M,
    MATERIALS,
    Clutter,
    Occluder,
    PlanarObject,
    PointCloudObject,
    Scene,
    card,
    disc,
    from_points,
    letter,
    letter_mask,
    paper_scene,
    scatterer_spacing_m,
)


def test_materials_table():
    assert MATERIALS["metal"].reflectivity == 1.0
    assert 0 < MATERIALS["plastic"].reflectivity < MATERIALS["wood"].reflectivity < 1.0
    assert np.isinf(MATERIALS["metal"].two_way_attenuation_db)
    for name in ("polyester", "cloth", "paper", "plastic"):
        assert 0 < MATERIALS[name].two_way_attenuation_db < 20
    with pytest.raises(TwinFocusError, match="unknown material 'gold'"):
        letter("A", material="gold")


@pytest.mark.parametrize("char,height", [("A", 0.127), ("F", 0.127), ("g", 0.05), ("8", 0.2), ("K", 0.0762)])
def test_letter_mask_height_and_stroke(char, height):
    pixel = height / 300
    m = letter_mask(char, height, pixel)
    assert m.dtype == bool and m.any()
    # Cropped to the ink: its height is the requested one to within a pixel or two.
    assert abs(m.shape[0] * pixel - height) <= 2 * pixel
    assert m[0].any() and m[-1].any() and m[:, 0].any() and m[:, -1].any()


def test_letter_stroke_width_and_font_width():
    h = 0.127
    pixel = h / 400
    i_mask = letter_mask("I", h, pixel, stroke_m=0.015)
    widths = i_mask[50:-50].sum(axis=1) * pixel
    np.testing.assert_allclose(widths, 0.015, atol=2 * pixel)
    assert letter_mask("W", h, pixel).shape[1] > 2 * letter_mask("I", h, pixel).shape[1]
    narrow = letter_mask("A", h, pixel, width_scale=0.5).shape[1]
    wide = letter_mask("A", h, pixel, width_scale=1.0).shape[1]
    assert narrow < wide


@pytest.mark.parametrize("bad", ["", "AB", " ", "\u00e9", 7])
def test_letter_rejects_unknown_characters(bad):
    with pytest.raises(TwinFocusError, match="character"):
        letter(bad)


def test_letter_bad_font_and_sizes():
    with pytest.raises(TwinFocusError, match="font"):
        letter("A", font="comic")
    with pytest.raises(TwinFocusError, match="height_m"):
        letter("A", height_m=-1)
    with pytest.raises(TwinFocusError, match="stroke_m"):
        letter("A", height_m=0.1, stroke_m=0.2)


def test_planar_scatterers_lie_on_the_mask():
    obj = letter("R", 0.127, centre_m=(0.01, -0.02, 0.7))
    pts, amp = obj.scatterers(DEFAULT_SPACING_M, rng=0)
    np.testing.assert_allclose(pts[:, 2], 0.7)
    h, w = obj.mask.shape
    col = np.floor((pts[:, 0] - 0.01) / obj.pixel_m + w / 2).astype(int)
    row = np.floor((pts[:, 1] + 0.02) / obj.pixel_m + h / 2).astype(int)
    assert obj.mask[row, col].all()
    # One point per cell: count ~ inked area / spacing^2.
    area = obj.mask.sum() * obj.pixel_m**2
    assert len(pts) == pytest.approx(area / DEFAULT_SPACING_M**2, rel=0.05)
    np.testing.assert_allclose(np.abs(amp), 1.0)
    assert np.std(np.angle(amp)) > 1.0  # random phases
    _, real = obj.scatterers(DEFAULT_SPACING_M, rng=0, speckle=False)
    np.testing.assert_array_equal(real, 1.0)
    wood = letter("R", material="wood")
    assert np.abs(wood.scatterers(rng=0)[1]).max() == pytest.approx(MATERIALS["wood"].reflectivity)


def test_rotation_moves_corners_and_points():
    r = quat_to_matrix(quat_from_rotvec([0.0, 0.0, np.pi / 2]))  # u -> +y, v -> -x
    obj = card(centre_m=(0.0, 0.0, 0.5), rotation=r)
    c = obj.corners_m()
    w, h = obj.size_m
    np.testing.assert_allclose(c[0], [h / 2, -w / 2, 0.5], atol=1e-12)
    np.testing.assert_allclose(obj.normal_m, [0, 0, -1], atol=1e-12)
    pts, _ = obj.scatterers(1e-3, rng=0)
    assert np.abs(pts[:, 0]).max() <= h / 2 + 1e-9 and np.abs(pts[:, 1]).max() <= w / 2 + 1e-9
    tilt = quat_to_matrix(quat_from_rotvec([0.0, np.pi / 4, 0.0]))
    tilted = card(centre_m=(0.0, 0.0, 0.5), rotation=tilt)
    pts, _ = tilted.scatterers(1e-3, rng=0)
    # Points stay on the tilted plane through the centre.
    np.testing.assert_allclose((pts - [0, 0, 0.5]) @ tilted.rotation[:, 2], 0.0, atol=1e-12)
    with pytest.raises(TwinFocusError, match="rotation"):
        card(rotation=np.diag([1.0, 1.0, -1.0]))


def test_card_disc_sizes():
    c = card()
    assert c.size_m == pytest.approx((0.0856, 0.054), abs=0.5e-3)
    d = disc(0.03, pixel_m=0.25e-3)
    assert d.mask.sum() * d.pixel_m**2 == pytest.approx(np.pi * 0.03**2, rel=0.01)


def test_paper_scene_layout_fits_design_rois():
    scene = paper_scene()
    ref, tgt = scene.object("reference"), scene.object("target")
    for obj, (x0, x1) in ((ref, (-0.15, 0.0)), (tgt, (0.02, 0.13))):
        c = obj.corners_m()
        assert c[:, 0].min() >= x0 and c[:, 0].max() <= x1
        assert c[:, 1].min() >= -0.11 and c[:, 1].max() <= 0.12
        np.testing.assert_allclose(c[:, 2], 0.6)
        n = len(obj.scatterers(rng=0)[0])
        assert 1000 <= n <= 3000, n
    u_ref = ref.centre_m / np.linalg.norm(ref.centre_m)
    u_tgt = tgt.centre_m / np.linalg.norm(tgt.centre_m)
    assert np.degrees(np.arccos(u_ref @ u_tgt)) == pytest.approx(10.0, abs=1e-9)
    near = paper_scene(distance_m=0.4, reference_distance_m=0.76, separation_deg=20)
    r, t = near.object("reference").centre_m, near.object("target").centre_m
    assert np.degrees(np.arctan2(t[0], t[2]) - np.arctan2(r[0], r[2])) == pytest.approx(20.0)


def test_default_spacing_from_resolution():
    assert scatterer_spacing_m(0.6) == pytest.approx(0.5 * 3.9e-3 * 0.6 / (2 * 0.49))
    assert DEFAULT_SPACING_M == pytest.approx(scatterer_spacing_m(0.6), rel=0.01)


def test_occluder_attenuates_only_behind_it():
    occ = Occluder((0.0, 0.0, 0.5), (0.1, 0.1), material="paper")
    pts = np.array([[0.0, 0.0, 0.8], [0.0, 0.0, 0.4], [0.3, 0.0, 0.8], [0.04, -0.04, 0.9]])
    scene = Scene([from_points(pts, np.ones(4))], [occ])
    p, a = scene.scatterers(rng=0)
    factor = 10 ** (-MATERIALS["paper"].two_way_attenuation_db / 20)
    np.testing.assert_allclose(np.abs(a), [factor, 1.0, 1.0, factor])
    np.testing.assert_array_equal(p, pts)
    custom = Scene([from_points(pts, np.ones(4))], [Occluder((0, 0, 0.5), (0.1, 0.1), attenuation_db=20.0)])
    np.testing.assert_allclose(np.abs(custom.scatterers(rng=0)[1]), [0.1, 1.0, 1.0, 0.1])
    # An opaque sheet removes what it hides.
    metal = Scene([from_points(pts, np.ones(4))], [Occluder((0, 0, 0.5), (0.1, 0.1), material="metal")])
    p, a = metal.scatterers(rng=0)
    np.testing.assert_array_equal(p, pts[[1, 2]])


def test_paper_scene_occluder_covers_target_not_reference():
    scene = paper_scene(occluder="polyester")
    p, a, lab = scene.scatterers(rng=0, return_labels=True)
    factor = 10 ** (-MATERIALS["polyester"].two_way_attenuation_db / 20)
    np.testing.assert_allclose(np.abs(a[lab == 0]), 1.0)
    np.testing.assert_allclose(np.abs(a[lab == 1]), factor)


def test_select_keeps_the_same_scatterers():
    scene = paper_scene(clutter=True)
    p_all, a_all, lab = scene.scatterers(rng=11, return_labels=True)
    p_ref, a_ref = scene.select("reference").scatterers(rng=11)
    np.testing.assert_array_equal(p_ref, p_all[lab == 0])
    np.testing.assert_array_equal(a_ref, a_all[lab == 0])
    p_other, _ = scene.select("reference").scatterers(rng=12)
    assert p_other.shape != p_ref.shape or not np.array_equal(p_other, p_ref)
    with pytest.raises(TwinFocusError, match="no object named"):
        scene.select("nothing")


def test_clutter_room():
    c = Clutter.room(0.6, n_points=200, n_strong=3)
    p, a = c.scatterers(rng=0)
    assert p.shape == (203, 3)
    assert np.all(p >= c.volume_min_m) and np.all(p <= c.volume_max_m)
    np.testing.assert_allclose(np.abs(a[:200]), c.amplitude)
    np.testing.assert_allclose(np.abs(a[200:]), c.strong_amplitude)


def test_bad_scene_inputs():
    with pytest.raises(TwinFocusError, match="empty"):
        Scene().scatterers()
    with pytest.raises(TwinFocusError, match="NaN"):
        from_points([[0, 0, np.nan]])
    with pytest.raises(TwinFocusError, match=r"\(N, 3\)"):
        from_points(np.zeros((4, 2)))
    with pytest.raises(TwinFocusError, match="amplitudes"):
        from_points(np.zeros((4, 3)), np.ones(3))
    with pytest.raises(TwinFocusError, match="mask is empty"):
        PlanarObject(np.zeros((4, 4), bool), 1e-3, (0, 0, 1))
    with pytest.raises(TwinFocusError, match="boolean"):
        PlanarObject(np.ones((4, 4)), 1e-3, (0, 0, 1))
    with pytest.raises(TwinFocusError, match="centre_m"):
        PlanarObject(np.ones((4, 4), bool), 1e-3, (0, 0))
    with pytest.raises(TwinFocusError, match="size_m"):
        Occluder((0, 0, 1), (0.1, -0.1))
    with pytest.raises(TwinFocusError, match="PlanarObject or PointCloudObject"):
        Scene(["A"])


def test_point_cloud_thinning():
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 0.01, (5000, 3))
    obj = PointCloudObject(pts, material="plastic")
    p, a = obj.scatterers(spacing_m=0.005, rng=0)
    assert len(p) == 8  # one per occupied 5 mm cube of a 1 cm cube
    np.testing.assert_allclose(np.abs(a), MATERIALS["plastic"].reflectivity)
    p_all, _ = obj.scatterers(rng=0)
    np.testing.assert_array_equal(p_all, pts)


# --- field-like objects: rough surfaces, non-planar shapes -----------------------------------


@pytest.mark.parametrize("deg,spread", [(90.0, 0.3), (30.0, 0.1)])
def test_rough_surface_phase_and_amplitude_spread(deg, spread):
    from dataclasses import replace

    obj = replace(card(), roughness_deg=deg, amplitude_spread=spread)
    _, a = obj.scatterers(1e-3, 5, speckle=True)  # roughness overrides scene-wide speckle
    ph = np.rad2deg(np.angle(a))
    # Uniform in +-deg: bounded, sd deg / sqrt(3), mean 0.
    assert np.abs(ph).max() <= deg + 1e-9 and np.abs(ph).max() > 0.98 * deg
    assert abs(ph.std() - deg / np.sqrt(3)) < 0.03 * deg
    assert abs(ph.mean()) < 0.05 * deg
    mag = np.abs(a) / obj.reflectivity
    assert mag.min() >= 1 - spread - 1e-12 and mag.max() <= 1 + spread + 1e-12
    assert abs(mag.std() - spread / np.sqrt(3)) < 0.03 * spread


def test_rough_surface_seeded_per_object_in_scene():
    from dataclasses import replace

    sc = paper_scene()
    sc.objects[0] = replace(sc.objects[0], roughness_deg=90.0, amplitude_spread=0.3)
    p1, a1, l1 = sc.scatterers(rng=3, return_labels=True)
    p2, a2 = sc.select("reference").scatterers(rng=3)
    np.testing.assert_array_equal(a1[l1 == 0], a2)
    with pytest.raises(TwinFocusError, match="roughness_deg"):
        replace(sc.objects[0], roughness_deg=200.0)
    with pytest.raises(TwinFocusError, match="amplitude_spread"):
        replace(sc.objects[0], amplitude_spread=1.0)


def test_cylinder_section_points_lie_on_the_cylinder():
    from twinfocus.scene import cylinder_section

    r = 0.15
    obj = cylinder_section(card((0.0, 0.0, 0.6)), r)
    pts, _ = obj.scatterers(1e-3, 0)
    # Axis along y at x = 0, z = 0.6 + r; the card's face is the near side of the cylinder.
    dist = np.hypot(pts[:, 0], pts[:, 2] - (0.6 + r))
    # depth_m is per mask column: a point is off by at most half a pixel x the surface's slope
    # (u / sqrt(R^2 - u^2) <= 0.3 at the card's edge).
    np.testing.assert_allclose(dist, r, atol=obj.pixel_m / 2 * 0.3)
    assert pts[:, 2].min() >= 0.6 - 1e-12 and pts[:, 2].max() > 0.6 + 0.005
    with pytest.raises(TwinFocusError, match="radius"):
        cylinder_section(card(), 0.01)


def test_bent_plate_two_planes_at_the_bend_angle():
    from twinfocus.scene import bent_plate, shaped

    obj = bent_plate(card((0.0, 0.0, 0.6)), 40.0)
    pts = obj.surface_points(1e-3)
    for side in (pts[:, 0] > 0.002, pts[:, 0] < -0.002):
        q = pts[side]
        slope = np.polyfit(np.abs(q[:, 0]), q[:, 2] - 0.6, 1)[0]
        assert abs(np.rad2deg(np.arctan(slope)) - 20.0) < 0.5
    assert shaped(card(), "plane").depth_m is None
    with pytest.raises(TwinFocusError, match="unknown shape"):
        shaped(card(), "sphere")
