"""Edge/line feature model after the second reference: feature map (shadow edges, clutter) and eq. (2)-(4)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from test_dense_models import ALT_M, briefing_standin, observation, orthomap_standin, render_frame

from aerial_loc_env.config import build_config
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl.edges import (
    EdgeModelConfig,
    EdgeOrientationModel,
    FeatureMapConfig,
    build_feature_map,
    cell_orientations,
    light_direction_px,
    orientation_similarity,
)

SUN_AZ_DEG = 225.0   # sun in the south-west: shadows fall to the north-east


def building_scene(sun_az_deg: float = SUN_AZ_DEG, shadow_px: int = 20, seed: int = 0):
    """Gray database with three bright roofs, their cast shadows (dark) and a vegetation patch."""
    g = np.random.default_rng(seed)
    img = np.full((300, 300), 120, np.float32) + g.normal(0, 3, (300, 300)).astype(np.float32)
    roof = np.zeros((300, 300), np.uint8)
    for r0, r1, c0, c1 in ((100, 160, 100, 180), (200, 260, 40, 90), (30, 70, 200, 260)):
        roof[r0:r1, c0:c1] = 1
    light = light_direction_px(sun_az_deg)
    shadow = np.zeros((300, 300), bool)
    for t in np.linspace(0, shadow_px, 4 * shadow_px):
        m = np.float32([[1, 0, t * light[0]], [0, 1, t * light[1]]])
        shadow |= cv2.warpAffine(roof, m, (300, 300), flags=cv2.INTER_NEAREST).astype(bool)
    shadow &= ~roof.astype(bool)
    img[shadow] = 50
    img[roof.astype(bool)] = 200
    crowns = cv2.GaussianBlur(g.standard_normal((60, 60)).astype(np.float32), (0, 0), 1.5) > 0
    img[220:280, 200:260] = np.where(crowns, 160, 70)          # blotchy tree crowns: edges in all directions
    return np.clip(img, 0, 255)


# regions of the scene (rows, cols)
FAR_SHADOW_EDGE = (slice(80, 92), slice(125, 190))      # the north edge of the first roof's shadow (on the ground)
ROOF_WEST_EDGE = (slice(105, 155), slice(97, 104))      # the sunward roof edge
ROOF_SHARED_EDGE = (slice(97, 104), slice(105, 175))    # the roof edge the shadow starts at
VEGETATION = (slice(225, 275), slice(205, 255))


def test_light_direction_points_away_from_the_sun():
    assert light_direction_px(180.0) == pytest.approx([0.0, -1.0], abs=1e-12)   # sun south: light goes north (up)
    assert light_direction_px(90.0) == pytest.approx([-1.0, 0.0], abs=1e-12)    # sun east: light goes west


@pytest.mark.parametrize("illumination", ["parameter", "estimate"])
def test_feature_map_drops_the_shadow_edge_and_keeps_the_roof_edges(illumination):
    img = building_scene()
    cfg = FeatureMapConfig(illumination=illumination,
                           sun_azimuth_deg=SUN_AZ_DEG if illumination == "parameter" else None)
    fm = build_feature_map(img, cfg)
    plain = build_feature_map(img, FeatureMapConfig(illumination="none"))
    assert plain.edges[FAR_SHADOW_EDGE].sum() > 30          # Canny finds the shadow's far edge ...
    assert fm.edges[FAR_SHADOW_EDGE].sum() == 0             # ... and the illumination rule removes it
    assert fm.shadow_edges[FAR_SHADOW_EDGE].sum() > 30
    for region in (ROOF_WEST_EDGE, ROOF_SHARED_EDGE):       # building boundaries stay
        assert fm.edges[region].sum() == plain.edges[region].sum() > 30
    assert fm.sun_azimuth_deg == pytest.approx(SUN_AZ_DEG, abs=20.0)


def test_a_wrong_illumination_direction_removes_nothing_on_the_far_side():
    fm = build_feature_map(building_scene(), FeatureMapConfig(illumination="parameter", sun_azimuth_deg=45.0))
    assert fm.edges[FAR_SHADOW_EDGE].sum() > 30


def test_clutter_mask_covers_vegetation_not_roofs():
    img = building_scene()
    fm = build_feature_map(img, FeatureMapConfig(illumination="none"))
    assert fm.raw_edges[VEGETATION].sum() > 50
    assert fm.clutter[VEGETATION].mean() > 0.3
    assert fm.edges[VEGETATION].sum() < 0.3 * fm.raw_edges[VEGETATION].sum()
    assert fm.clutter[100:160, 100:180].mean() < 0.02


def test_segments_are_rasterized_as_doubled_angle_vectors():
    fm = build_feature_map(building_scene(), FeatureMapConfig(illumination="parameter", sun_azimuth_deg=SUN_AZ_DEG))
    assert len(fm.segments) > 0
    west = fm.orientation[ROOF_WEST_EDGE]                   # a vertical line: theta = 90 deg, 2 theta = 180 deg
    v = west.reshape(-1, 2).sum(axis=0)
    assert math.degrees(math.atan2(v[1], v[0])) % 360 == pytest.approx(180.0, abs=5.0)


def test_orientation_similarity_is_eq_2():
    d = np.radians([0.0, 20.0, 40.0, 90.0])
    eta = orientation_similarity(d)
    assert eta[0] == pytest.approx(1.0 - 1.0 / (1.0 + math.exp(10.0)))
    assert eta[1] == pytest.approx(0.5)
    assert eta[2] < 1e-4 and eta[3] < 1e-12


def test_cell_orientations_average_modulo_180_degrees():
    layer = np.zeros((4, 8, 2), np.float32)
    for theta_deg, cols in ((89.0, slice(0, 2)), (-89.0, slice(2, 4))):   # nearly the same (vertical) line
        layer[:, cols] = (math.cos(math.radians(2 * theta_deg)), math.sin(math.radians(2 * theta_deg)))
    angle2, coverage = cell_orientations(layer, 2, 1)
    assert abs(math.degrees(angle2[0, 0])) == pytest.approx(180.0, abs=1e-3)
    assert coverage[0, 0] == pytest.approx(math.cos(math.radians(2.0)), abs=1e-4)
    assert coverage[0, 1] == 0.0


def city_map(seed: int = 0):
    """Rotated rectangular roofs of many orientations on a mildly noisy ground (an Orthomap stand-in)."""
    g = np.random.default_rng(seed)
    img = np.full((400, 400), 110, np.float32) + g.normal(0, 3, (400, 400)).astype(np.float32)
    for _ in range(70):
        c = g.uniform(20, 380, 2)
        size = g.uniform(14, 40, 2)
        box = cv2.boxPoints(((float(c[0]), float(c[1])), (float(size[0]), float(size[1])), float(g.uniform(0, 180))))
        cv2.fillPoly(img, [np.rint(box).astype(np.int32)], float(g.uniform(170, 230)))
    rgb = np.repeat(np.clip(img, 0, 255)[..., None], 3, axis=2).astype(np.uint8)
    return orthomap_standin(rgb)


def test_edge_model_prefers_the_true_pose_over_rotated_and_distant_ones():
    m = city_map()
    model = EdgeOrientationModel(EdgeModelConfig(map_params={"illumination": "none"}))
    model.reset(briefing_standin(m), np.random.default_rng(0))
    x, y, yaw = 100.0, 100.0, 0.4
    prep = model.prepare(observation(render_frame(m, x, y, yaw), yaw), np.random.default_rng(0))
    assert prep.observed.sum() >= 6
    rotated = [[x, y, yaw + math.radians(d)] for d in (-60, -35, 35, 60)]
    g = np.random.default_rng(1)
    far = np.column_stack([x + g.choice([-1, 1], 30) * g.uniform(15, 40, 30),
                           y + g.choice([-1, 1], 30) * g.uniform(15, 40, 30), np.full(30, yaw)])
    states = np.vstack([[[x, y, yaw]], rotated, far])
    ll = model.log_likelihood(prep, states, ALT_M)
    assert ll.shape == (len(states),) and np.all(np.isfinite(ll))
    assert ll[0] > ll[1:5].max()
    assert ll[0] > np.quantile(ll[5:], 0.9)
    assert model.log_likelihood(prep, np.array([[-500.0, 0.0, 0.0]]), ALT_M)[0] == pytest.approx(
        math.log(model.config.floor))


def test_edge_config_errors_name_the_field():
    with pytest.raises(ConfigError, match="sun_azimuth_deg"):
        build_config(FeatureMapConfig, {"illumination": "parameter"})
    with pytest.raises(ConfigError, match="map_params"):
        build_config(EdgeModelConfig, {"map_params": {"canny_low": 200.0, "canny_high": 100.0}})


def test_edge_pixel_orientation_source_follows_the_edge_direction():
    img = building_scene()
    fm = build_feature_map(img, FeatureMapConfig(illumination="none", orientation_source="edges"))
    v = fm.orientation[ROOF_WEST_EDGE].reshape(-1, 2).sum(axis=0)      # vertical edge: 2 theta = 180 deg
    assert np.hypot(*v) > 30 and math.degrees(math.atan2(v[1], v[0])) % 360 == pytest.approx(180.0, abs=5.0)
