"""world/maps/pairs.py: two epochs on one grid (georeferences honoured: sub-pixel offsets, anisotropic pixels,
mixed ground samplings), the residual misregistration measured, refused beyond the bound, corrected on request."""

from __future__ import annotations

import math

import numpy as np
import pytest
from shared_helpers import SHARED_DATA
from synthetic_pairs import write_pair

from aerial_loc_env.errors import MapError
from aerial_loc_env.world.maps import pairs


@pytest.mark.parametrize("shift_m", [(0.0, 0.0), (0.35, -0.6), (-1.1, 0.45)])
def test_a_known_shift_is_measured_within_a_quarter_pixel(tmp_path, shift_m):
    a, b = write_pair(tmp_path, shift_m=shift_m)
    pair = pairs.load_pair(a, b, max_shift_m=None)
    reg = pair.registration
    g = pair.grid.gsd_m
    # UTM's scale at the central meridian: projected metres are 0.9996 ground metres
    east, north = (s * g / 0.5 for s in shift_m)
    assert abs(reg.east_m - east) <= 0.25 * g and abs(reg.north_m - north) <= 0.25 * g, reg.describe()
    assert reg.windows >= 1 and reg.spread_px < 0.25


def test_a_shift_beyond_the_bound_is_refused_naming_it(tmp_path):
    a, b = write_pair(tmp_path, shift_m=(2.0, 0.0))
    with pytest.raises(MapError, match=r"p\.png \(A\) and p\.png \(B\) are misregistered by 2\.0\d m on the "
                                       r"ground, beyond map\.max_shift_m = 1\.5 m: misregistration \+4\.0\d, "
                                       r"[+-]0\.0\d px \(\+2\.0\d m east.*map\.correct_shift = true"):
        pairs.load_pair(a, b)
    assert pairs.load_pair(a, b, max_shift_m=2.5).registration.shift_m == pytest.approx(2.0, abs=0.15)


def test_correct_shift_removes_a_small_constant_shift(tmp_path):
    a, b = write_pair(tmp_path, shift_m=(2.0, -1.0))
    pair = pairs.load_pair(a, b, correct_shift=True)
    reg = pair.registration
    assert reg.corrected == pytest.approx((4.0, 2.0), abs=0.15)
    assert reg.shift_m <= 0.25 * pair.grid.gsd_m, reg.describe()
    assert "after removing a constant shift of +4.0" in pair.surveyed.source


def test_a_sub_pixel_offset_between_the_grids_is_honoured_not_compared_pixel_for_pixel(tmp_path):
    """B's grid starts 0.4 px east and 0.3 px south of A's: its pixels show other ground, and the georeferences say
    so. Resampled onto one grid, the two agree (no misregistration); compared pixel for pixel they would not."""
    a, b = write_pair(tmp_path, b_offset_px=(0.4, 0.3))
    pair = pairs.load_pair(a, b)
    assert pair.grid.own and pair.registration.shift_m <= 0.25 * pair.grid.gsd_m, pair.registration.describe()
    raw = pairs.measure_shift(_png(a), _png(b), None, 0.5)          # pixel for pixel: the offset shows
    assert raw.dx_px == pytest.approx(-0.4, abs=0.15) and raw.dy_px == pytest.approx(-0.3, abs=0.15)


def test_anisotropic_pixels_are_resampled_to_square_ones(tmp_path):
    """A 0.500 x 0.600 m grid for B: the common grid has square pixels (0.5 m, A's), B's extent on it, and the two
    epochs align on it."""
    a, b = write_pair(tmp_path, b_gsd_xy_m=(0.5, 0.6))
    pair = pairs.load_pair(a, b)
    g = pair.grid
    assert not g.own and g.gsd_m == pytest.approx(0.5 / 0.9996, rel=1e-3)
    for om in (pair.surveyed, pair.ground):
        assert om.gsd_x_m == om.gsd_y_m == g.gsd_m
        assert om.width_m == pytest.approx(256.0, rel=0.02)
        assert om.height_m == pytest.approx(256.0, rel=0.02)
    assert pair.registration.shift_m <= 0.25 * g.gsd_m, pair.registration.describe()


def test_mixed_ground_samplings_go_onto_the_finer_grid(tmp_path):
    """A at 0.5 m, B at 0.25 m over the same ground: the grid is B's own (the finer), A is resampled onto it."""
    a, b = write_pair(tmp_path, b_gsd_xy_m=(0.25, 0.25))
    pair = pairs.load_pair(a, b)
    assert pair.grid.own and pair.surveyed.rgb.shape == pair.ground.rgb.shape
    assert pair.surveyed.gsd_x_m == pytest.approx(0.25 / 0.9996, rel=1e-4)
    assert pair.ground.width_px == pytest.approx(1024, abs=2)
    assert pair.registration.shift_m <= 0.25 * pair.grid.gsd_m, pair.registration.describe()
    # B finer than A, the other way round: the grid is then A's sampling, B area-averaged onto it
    a2, b2 = write_pair(tmp_path / "coarse_b", gsd_m=0.25, size_px=1024, b_gsd_xy_m=(0.5, 0.5))
    other = pairs.load_pair(a2, b2)
    assert not other.grid.own and other.grid.gsd_m == pytest.approx(0.25 / 0.9996, rel=1e-3)
    assert other.registration.shift_m <= 0.25 * other.grid.gsd_m, other.registration.describe()


def test_images_without_georeference_take_a_stated_sampling_and_align_by_their_centres(tmp_path):
    a, b = write_pair(tmp_path, world_file=False, shift_m=(0.5, 0.0))
    with pytest.raises(MapError, match=r"no georeference .* no gsd_m"):
        pairs.load_pair(a, b)
    pair = pairs.load_pair(a, b, gsd_m=0.5)
    assert pair.grid.own and pair.grid.gsd_m == 0.5
    assert pair.registration.east_m == pytest.approx(0.5, abs=0.125)


def test_one_georeferenced_and_one_plain_image_cannot_share_a_grid(tmp_path):
    a, _ = write_pair(tmp_path)
    _, b = write_pair(tmp_path / "plain", world_file=False)
    with pytest.raises(MapError, match=r"p\.png has a georeference but p\.png has none"):
        pairs.load_pair(a, b, gsd_m=0.5)


def test_missing_images_and_disjoint_pairs_are_clear_errors(tmp_path):
    a, b = write_pair(tmp_path)
    with pytest.raises(MapError, match=r"image B \(the camera's epoch\) '.*nowhere\.png' does not exist"):
        pairs.load_pair(a, tmp_path / "nowhere.png")
    far = tmp_path / "far"
    from synthetic_pairs import write_image

    write_image(far / "q.png", 256, 256, (0.5, 0.5), offset_px=(4000.0, 0.0))
    with pytest.raises(MapError, match=r"overlap on only 0\.0 x 0\.0 m"):
        pairs.load_pair(a, far / "q.png")


def test_a_folder_of_pairs_lists_a_and_b_namesakes(tmp_path):
    write_pair(tmp_path, "one.png")
    write_pair(tmp_path, "two.png")
    (tmp_path / "A" / "lonely.png").write_bytes(b"")
    found = pairs.pairs_in(tmp_path)
    assert [a.name for a, _ in found] == ["one.png", "two.png"]
    assert all(b.parent.name == "B" for _, b in found)
    with pytest.raises(MapError, match=r"holds A/ .* and B/ .*; B/ is missing"):
        (tmp_path / "only_a" / "A").mkdir(parents=True)
        pairs.pairs_in(tmp_path / "only_a")


def test_the_levir_pairs_load_within_the_bound():
    levir = SHARED_DATA / "pairs" / "levir-cd"
    if not (levir / "A").is_dir():
        pytest.skip(f"real image pairs not available: {levir} (../shared/data/pairs, beside the project)")
    for a, b in pairs.pairs_in(levir)[:2]:
        pair = pairs.load_pair(a, b, gsd_m=0.5)
        assert pair.grid.own and pair.surveyed.rgb.shape == (1024, 1024, 3)
        assert pair.registration.shift_m <= pairs.DEFAULT_MAX_SHIFT_M
        assert math.isfinite(pair.registration.spread_px)


def _png(path):
    import cv2

    return np.ascontiguousarray(cv2.imread(str(path))[..., ::-1])
